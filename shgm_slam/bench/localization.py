"""The localization benchmark (``shgm-slam bench localization``): the paper's experiments on our worlds.

All three descriptors (semantic histogram, neighbor vector, random walk) and both outlier modes
(``paper`` = Alg. 2 RANSAC over the best candidate per node, as the authors' release; ``robust`` =
maximum clique over the top-k candidates) run side by side on the same graphs:

1. Table II: airsim-like car1-car2 (gravity-aligned, random yaw) and UAV-car1 (random 3D rotation),
   ``runs`` random transforms (and RANSAC / random-walk seeds): time, good matches, success, errors.
   The random walk is also timed with X-view's per-pair walk-map comparison (``xview_baseline``).
2. Fig. 5: synthia-like, graphs of 30 backward-camera frames localized in the whole forward graph;
   precision-recall over the inlier threshold, success rate at recall 0.35, best F1.
3. Table I: per-module time: object extraction per frame (640x192 and 1242x375), descriptors,
   matching, outlier rejection and pose per query.
4. Fig. 8 ablations on synthia-like: connectivity, path length, same-label vs all-label matching,
   removed classes, depth noise and label noise (``sim.corruption`` on the rendered frames).
5. Partial overlap: synthia-like forward and backward sub-maps of 100 frames overlapping 30-70 %, and
   airsim-like car1 halves vs car2.
6. Disjoint: the disjoint scenario's whole graphs and 30-frame windows; every success is false.

Scoring is in ``localization_metrics`` (errors at the query centroid, PR as the paper defines it),
rendering and graph building in ``localization_scenes`` (cached), tables and the PR plot in
``localization_report``. Timing runs with single-threaded BLAS; the machine load is recorded.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.bench.localization_metrics import (
    Localization,
    good_matches,
    mean_std,
    precision_recall,
    random_transform,
    score_match,
    true_transform,
)
from shgm_slam.bench.localization_scenes import (
    RenderedRobot,
    SceneSpec,
    build_graph,
    extract_keyframes,
    load_scene,
)
from shgm_slam.bench.report import write_report
from shgm_slam.bench.xview_baseline import pairwise_walk_similarity, walk_maps
from shgm_slam.config import (
    CandidateMode,
    DescriptorConfig,
    DescriptorKind,
    ExtractionConfig,
    MatchingConfig,
    OutlierMode,
    ShgmConfig,
)
from shgm_slam.descriptors import NodeDescriptors, compute_descriptors, similarity
from shgm_slam.environment import environment
from shgm_slam.errors import SimulationError
from shgm_slam.graph.extraction import ObjectObservations, extract_objects
from shgm_slam.labels import Label
from shgm_slam.matching import match_graphs, select_candidates
from shgm_slam.sim.corruption import CorruptionLevels
from shgm_slam.sim.render import Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario
from shgm_slam.sim.trajectories import RobotKind
from shgm_slam.types import GraphArrays

ProgressFn = Callable[[str], None]
"""Called with a short description of each experiment as it starts."""

UP_AXIS_WORLD = (0.0, 0.0, 1.0)
"""Simulated worlds are z up; gravity-aligned matching uses this axis."""

UAV_MAX_DEPTH_M = 120.0
"""The UAV flies at 44-54 m with a 50 deg oblique camera: the ground lies 45-110 m away."""

UAV_BLOB_SCALE = 0.25
"""UAV objects seen at 2-4x a car's range appear ~4x smaller in area: scale the minimum blob size."""

WINDOW_FRAMES = 30
"""Query graphs of Fig. 5: 30 consecutive backward-camera frames (paper and X-view)."""

SUBMAP_FRAMES = 100
"""Partial-overlap sub-maps: 100 frames (~100 m) per robot."""


class BenchMode(str, Enum):
    """The two matching pipelines compared side by side."""

    PAPER = "paper"  # Alg. 2 ICP-RANSAC over the best candidate per node (authors' release)
    ROBUST = "robust"  # pairwise consistency + maximum clique over the top-k candidates


MODE_OVERRIDES: dict[BenchMode, dict] = {
    BenchMode.PAPER: {"outlier_mode": OutlierMode.RANSAC, "candidate_mode": CandidateMode.BEST,
                      "min_inliers": 18, "max_rmse_m": 5.0},
    BenchMode.ROBUST: {"outlier_mode": OutlierMode.CLIQUE, "candidate_mode": CandidateMode.TOP_K},
}
"""MatchingConfig fields each mode sets; everything else is the configured default (the robust mode).

RANSAC's 10 m inliers (authors' threshold) are a weaker test than the clique's pairwise consistency, so
the paper mode needs its own acceptance: a fit RMSE up to half the inlier threshold and an inlier floor
chosen for zero false successes on the training worlds (seed 1), on top of the verification's likelihood ratio."""


@dataclass
class BenchOptions:
    """What to run.

    Attributes:
        runs: random transforms per Table II / disjoint configuration (paper: 100).
        quick: compact worlds at 320x96, fewer runs, windows and ablation levels (~2 min).
        world_seed: seed of the simulated worlds (defaults were tuned on seed 1; report on seed 0).
        cache_dir: rendered keyframes are cached here and reused.
        resolution: render size of the experiments (Table I adds 1242x375).
        window_stride: frames between the starts of consecutive 30-frame query windows.
        kinds, modes: descriptors and matching modes to compare.
    """

    runs: int = 100
    quick: bool = False
    world_seed: int = 0
    cache_dir: Path = Path("cache/bench")
    resolution: tuple[int, int] = (640, 192)
    window_stride: int = 10
    kinds: tuple[DescriptorKind, ...] = tuple(DescriptorKind)
    modes: tuple[BenchMode, ...] = tuple(BenchMode)
    xview_timing_runs: int = 3
    depth_noise_levels: tuple[float, ...] = (0.05, 0.15)
    depth_scale_errors: tuple[float, ...] = (0.05,)
    label_noise_levels: tuple[float, ...] = (0.1, 0.25)
    large_resolution: tuple[int, int] | None = (1242, 375)
    large_frames: int = 20

    @staticmethod
    def quick_options(**overrides) -> BenchOptions:
        """The ``--quick`` preset: compact worlds, 320x96, 10 runs, one noise level each."""
        base = dict(runs=10, quick=True, resolution=(320, 96), window_stride=10, xview_timing_runs=1,
                    depth_noise_levels=(0.1,), depth_scale_errors=(), label_noise_levels=(0.2,),
                    large_resolution=None)  # fmt: skip
        return BenchOptions(**(base | overrides))


@dataclass
class _Context:
    """Shared state of one benchmark run: options, config and caches of extracted keyframes."""

    options: BenchOptions
    cfg: ShgmConfig
    progress: ProgressFn
    observations: dict[tuple, list[ObjectObservations]] = field(default_factory=dict)
    extraction_ms: dict[str, list[float]] = field(default_factory=dict)

    def scene(self, scenario: str) -> dict[str, RenderedRobot]:
        o = self.options
        spec = SceneSpec(scenario, o.world_seed, o.resolution, o.quick)
        self.progress(f"scene {spec.folder_name} (rendered once into {o.cache_dir})")
        return load_scene(spec, o.cache_dir)

    def extraction(self, robot: RenderedRobot, labels: tuple[int, ...] | None = None) -> ExtractionConfig:
        """The extraction config for a robot kind (fleet values for fields left to ``scene_scale``;
        UAV: longer range, smaller blobs, as this benchmark was tuned)."""
        e = self.cfg.extraction.filled()
        if robot.kind is RobotKind.UAV:
            e = e.model_copy(update={"max_depth_m": max(e.max_depth_m, UAV_MAX_DEPTH_M),
                                     "min_blob_fraction": e.min_blob_fraction * UAV_BLOB_SCALE})
        return e if labels is None else e.model_copy(update={"labels": labels})

    def keyframe_objects(self, key: str, robot: RenderedRobot,
                         corruption: CorruptionLevels | None = None) -> list[ObjectObservations]:
        """Objects of all keyframes of ``robot`` (cached per scene key and corruption; timed)."""
        ck = (key, robot.name, corruption)
        if ck not in self.observations:
            t0 = time.perf_counter()
            self.observations[ck] = extract_keyframes(robot, self.extraction(robot), corruption,
                                                      seed=self.options.world_seed)
            if corruption is None:
                per_frame = 1e3 * (time.perf_counter() - t0) / max(len(robot), 1)
                self.extraction_ms.setdefault(f"{robot.intrinsics.width}x{robot.intrinsics.height}", []).append(
                    per_frame)
        return self.observations[ck]

    def matching(self, mode: BenchMode, gravity_aligned: bool, seed: int, **updates) -> MatchingConfig:
        return self.cfg.matching.model_copy(update={
            **MODE_OVERRIDES[mode], "gravity_aligned": gravity_aligned, "up_axis": UP_AXIS_WORLD, "seed": seed,
            **updates})  # fmt: skip

    def descriptor(self, kind: DescriptorKind, seed: int = 0, **updates) -> DescriptorConfig:
        return self.cfg.descriptor.model_copy(update={"kind": kind, "seed": seed, **updates})


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Limit the OpenBLAS libraries loaded by numpy and scipy to one thread (stable timing on a shared
    machine), restoring their thread counts afterwards; a no-op where the symbols are absent."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    restore = []
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        maps = ""
    for path in sorted(set(re.findall(r"(/\S*openblas\S*\.so\S*)", maps))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for suffix in ("64_", "", "_"):
            setter = getattr(lib, f"scipy_openblas_set_num_threads{suffix}", None)
            getter = getattr(lib, f"scipy_openblas_get_num_threads{suffix}", None)
            if setter is not None and getter is not None:
                getter.restype = ctypes.c_int
                restore.append((setter, int(getter())))
                setter(ctypes.c_int(1))
                break
    try:
        yield
    finally:
        for setter, n in restore:
            setter(ctypes.c_int(n))


# --- shared building blocks ----------------------------------------------------------------------------


def _window_rows(robot: RenderedRobot, frames: int, stride: int, first: int = 0) -> list[np.ndarray]:
    """Keyframe rows of consecutive windows of ``frames`` trajectory frames starting every ``stride``."""
    f = robot.frame_indices
    last = int(f[-1]) if f.size else 0
    starts = range(first, max(last - frames + 2, first + 1), stride)
    return [np.flatnonzero((f >= s) & (f < s + frames)) for s in starts]


def _subgraph(obs: list[ObjectObservations], robot: RenderedRobot, rows: np.ndarray, ctx: _Context,
              labels: tuple[int, ...] | None = None, connectivity_m: float | None = None) -> GraphArrays:
    """The graph of keyframe ``rows`` (optionally keeping only ``labels`` / another connectivity)."""
    picked = [obs[i] for i in rows.tolist()]
    if labels is not None:
        keep = np.asarray(labels)
        picked = [o.subset(np.isin(o.label_ids, keep)) for o in picked]
    gcfg = ctx.cfg.graph if connectivity_m is None else ctx.cfg.graph.model_copy(
        update={"connectivity_m": connectivity_m})
    return build_graph(picked, robot.T_world_cam[rows], gcfg, robot.frame_indices[rows])


def _localize(a: GraphArrays, b: GraphArrays, dcfg: DescriptorConfig, mcfg: MatchingConfig,
              rng: np.random.Generator, full_rotation: bool,
              descriptors_a: NodeDescriptors | None = None) -> tuple[Localization, GraphArrays, np.ndarray]:
    """Move B by a random transform, match, score. Returns the score, moved B and the true T_a_b'."""
    T_moved = random_transform(rng, full_rotation)
    moved = b.transformed(T_moved)
    T_true = true_transform(T_moved)
    result = match_graphs(a, moved, dcfg, mcfg, descriptors_a=descriptors_a)
    return score_match(result, T_true, moved), moved, T_true


def _summary(locs: list[Localization]) -> dict:
    """Success counts, error statistics of accepted matches and timing statistics."""
    succ = [x for x in locs if x.success]
    t_mean, t_std = mean_std([x.trans_err_m for x in succ])
    r_mean, r_std = mean_std([x.rot_err_deg for x in succ])
    total = np.array([x.timings_ms.get("total", 0.0) for x in locs])
    stage = {k: round(float(np.mean([x.timings_ms.get(k, 0.0) for x in locs])), 3)
             for k in ("descriptors", "matching", "ransac", "pose")} if locs else {}
    return {
        "queries": len(locs),
        "successes": len(succ),
        "correct_successes": sum(x.correct for x in succ),
        "false_successes": sum(x.false_success for x in locs),
        "success_rate": round(len(succ) / max(len(locs), 1), 4),
        "trans_err_m": _round_pair(t_mean, t_std),
        "rot_err_deg": _round_pair(r_mean, r_std),
        "inliers_mean": round(float(np.mean([x.num_inliers for x in locs])), 2) if locs else 0.0,
        "total_ms_mean": round(float(total.mean()), 3) if locs else None,
        "total_ms_median": round(float(np.median(total)), 3) if locs else None,
        "total_ms_min": round(float(total.min()), 3) if locs else None,
        "stage_ms_mean": stage,
    }


def _round_pair(mean: float | None, std: float | None) -> list[float] | None:
    return None if mean is None else [round(mean, 3), round(std, 3)]


def _pr_summary(locs: list[Localization]) -> dict:
    pr = precision_recall(np.array([x.num_inliers for x in locs]), np.array([x.correct for x in locs]))
    s = _summary(locs)
    s["pr"] = pr
    accepted = [x for x in locs if x.success]
    s["operating_point"] = {
        "precision": round(sum(x.correct for x in accepted) / len(accepted), 4) if accepted else None,
        "recall": round(sum(x.correct for x in accepted) / max(len(locs), 1), 4),
    }
    return s


# --- 1. Table II ------------------------------------------------------------------------------------


def _xview_timing(a: GraphArrays, b: GraphArrays, dcfg: DescriptorConfig, runs: int) -> dict:
    """Time X-view's per-pair random-walk similarity (walk maps + same-label pair loop) on a and b."""
    walks_ms, sim_ms, max_diff = [], [], 0.0
    for run in range(runs):
        t0 = time.perf_counter()
        maps_a = walk_maps(a, dcfg.num_walks, dcfg.walk_length, run)
        maps_b = walk_maps(b, dcfg.num_walks, dcfg.walk_length, run)
        t1 = time.perf_counter()
        scores = pairwise_walk_similarity(a, b, maps_a, maps_b)
        t2 = time.perf_counter()
        walks_ms.append(1e3 * (t1 - t0))
        sim_ms.append(1e3 * (t2 - t1))
        if run == 0:  # the per-pair scores must equal the matcher's vectorised random-walk scores
            da = compute_descriptors(a, dcfg.model_copy(update={"seed": 0}))
            db = compute_descriptors(b, dcfg.model_copy(update={"seed": 0}))
            diff = abs(scores - similarity(da, db))
            max_diff = float(diff.max()) if diff.nnz else 0.0
    return {"walks_ms": round(float(np.mean(walks_ms)), 2), "similarity_ms": round(float(np.mean(sim_ms)), 2),
            "runs": runs, "max_score_difference_vs_vectorised": max_diff}


def table2(ctx: _Context) -> list[dict]:
    """Table II: whole-graph matching of car1-car2 and UAV-car1 under random transforms."""
    scene = ctx.scene("airsim-like")
    graphs = {}
    for name, robot in scene.items():
        graphs[name] = _subgraph(ctx.keyframe_objects("airsim", robot), robot, np.arange(len(robot)), ctx)
    rows = []
    pairs = (("car1", "car2", False, "car-car"), ("uav", "car1", True, "uav-car"))
    for name_a, name_b, full, label in pairs:
        a, b = graphs[name_a], graphs[name_b]
        for kind in ctx.options.kinds:
            for mode in ctx.options.modes:
                ctx.progress(f"Table II {label}: {kind.value}, {mode.value} ({ctx.options.runs} runs)")
                locs, goods, cands = [], [], []
                for run in range(ctx.options.runs):
                    rng = np.random.default_rng([ctx.options.world_seed, run, 2])
                    dcfg, mcfg = ctx.descriptor(kind, run), ctx.matching(mode, not full, run)
                    loc, moved, T_true = _localize(a, b, dcfg, mcfg, rng, full)
                    locs.append(loc)
                    # good matches (paper): the best candidate of every node of B within 10 m of the truth
                    scores = similarity(compute_descriptors(a, dcfg), compute_descriptors(moved, dcfg))
                    best = select_candidates(scores, CandidateMode.BEST, mcfg.score_threshold)
                    goods.append(good_matches(a, moved, best.rows_a, best.rows_b, T_true))
                    cands.append(len(best))
                row = {"pair": label, "robot_a": name_a, "robot_b": name_b, "nodes_a": len(a), "nodes_b": len(b),
                       "edges_a": a.num_edges, "edges_b": b.num_edges, "descriptor": kind.value,
                       "mode": mode.value, "good_matches": round(float(np.mean(goods)), 1),
                       "best_candidates": round(float(np.mean(cands)), 1),
                       "good_match_rate": round(float(np.sum(goods) / max(np.sum(cands), 1)), 4),
                       **_summary(locs)}  # fmt: skip
                st = row["stage_ms_mean"]
                row["matching_ms_mean"] = round(st.get("descriptors", 0.0) + st.get("matching", 0.0), 3)
                if kind is DescriptorKind.RANDOM_WALK and mode is ctx.options.modes[0]:
                    ctx.progress(f"Table II {label}: X-view per-pair random-walk timing")
                    x = _xview_timing(a, b, ctx.descriptor(kind), ctx.options.xview_timing_runs)
                    rest = row["total_ms_mean"] - row["matching_ms_mean"]
                    x["end_to_end_ms"] = round(x["walks_ms"] + x["similarity_ms"] + rest, 2)
                    row["xview_per_pair"] = x
                rows.append(row)
    return rows


# --- 2. Fig. 5 and 4. ablations on synthia-like ----------------------------------------------------


@dataclass
class _Synthia:
    forward: RenderedRobot
    backward: RenderedRobot
    windows: list[np.ndarray]


def _synthia_queries(ctx: _Context, data: _Synthia, kind: DescriptorKind, mode: BenchMode, *,
                     corruption: CorruptionLevels | None = None, labels: tuple[int, ...] | None = None,
                     connectivity_m: float | None = None, descriptor_updates: dict | None = None,
                     matching_updates: dict | None = None) -> list[Localization]:
    """Localize every 30-frame backward window in the whole forward graph (one variant)."""
    key = "synthia"
    obs_f = ctx.keyframe_objects(key, data.forward, corruption)
    obs_b = ctx.keyframe_objects(key, data.backward, corruption)
    a = _subgraph(obs_f, data.forward, np.arange(len(data.forward)), ctx, labels, connectivity_m)
    dcfg = ctx.descriptor(kind, 0, **(descriptor_updates or {}))
    desc_a = compute_descriptors(a, dcfg)
    locs = []
    for q, rows in enumerate(data.windows):
        b = _subgraph(obs_b, data.backward, rows, ctx, labels, connectivity_m)
        rng = np.random.default_rng([ctx.options.world_seed, q, 5])
        mcfg = ctx.matching(mode, True, q, **(matching_updates or {}))
        if len(b) == 0:
            locs.append(Localization(False, False, np.inf, np.inf, 0, 0, {}))
            continue
        loc, _, _ = _localize(a, b, dcfg, mcfg, rng, False, descriptors_a=desc_a)
        locs.append(loc)
    return locs


def _synthia_data(ctx: _Context) -> _Synthia:
    scene = ctx.scene("synthia-like")
    fwd, bwd = scene["forward"], scene["backward"]
    return _Synthia(fwd, bwd, _window_rows(bwd, WINDOW_FRAMES, ctx.options.window_stride))


def figure5(ctx: _Context, data: _Synthia) -> list[dict]:
    """Fig. 5: PR of every descriptor x mode on the synthia-like forward/backward views."""
    obs_f, obs_b = ctx.keyframe_objects("synthia", data.forward), ctx.keyframe_objects("synthia", data.backward)
    nodes_a = len(_subgraph(obs_f, data.forward, np.arange(len(data.forward)), ctx))
    nodes_b = float(np.mean([len(_subgraph(obs_b, data.backward, w, ctx)) for w in data.windows]))
    rows = []
    for kind in ctx.options.kinds:
        for mode in ctx.options.modes:
            ctx.progress(f"Fig. 5: {kind.value}, {mode.value} ({len(data.windows)} query windows)")
            locs = _synthia_queries(ctx, data, kind, mode)
            rows.append({"descriptor": kind.value, "mode": mode.value, "nodes_a": nodes_a,
                         "query_nodes_mean": round(nodes_b, 1), **_pr_summary(locs)})
    return rows


def _ablation_variants(o: BenchOptions) -> list[tuple[str, str, dict]]:
    """(group, variant, keyword arguments of ``_synthia_queries``) of the Fig. 8 ablations."""
    v: list[tuple[str, str, dict]] = [("connectivity", f"{c:g} m", {"connectivity_m": c}) for c in (5.0, 10.0, 15.0)]
    v += [("path length", str(n), {"descriptor_updates": {"path_length": n}}) for n in (2, 3, 4)]
    v += [("label matching", "same label", {}), ("label matching", "all labels",
                                                  {"matching_updates": {"same_label_only": False}})]
    default = ExtractionConfig().labels
    for name, drop in (("no building", (Label.BUILDING,)), ("no road", (Label.ROAD,)),
                       ("no building, no road", (Label.BUILDING, Label.ROAD))):
        v.append(("classes", name, {"labels": tuple(x for x in default if x not in drop)}))
    v.append(("classes", "all classes", {}))
    v.append(("depth noise", "none", {}))
    v += [("depth noise", f"{100 * d:g} % (correlated)", {"corruption": CorruptionLevels.from_levels(depth_noise=d)})
          for d in o.depth_noise_levels]
    v += [("depth noise", f"scale {100 * s:+g} %", {"corruption": CorruptionLevels(depth_scale_error=s)})
          for s in o.depth_scale_errors]
    v.append(("label noise", "none", {}))
    v += [("label noise", f"{100 * p:g} % segments, {round(10 * p)} px boundaries",
           {"corruption": CorruptionLevels.from_levels(label_noise=p)}) for p in o.label_noise_levels]
    return v


def ablations(ctx: _Context, data: _Synthia, baseline: dict[str, list[dict]]) -> list[dict]:
    """Fig. 8: the histogram descriptor under parameter and input-quality variations, both modes.

    Variants equal to the defaults reuse the Fig. 5 results (``baseline`` rows by mode).
    """
    rows = []
    for group, variant, kwargs in _ablation_variants(ctx.options):
        for mode in ctx.options.modes:
            is_default = not kwargs or kwargs == {"connectivity_m": ctx.cfg.graph.connectivity_m} or kwargs == {
                "descriptor_updates": {"path_length": ctx.cfg.descriptor.path_length}}
            if is_default and mode.value in baseline:
                summary = baseline[mode.value]
            else:
                ctx.progress(f"Fig. 8 {group}: {variant}, {mode.value}")
                summary = _pr_summary(_synthia_queries(ctx, data, DescriptorKind.HISTOGRAM, mode, **kwargs))
            rows.append({"group": group, "variant": variant, "mode": mode.value,
                         "default": is_default, **{k: v for k, v in summary.items() if k != "pr"},
                         "precision_at_recall": summary["pr"]["precision_at_recall"],
                         "best_f1": summary["pr"]["best_f1"], "max_recall": summary["pr"]["max_recall"]})
    return rows


# --- 3. Table I -------------------------------------------------------------------------------------


def table1(ctx: _Context, fig5_rows: list[dict], data: _Synthia) -> dict:
    """Per-module time: extraction per frame, graph update per keyframe, and per-query matching stages."""
    out: dict = {"extraction_ms_per_frame": {}}
    for res, values in ctx.extraction_ms.items():
        out["extraction_ms_per_frame"][res] = {"mean": round(float(np.mean(values)), 2), "runs": len(values)}
    obs = ctx.keyframe_objects("synthia", data.forward)
    t0 = time.perf_counter()
    _subgraph(obs, data.forward, np.arange(len(data.forward)), ctx)
    out["graph_update_ms_per_keyframe"] = round(1e3 * (time.perf_counter() - t0) / max(len(obs), 1), 3)
    o = ctx.options
    if o.large_resolution is not None:
        ctx.progress(f"Table I: extraction at {o.large_resolution[0]}x{o.large_resolution[1]}")
        out["extraction_ms_per_frame"].update(_large_extraction(ctx, o.large_resolution, o.large_frames))
    out["per_query_ms"] = {
        f"{r['descriptor']}/{r['mode']}": r["stage_ms_mean"] | {"total": r["total_ms_mean"]} for r in fig5_rows}
    return out


def _large_extraction(ctx: _Context, resolution: tuple[int, int], frames: int) -> dict:
    """Extraction ms/frame on synthia-like forward frames rendered at ``resolution`` (not cached)."""
    plan = build_scenario("synthia-like", ScenarioOptions(seed=ctx.options.world_seed))
    traj = plan.robots[0]
    poses = traj.T_world_cam[:: max(1, len(traj) // frames)][:frames]
    K = make_intrinsics(*resolution)
    e = ctx.cfg.extraction.filled()
    times = []
    with Renderer(plan.world, K, threads=2) as renderer:
        for T in poses:
            view = renderer.render(T)
            t0 = time.perf_counter()
            extract_objects(view.depth_m, view.label_ids, K, T, labels=e.labels, max_depth_m=e.max_depth_m,
                            min_depth_m=e.min_depth_m, depth_step_m=e.depth_step_m,
                            min_blob_fraction=e.min_blob_fraction)  # fmt: skip
            times.append(1e3 * (time.perf_counter() - t0))
    return {f"{resolution[0]}x{resolution[1]}": {"mean": round(float(np.mean(times)), 2),
                                                 "std": round(float(np.std(times)), 2), "frames": len(times)}}


# --- 5. partial overlap and 6. disjoint ---------------------------------------------------------------


def overlap_fraction(a: GraphArrays, b: GraphArrays, radius_m: float = 5.0) -> float:
    """Fraction of B's nodes with a same-label node of A within ``radius_m`` (both in the world frame)."""
    if len(b) == 0 or len(a) == 0:
        return 0.0
    near = np.zeros(len(b), dtype=bool)
    for label in np.unique(b.label_ids):
        pa = a.positions_xyz[a.label_ids == label]
        if len(pa):
            sel = b.label_ids == label
            near[sel] = cKDTree(pa).query(b.positions_xyz[sel], distance_upper_bound=radius_m)[0] <= radius_m
    return float(near.mean())


OVERLAP_BINS = ((0.0, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 1.01))


def partial_overlap(ctx: _Context, data: _Synthia) -> list[dict]:
    """Sub-maps seeing only part of each other's area: synthia-like forward vs backward sub-maps offset by
    70-120 frames, and airsim-like car1 halves vs car2; results binned by the measured node overlap."""
    cases: list[tuple[GraphArrays, GraphArrays, bool]] = []
    obs_f = ctx.keyframe_objects("synthia", data.forward)
    obs_b = ctx.keyframe_objects("synthia", data.backward)
    step = 3 * SUBMAP_FRAMES if ctx.options.quick else SUBMAP_FRAMES
    for rows_a in _window_rows(data.forward, SUBMAP_FRAMES, step):
        if rows_a.size == 0:
            continue
        start = int(data.forward.frame_indices[rows_a[0]])
        for offset in (70, 95, 120):
            f = data.backward.frame_indices
            rows_b = np.flatnonzero((f >= start + offset) & (f < start + offset + SUBMAP_FRAMES))
            if rows_b.size:
                cases.append((_subgraph(obs_f, data.forward, rows_a, ctx),
                              _subgraph(obs_b, data.backward, rows_b, ctx), True))
    scene = ctx.scene("airsim-like")
    car1, car2 = scene["car1"], scene["car2"]
    obs1, obs2 = ctx.keyframe_objects("airsim", car1), ctx.keyframe_objects("airsim", car2)
    a = _subgraph(obs2, car2, np.arange(len(car2)), ctx)
    half = len(car1) // 2
    for rows in (np.arange(half), np.arange(half, len(car1))):
        cases.append((a, _subgraph(obs1, car1, rows, ctx), True))
    rows_out = []
    for kind in ctx.options.kinds:
        for mode in ctx.options.modes:
            ctx.progress(f"partial overlap: {kind.value}, {mode.value} ({len(cases)} pairs)")
            records = []
            for i, (a, b, gravity) in enumerate(cases):
                rng = np.random.default_rng([ctx.options.world_seed, i, 7])
                loc, _, _ = _localize(a, b, ctx.descriptor(kind, i), ctx.matching(mode, gravity, i), rng, False)
                records.append((overlap_fraction(a, b), loc))
            for lo, hi in OVERLAP_BINS:
                locs = [loc for ov, loc in records if lo <= ov < hi]
                if locs:
                    rows_out.append({"descriptor": kind.value, "mode": mode.value,
                                     "overlap": f"{100 * lo:.0f}-{min(100 * hi, 100):.0f} %",
                                     **{k: v for k, v in _summary(locs).items() if k != "stage_ms_mean"}})
    return rows_out


def disjoint(ctx: _Context) -> list[dict]:
    """The disjoint scenario: whole graphs (``runs`` transforms) and 30-frame windows of car_b in car_a."""
    scene = ctx.scene("disjoint")
    ra, rb = scene["car_a"], scene["car_b"]
    obs_a, obs_b = ctx.keyframe_objects("disjoint", ra), ctx.keyframe_objects("disjoint", rb)
    a = _subgraph(obs_a, ra, np.arange(len(ra)), ctx)
    b = _subgraph(obs_b, rb, np.arange(len(rb)), ctx)
    windows = [_subgraph(obs_b, rb, rows, ctx) for rows in _window_rows(rb, WINDOW_FRAMES, ctx.options.window_stride)]
    rows = []
    for kind in ctx.options.kinds:
        for mode in ctx.options.modes:
            ctx.progress(f"disjoint: {kind.value}, {mode.value}")
            whole, win = [], []
            for run in range(ctx.options.runs):
                rng = np.random.default_rng([ctx.options.world_seed, run, 11])
                whole.append(_localize(a, b, ctx.descriptor(kind, run), ctx.matching(mode, True, run), rng, False)[0])
            desc_a = compute_descriptors(a, ctx.descriptor(kind, 0))
            for q, w in enumerate(windows):
                if len(w) == 0:
                    continue
                rng = np.random.default_rng([ctx.options.world_seed, q, 13])
                win.append(_localize(a, w, ctx.descriptor(kind, 0), ctx.matching(mode, True, q), rng, False,
                                     descriptors_a=desc_a)[0])
            rows.append({"descriptor": kind.value, "mode": mode.value, "nodes_a": len(a), "nodes_b": len(b),
                         "whole_runs": len(whole), "whole_successes": sum(x.success for x in whole),
                         "windows": len(win), "window_successes": sum(x.success for x in win),
                         "max_inliers": max([x.num_inliers for x in whole + win], default=0)})
    return rows


# --- the whole benchmark ------------------------------------------------------------------------------


def _targets(results: dict) -> dict:
    """The issue's targets, each with the measured value and whether it is met."""
    t2 = results["table2"]
    fig5 = {(r["descriptor"], r["mode"]): r for r in results["figure5"]}

    def row(pair: str, kind: str, mode: str) -> dict | None:
        return next((r for r in t2 if r["pair"] == pair and r["descriptor"] == kind and r["mode"] == mode), None)

    out: dict = {}
    for mode in (m.value for m in BenchMode):
        h = fig5.get(("histogram", mode))
        if h is None:
            continue
        p = h["pr"]["precision_at_recall"]
        out[f"success_at_recall_0.35_{mode}"] = {"value": p, "target": ">= 0.97", "met": p is not None and p >= 0.97}
        kinds = [k for k in ("histogram", "neighbor-vector", "random-walk") if (k, mode) in fig5]
        success = {k: fig5[(k, mode)]["pr"]["precision_at_recall"] or 0.0 for k in kinds}
        errors = {}
        for k in kinds:
            e = [r["trans_err_m"][0] for r in t2 if r["descriptor"] == k and r["mode"] == mode and r["trans_err_m"]]
            errors[k] = round(float(np.mean(e)), 3) if e else None
        beats_success = all(success["histogram"] >= v for v in success.values())
        beats_error = errors.get("histogram") is not None and all(
            v is None or errors["histogram"] <= v for v in errors.values())
        out[f"histogram_beats_baselines_{mode}"] = {
            "success_at_recall_0.35": success, "table2_trans_err_m": errors,
            "target": "histogram best in both", "met": bool(beats_success and beats_error)}
        hc = row("car-car", "histogram", mode)
        rw = row("car-car", "random-walk", mode)
        if hc and rw:
            out[f"car_car_histogram_end_to_end_ms_{mode}"] = {
                "value": hc["total_ms_mean"], "median": hc["total_ms_median"], "min": hc["total_ms_min"],
                "nodes": [hc["nodes_a"], hc["nodes_b"]],
                "target": "<= 5 ms", "met": hc["total_ms_mean"] <= 5.0}
            speed = {"vs_vectorised_random_walk": round(rw["total_ms_mean"] / max(hc["total_ms_mean"], 1e-9), 1)}
            if "xview_per_pair" in rw:
                speed["vs_xview_per_pair_random_walk"] = round(
                    rw["xview_per_pair"]["end_to_end_ms"] / max(hc["total_ms_mean"], 1e-9), 1)
            out[f"histogram_speedup_{mode}"] = speed | {"target": ">= 100x",
                                                        "met": max(speed.values()) >= 100}  # fmt: skip
    d = results["disjoint"]
    false = sum(r["whole_successes"] + r["window_successes"] for r in d)
    out["disjoint_false_successes"] = {"value": false, "target": "0", "met": false == 0}
    return out


def check_cache_dir(cache_dir: Path) -> None:
    """Refuse a ``--cache`` that is a file, or lies under one (an ``[Errno 20] Not a directory`` once the first
    scene was rendered, before).

    Raises:
        SimulationError: it is, naming the file.
    """
    path = Path(cache_dir)
    file = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    if file is not None:
        where = "is a file" if file == path else f"lies under {file}, a file"
        raise SimulationError(f"--cache {path} {where}; give a folder for the rendered keyframes (created if missing)")


def run_localization_benchmark(
    out_dir: Path | None = None,
    options: BenchOptions | None = None,
    cfg: ShgmConfig | None = None,
    progress: ProgressFn | None = None,
) -> dict:
    """Run every experiment; returns the results dict and writes ``localization.json`` (and the markdown
    tables ``localization.md`` and ``pr_curve.png``) into ``out_dir`` when given.

    Raises:
        SimulationError: a scenario cannot be rendered or the cache folder cannot be written (a file given for it:
            ``check_cache_dir``, before any work).
    """
    from shgm_slam.bench.localization_report import localization_markdown, plot_pr_curves

    options = options or BenchOptions()
    check_cache_dir(options.cache_dir)
    cfg = cfg or ShgmConfig()
    ctx = _Context(options, cfg, progress or (lambda _msg: None))
    load = os.getloadavg()
    t0 = time.perf_counter()
    with single_threaded_blas():
        synthia = _synthia_data(ctx)
        fig5 = figure5(ctx, synthia)
        results = {
            "benchmark": "localization",
            "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in options.__dict__.items()}
            | {"kinds": [k.value for k in options.kinds], "modes": [m.value for m in options.modes]},
            "config": {"matching": cfg.matching.model_dump(mode="json"),
                       "descriptor": cfg.descriptor.model_dump(mode="json"),
                       "graph": cfg.graph.model_dump(mode="json"),
                       "extraction": cfg.extraction.model_dump(mode="json")},
            "mode_overrides": {m.value: {k: getattr(v, "value", v) for k, v in o.items()}
                               for m, o in MODE_OVERRIDES.items()},
            "cpu_count": os.cpu_count(),
            "load_average_1min_at_start": round(load[0], 2),
            "synthia_queries": len(synthia.windows),
            "figure5": fig5,
        }
        results["table2"] = table2(ctx)
        baseline = {r["mode"]: r for r in fig5 if r["descriptor"] == DescriptorKind.HISTOGRAM.value}
        results["ablations"] = ablations(ctx, synthia, baseline)
        results["partial_overlap"] = partial_overlap(ctx, synthia)
        results["disjoint"] = disjoint(ctx)
        results["table1"] = table1(ctx, fig5, synthia)
    results["targets"] = _targets(results)
    results["wall_time_s"] = round(time.perf_counter() - t0, 1)
    results["environment"] = environment()
    if out_dir is not None:
        write_report(out_dir, "localization", results, localization_markdown)
        plot_pr_curves(results, Path(out_dir) / "pr_curve.png")
    return results
