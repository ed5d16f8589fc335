"""Sparse, map-like localization benchmark (``shgm-slam bench sparse``): graphs like real city maps.

Real semantic maps are much sparser than the graphs our renderer produces: 15-150 nodes per robot,
only the classes a map holds, many objects missed, noisy centroids and some label confusions. This
benchmark builds such graphs directly from a synthetic city's ground-truth objects (no rendering):

- a drive is a random street route; a robot's graph holds the map-class objects (``MAP_KINDS``) whose
  centres lie within ``VIEW_RANGE_M`` of its lane (buildings ``BUILDING_RANGE_M``), each missed with
  the robot's miss rate (30-60 %), moved by its centroid noise (0.5-2 m horizontal RMS), and a few
  relabelled with a confusable class (``CONFUSIONS``);
- overlapping pairs: two drives along one route sharing 50-300 m of street (B reversed half of the time);
- negatives: two drives whose lanes stay ``NEGATIVE_GAP_M`` apart; half of them on parallel streets;
- every B graph is moved by a random rigid transform (yaw + translation, or a full 3D rotation).

A localization is right when the accepted ``T_a_b`` maps B's centroid within ``CORRECT_M`` and
``CORRECT_DEG`` of the truth; a success outside that is a wrong claim; any success on a negative pair
is a false acceptance. Deterministic by seed. Tuning seeds: ``TUNING_SEEDS``; the report seeds
``REPORT_SEEDS`` are reserved for the final table.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.bench.localization import single_threaded_blas
from shgm_slam.bench.localization_metrics import random_transform, true_transform
from shgm_slam.config import DescriptorConfig, GraphConfig, MatchingConfig
from shgm_slam.errors import ConfigError, SimulationError
from shgm_slam.geometry.se3 import pose_error, transform_points
from shgm_slam.labels import Label
from shgm_slam.matching import MatchResult, judge_alignment, match_graphs
from shgm_slam.matching.matcher import searched_hypotheses
from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.shapes import KIND_LABEL, ObjectKind
from shgm_slam.sim.trajectories import arc_length, fillet_path, lane_path, random_route
from shgm_slam.sim.world import World
from shgm_slam.types import GraphArrays

TUNING_SEEDS = tuple(range(10, 20))
REPORT_SEEDS = tuple(range(210, 220))

MAP_KINDS = (ObjectKind.TREE, ObjectKind.POLE, ObjectKind.STREET_LAMP, ObjectKind.SIGNAL_POLE,
             ObjectKind.TRAFFIC_LIGHT, ObjectKind.TRAFFIC_SIGN, ObjectKind.BUILDING)  # fmt: skip
"""Object kinds a city map holds (vegetation, poles and lamps, signals, signs, buildings)."""

CONFUSIONS: dict[int, tuple[int, ...]] = {
    Label.POLE: (Label.TRAFFIC_SIGN, Label.TRAFFIC_LIGHT),
    Label.TRAFFIC_SIGN: (Label.POLE,),
    Label.TRAFFIC_LIGHT: (Label.POLE, Label.TRAFFIC_SIGN),
    Label.VEGETATION: (Label.BUILDING, Label.POLE),
    Label.BUILDING: (Label.VEGETATION,),
}
"""Label confusions a map builder makes: true train id -> train ids it may be mistaken for."""

VIEW_RANGE_M = 25.0
BUILDING_RANGE_M = 40.0
CORNER_RADIUS_M = 8.0
LANE_OFFSET_M = 2.2
NEGATIVE_GAP_M = 120.0
CORRECT_M = 2.0
CORRECT_DEG = 5.0
MIN_NODES, MAX_NODES = 15, 150
MIN_COMMON = 12
"""Overlapping pairs share at least this many objects (real layouts: 12-51)."""
UP_WORLD = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class SparseOptions:
    """What to run.

    Attributes:
        seeds: world seeds (one city each).
        pairs_per_seed: overlapping pairs per world (as many negatives).
        miss_range: per-robot fraction of objects missed, drawn uniformly.
        noise_range_m: per-robot horizontal centroid noise (RMS, metres), drawn uniformly.
        confusion_rate: fraction of a robot's nodes relabelled with a confusable class.
        share_range_m: street length two overlapping drives share.
        full_rotation: also run every pair with a random 3D rotation (6-DoF matching).
        heights: the maps hold their objects' heights; False: every node at height 0 in the world frame, as a map
            layer without heights is read (graph files of ``[x, y]`` positions); the pairs are the same otherwise.
    """

    seeds: tuple[int, ...] = TUNING_SEEDS
    pairs_per_seed: int = 10
    miss_range: tuple[float, float] = (0.3, 0.6)
    noise_range_m: tuple[float, float] = (0.5, 2.0)
    confusion_rate: float = 0.05
    share_range_m: tuple[float, float] = (50.0, 300.0)
    full_rotation: bool = True
    heights: bool = True

    def __post_init__(self) -> None:
        for name, (low, high, _, _) in MAP_CONDITIONS.items():
            values = _values(getattr(self, name))
            if not all(math.isfinite(v) and low <= v <= high for v in values) or list(values) != sorted(values):
                wanted = "a range A-B with A <= B" if len(values) == 2 else "a value"
                given = "-".join(f"{v:g}" for v in values)
                raise ConfigError(f"sparse benchmark {name} {given}: give {wanted} within {low:g}..{high:g}")

    def conditions(self) -> dict[str, float | list[float]]:
        """How the maps are made (miss rate, centroid noise, confusions, shared street), for the JSON report."""
        shown = {name: (list(v) if isinstance(v := getattr(self, name), tuple) else v) for name in MAP_CONDITIONS}
        return {**shown, "heights": self.heights}

    def conditions_note(self) -> str:
        """'' for the specified map conditions, else each one that differs, e.g. 'centroid noise 1.5-2.5 m
        (specified: 0.5-2 m)'."""
        spec = SparseOptions()
        notes = [
            f"{what} {_shown(getattr(self, name), unit)} (specified: {_shown(getattr(spec, name), unit)})"
            for name, (_, _, what, unit) in MAP_CONDITIONS.items() if getattr(self, name) != getattr(spec, name)
        ]  # fmt: skip
        return ", ".join(notes + ([] if self.heights else ["no heights (every node at height 0)"]))


MAP_CONDITIONS: dict[str, tuple[float, float, str, str]] = {
    "miss_range": (0.0, 0.95, "missed", "%"),
    "noise_range_m": (0.0, 10.0, "centroid noise", "m"),
    "confusion_rate": (0.0, 1.0, "confused", "%"),
    "share_range_m": (10.0, 1000.0, "shared street", "m"),
}
"""The map conditions ``SparseOptions`` varies (``bench sparse --miss/--noise-m/--confusion/--share-m``): field ->
(lowest, highest accepted, what it is in words, unit written: '%' for a fraction, 'm')."""


def _values(value: float | tuple[float, ...]) -> tuple[float, ...]:
    return tuple(value) if isinstance(value, tuple) else (value,)


def _shown(value: float | tuple[float, ...], unit: str) -> str:
    """A condition's value as text: '0.5-2 m', '30-60 %', '5 %'."""
    scale = 100.0 if unit == "%" else 1.0
    return "-".join(f"{round(v * scale, 6):g}" for v in _values(value)) + f" {unit}"


@dataclass
class SparsePair:
    """One benchmark case: A's graph, B's graph in B's own (moved) frame and the true ``T_a_b``."""

    seed: int
    index: int
    overlapping: bool
    graph_a: GraphArrays
    graph_b: GraphArrays
    T_a_b: np.ndarray
    common: int
    parallel: bool = False


@dataclass
class SparseOutcome:
    """One scored match."""

    seed: int
    index: int
    overlapping: bool
    dof: int
    nodes: tuple[int, int]
    common: int
    success: bool
    correct: bool
    trans_err_m: float
    rot_err_deg: float
    ms: float
    cpu_ms: float
    reason: str
    truth_margin_nats: float = float("nan")  # the true alignment's LLR beyond the match's threshold (overlapping)
    sigma_m: float = float("nan")  # the error an accepted match predicts at B's centroid (``centroid_sigma_m``)

    def to_json(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) and np.isfinite(v) else v)
                for k, v in self.__dict__.items() if k != "reason"} | {"reason": self.reason}  # fmt: skip


@dataclass
class SparseResults:
    """All outcomes plus the summary per DoF (``summary``). Times are per match, descriptors of both
    graphs included: wall clock (``ms``) and this process's CPU time (``cpu_ms``, less sensitive to other
    load on a shared machine)."""

    outcomes: list[SparseOutcome] = field(default_factory=list)
    options: SparseOptions = field(default_factory=SparseOptions)  # what was run (its map conditions)
    seeds_done: list[int] = field(default_factory=list)  # seeds whose every pair was matched
    interrupted: bool = False  # stopped (Ctrl-C) before every seed was done: the outcomes are of seeds_done

    def summary(self) -> dict[str, dict]:
        out = {}
        for dof in sorted({o.dof for o in self.outcomes}):
            pos = [o for o in self.outcomes if o.dof == dof and o.overlapping]
            neg = [o for o in self.outcomes if o.dof == dof and not o.overlapping]
            ms = np.array([o.ms for o in self.outcomes if o.dof == dof])
            cpu = np.array([o.cpu_ms for o in self.outcomes if o.dof == dof])
            out[f"{dof}dof"] = {
                "overlapping_pairs": len(pos),
                "localized": sum(o.success and o.correct for o in pos),
                "localized_rate": sum(o.success and o.correct for o in pos) / max(len(pos), 1),
                "wrong_claims": sum(o.success and not o.correct for o in pos),
                "worst_wrong_m": max((o.trans_err_m for o in pos if o.success and not o.correct), default=None),
                "median_error_m": _median_or_none([o.trans_err_m for o in pos if o.success]),
                "within_2_sigma": _share([o.trans_err_m <= 2.0 * o.sigma_m for o in pos if o.success]),
                "search_ceiling": sum(map(_within_ceiling, pos)),
                "negatives": len(neg),
                "negatives_accepted": sum(o.success for o in neg),
                "median_ms": float(np.median(ms)) if ms.size else 0.0,
                "p90_ms": float(np.percentile(ms, 90)) if ms.size else 0.0,
                "median_cpu_ms": float(np.median(cpu)) if cpu.size else 0.0,
                "nodes_median": float(np.median([o.nodes for o in pos + neg])) if pos + neg else 0.0,
                "common_median": float(np.median([o.common for o in pos])) if pos else 0.0,
                "by_common": _by_common(pos),
            }
        return out

    def to_json(self) -> dict:
        return {"summary": self.summary(), "conditions": self.options.conditions(), "seeds_done": list(self.seeds_done),
                "interrupted": self.interrupted, "outcomes": [o.to_json() for o in self.outcomes]}  # fmt: skip


COMMON_BINS = (0, MIN_COMMON, 15, 20, 30)
"""Lower edges of the shared-object bins the report breaks the overlapping pairs down by (the last bin is open; the
first holds only pairs drawn with fewer than ``MIN_COMMON`` shared objects, which the benchmark does not draw)."""


def _within_ceiling(o: SparseOutcome) -> bool:
    """An overlapping pair a perfect search would localize: localized, or its true alignment clears the threshold."""
    return (o.success and o.correct) or o.truth_margin_nats > 0


def _by_common(pos: list[SparseOutcome]) -> list[dict]:
    """Overlapping pairs, those localized and the search ceiling (``_within_ceiling``) per bin of objects both maps
    hold (``COMMON_BINS``): where the misses lie, and whether the evidence or the search loses them (a pair sharing
    a dozen objects carries less evidence than one sharing forty). Empty bins are left out."""
    edges = (*COMMON_BINS, None)
    rows = []
    for lo, hi in pairwise(edges):
        inside = [o for o in pos if o.common >= lo and (hi is None or o.common < hi)]
        if inside:
            label = f"<{hi}" if lo == 0 else f"{lo}-{hi - 1}" if hi is not None else f"{lo}+"
            localized = sum(o.success and o.correct for o in inside)
            rows.append({"common": label, "pairs": len(inside), "localized": localized,
                         "search_ceiling": sum(map(_within_ceiling, inside))})  # fmt: skip
    return rows


def _median_or_none(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def map_objects(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M,) world object ids, (M,) train ids and (M, 3) centres (world, z up) of the map-class objects."""
    keep = {k.value for k in MAP_KINDS}
    ids = np.array([o.id for o in world.objects if o.kind.value in keep], dtype=np.int64)
    labels = np.array([KIND_LABEL[world.objects[i].kind] for i in ids], dtype=np.int64)
    centres = np.array([world.objects[i].centre_xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    return ids, labels, centres


def _route(world: World, rng: np.random.Generator, length_m: float, allowed: np.ndarray | None = None) -> np.ndarray:
    """A dense (M, 2) street centreline of about ``length_m`` (cut from a random route)."""
    route = random_route(world.streets, rng, length_m + 2 * CORNER_RADIUS_M, allowed=allowed)
    path = fillet_path(world.streets.nodes_xy[route], CORNER_RADIUS_M)
    s = arc_length(path)
    return path[s <= length_m]


def _cut(path: np.ndarray, s0: float, s1: float) -> np.ndarray:
    s = arc_length(path)
    return path[(s >= s0) & (s <= s1)]


def _seen(lane_xy: np.ndarray, labels: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(M,) bool: objects within view range of a (K, 2) lane (buildings: ``BUILDING_RANGE_M``)."""
    d = cKDTree(lane_xy).query(centres[:, :2])[0]
    return d <= np.where(labels == Label.BUILDING, BUILDING_RANGE_M, VIEW_RANGE_M)


def _robot_graph(
    seen: np.ndarray, labels: np.ndarray, centres: np.ndarray, rng: np.random.Generator,
    opt: SparseOptions, connectivity_m: float, id_offset: int,
) -> tuple[GraphArrays, np.ndarray]:  # fmt: skip
    """One robot's map: misses, centroid noise and confusions applied; returns the graph (world frame)
    and the (N,) indices of its objects into the map-object arrays."""
    miss = rng.uniform(*opt.miss_range)
    sigma = rng.uniform(*opt.noise_range_m)
    rows = np.flatnonzero(seen & (rng.random(seen.size) >= miss))
    n = rows.size
    pos = centres[rows] + np.column_stack([rng.normal(0, sigma / np.sqrt(2), (n, 2)), rng.normal(0, 0.3 * sigma, n)])
    lab = labels[rows].copy()
    for i in np.flatnonzero(rng.random(n) < opt.confusion_rate):
        options = CONFUSIONS.get(int(lab[i]))
        if options:
            lab[i] = options[int(rng.integers(len(options)))]
    edges = cKDTree(pos).query_pairs(connectivity_m, output_type="ndarray").astype(np.int64).reshape(-1, 2)
    order = rng.permutation(n)  # node order carries no information
    inv = np.empty(n, np.int64)
    inv[order] = np.arange(n)
    g = GraphArrays(np.arange(n, dtype=np.int64) + id_offset, lab[order], pos[order], np.ones(n),
                    np.sort(inv[edges], axis=1) if edges.size else edges)  # fmt: skip
    return g, rows[order]


def make_pairs(world: World, seed: int, opt: SparseOptions, connectivity_m: float) -> list[SparsePair]:
    """``pairs_per_seed`` overlapping and as many negative pairs in ``world`` (deterministic by seed).

    Pairs whose graphs fall outside ``MIN_NODES``-``MAX_NODES`` nodes are redrawn.
    """
    rng = np.random.default_rng(seed * 7919 + 17)
    _, labels, centres = map_objects(world)
    pairs: list[SparsePair] = []
    for overlapping in (True, False):
        for _attempt in range(50 * opt.pairs_per_seed):
            if sum(p.overlapping == overlapping for p in pairs) >= opt.pairs_per_seed:
                break
            pair = _draw_pair(world, rng, labels, centres, opt, connectivity_m, overlapping)
            if pair is not None:
                pair.seed, pair.index = seed, len(pairs)
                pairs.append(pair)
        else:
            kind = f"overlapping pairs sharing at least {MIN_COMMON} objects" if overlapping else "far-apart pairs"
            raise SimulationError(
                f"seed {seed}: could not draw {opt.pairs_per_seed} {kind} with graphs of {MIN_NODES}-{MAX_NODES} nodes"
                + (f" under these map conditions ({note}); make them milder" if (note := opt.conditions_note()) else "")
            )
    return pairs


def _draw_pair(world, rng, labels, centres, opt: SparseOptions, connectivity_m: float,
               overlapping: bool) -> SparsePair | None:  # fmt: skip
    len_a, len_b = rng.uniform(80.0, 350.0, 2)
    parallel = False
    try:
        if overlapping:
            share = min(rng.uniform(*opt.share_range_m), len_a, len_b)
            centre = _route(world, rng, len_a + len_b - share)
            lane_a = lane_path(_cut(centre, 0.0, len_a), LANE_OFFSET_M)
            piece_b = _cut(centre, len_a - share, len_a + len_b - share)
            lane_b = lane_path(piece_b[::-1] if rng.random() < 0.5 else piece_b, LANE_OFFSET_M)
        else:
            lane_a = lane_path(_route(world, rng, len_a), LANE_OFFSET_M)
            far = cKDTree(lane_a).query(world.streets.nodes_xy)[0] > NEGATIVE_GAP_M + 50.0
            parallel = bool(rng.random() < 0.5)
            lane_b = lane_path(_route(world, rng, len_b, allowed=far), LANE_OFFSET_M)
            if cKDTree(lane_a).query(lane_b)[0].min() < NEGATIVE_GAP_M:
                return None
            if parallel and not _parallel(lane_a, lane_b):
                return None
    except SimulationError:
        return None
    if len(lane_a) < 2 or len(lane_b) < 2:
        return None
    seen_a, seen_b = _seen(lane_a, labels, centres), _seen(lane_b, labels, centres)
    ga, rows_a = _robot_graph(seen_a, labels, centres, rng, opt, connectivity_m, 0)
    gb, rows_b = _robot_graph(seen_b, labels, centres, rng, opt, connectivity_m, 100_000)
    if not (MIN_NODES <= len(ga) <= MAX_NODES and MIN_NODES <= len(gb) <= MAX_NODES):
        return None
    common = int(np.intersect1d(rows_a, rows_b).size)
    if overlapping and common < MIN_COMMON:
        return None
    if not opt.heights:  # map layers without heights: every node at height 0 (the world's ground)
        ga, gb = _flat(ga), _flat(gb)
    # A's frame: world moved by a random transform too, so nothing is near the origin by construction
    T_a_world = random_transform(rng, False)
    T_b_world = random_transform(rng, False)
    return SparsePair(-1, -1, overlapping, ga.transformed(T_a_world), gb.transformed(T_b_world),
                      T_a_world @ true_transform(T_b_world), common, parallel)  # fmt: skip


def _flat(graph: GraphArrays) -> GraphArrays:
    """``graph`` (world frame, z up) with every node at height 0."""
    positions_xyz = graph.positions_xyz.copy()
    positions_xyz[:, 2] = 0.0
    return GraphArrays(graph.node_ids, graph.label_ids, positions_xyz, graph.sizes, graph.edges)


def _parallel(lane_a: np.ndarray, lane_b: np.ndarray) -> bool:
    """Both lanes' principal directions within 10 degrees (straight, parallel streets)."""
    def direction(p: np.ndarray) -> np.ndarray:
        c = p - p.mean(axis=0)
        return np.linalg.svd(c, full_matrices=False)[2][0]

    return abs(float(direction(lane_a) @ direction(lane_b))) > np.cos(np.radians(10.0))


def rotate_fully(pair: SparsePair, rng: np.random.Generator) -> SparsePair:
    """The same pair with B moved by an additional random 3D rotation (6-DoF matching)."""
    T = random_transform(rng, True, 50.0)
    return SparsePair(pair.seed, pair.index, pair.overlapping, pair.graph_a, pair.graph_b.transformed(T),
                      pair.T_a_b @ true_transform(T), pair.common, pair.parallel)  # fmt: skip


def score(result: MatchResult, pair: SparsePair) -> tuple[bool, float, float]:
    """(correct, translation error at B's centroid in metres, rotation error in degrees) of the accepted
    or best-hypothesis transform (inf without one)."""
    T = result.T_a_b if result.success else result.T_a_b_hypothesis
    if T is None or not pair.overlapping:
        return False, np.inf, np.inf
    c = pair.graph_b.positions_xyz.mean(axis=0)
    trans = float(np.linalg.norm(transform_points(T, c[None]) - transform_points(pair.T_a_b, c[None])))
    rot = float(pose_error(T, pair.T_a_b)[1])
    return trans < CORRECT_M and rot < CORRECT_DEG, trans, rot


def truth_margin_nats(result: MatchResult, pair: SparsePair, cfg: MatchingConfig) -> float:
    """How far the true alignment, judged as the matcher judges its hypotheses (``judge_alignment``), clears the
    match's own threshold, nats (NaN for a far-apart negative). Above 0 on a pair the matcher missed: its search
    missed (the evidence was there); below: the evidence itself stays within chance."""
    if not pair.overlapping:
        return float("nan")
    threshold = result.llr_threshold
    if not np.isfinite(threshold):  # no hypothesis was formed: the bar of a search of one
        threshold = float(np.log(searched_hypotheses(1, cfg) / cfg.false_alarm_rate))
    return judge_alignment(pair.graph_a, pair.graph_b, pair.T_a_b, cfg).llr - threshold


def run_sparse_benchmark(
    options: SparseOptions | None = None,
    descriptor_cfg: DescriptorConfig | None = None,
    matching_cfg: MatchingConfig | None = None,
    graph_cfg: GraphConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> SparseResults:
    """Match every pair of every seed with the given (default) configuration, gravity-aligned (4-DoF)
    and, with ``full_rotation``, 6-DoF; time each match (descriptors included, single-threaded BLAS).

    A Ctrl-C (KeyboardInterrupt) keeps the seeds finished before it: the results come back ``interrupted``,
    without the seed it stopped in (re-raised when no seed was finished)."""
    opt = options or SparseOptions()
    dcfg = descriptor_cfg or DescriptorConfig()
    mcfg = (matching_cfg or MatchingConfig()).model_copy(update={"up_axis": UP_WORLD})
    gcfg = graph_cfg or GraphConfig()
    results = SparseResults(options=opt)
    with single_threaded_blas():
        for seed in opt.seeds:
            kept = len(results.outcomes)
            try:
                _run_seed(seed, opt, dcfg, mcfg, gcfg, results, progress)
            except KeyboardInterrupt:
                if not results.seeds_done:
                    raise
                del results.outcomes[kept:]
                results.interrupted = True
                break
            results.seeds_done.append(seed)
    return results


def _run_seed(seed: int, opt: SparseOptions, dcfg: DescriptorConfig, mcfg: MatchingConfig, gcfg: GraphConfig,
              results: SparseResults, progress: Callable[[str], None] | None) -> None:  # fmt: skip
    """Build seed's world and pairs, match and score them (appends to ``results``)."""
    if progress:
        progress(f"seed {seed}")
    world = build_city(CityParams(), seed=seed)
    pairs = make_pairs(world, seed, opt, gcfg.connectivity_m)
    rng = np.random.default_rng(seed + 5)
    runs = [(4, p) for p in pairs] + ([(6, rotate_fully(p, rng)) for p in pairs] if opt.full_rotation else [])
    for dof, pair in runs:
        cfg = mcfg.model_copy(update={"gravity_aligned": dof == 4})
        t0, c0 = time.perf_counter(), time.process_time()
        r = match_graphs(pair.graph_a, pair.graph_b, dcfg, cfg)
        ms, cpu_ms = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
        correct, te, re = score(r, pair)
        results.outcomes.append(SparseOutcome(
            seed, pair.index, pair.overlapping, dof, (len(pair.graph_a), len(pair.graph_b)), pair.common,
            bool(r.success), correct, te, re, ms, cpu_ms, r.reason, truth_margin_nats(r, pair, cfg),
            r.centroid_sigma_m))  # fmt: skip


def sparse_markdown(results: SparseResults, seeds: tuple[int, ...]) -> str:
    """The summary table as markdown (of the seeds done, when the run was interrupted)."""
    title = f"Sparse map-like localization, seeds {seeds[0]}-{seeds[-1]} ({len(seeds)} worlds)"
    if results.interrupted:
        done = results.seeds_done
        title = (f"Sparse map-like localization, **interrupted**: seeds {done[0]}-{done[-1]} ({len(done)} of the "
                 f"{len(seeds)} worlds asked for, {seeds[0]}-{seeds[-1]})")  # fmt: skip
    if note := results.options.conditions_note():
        title += f"; maps unlike the specification: {note}"
    lines = [title, "",
             "| matching | overlapping pairs | localized | wrong claims | median error m | negatives accepted "
             "| median ms | p90 ms | median CPU ms | search ceiling |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    summary = results.summary()
    for key, s in summary.items():
        lines.append(
            f"| {key} | {s['overlapping_pairs']} | {s['localized']} ({100 * s['localized_rate']:.0f} %) | "
            f"{_wrong(s)} | {_metres(s['median_error_m'])} | {s['negatives_accepted']} / {s['negatives']} | "
            f"{s['median_ms']:.1f} | {s['p90_ms']:.1f} | {s['median_cpu_ms']:.1f} | {s['search_ceiling']} |"
        )
    lines += ["", "*wrong claims*: overlapping pairs accepted farther than 2 m or 5 deg from the truth (the "
              "farthest in brackets: a few metres is the right street placed imprecisely, tens of metres an "
              "alias). *median error*: of every accepted overlapping pair, at B's centroid. *search ceiling*: "
              "overlapping pairs localized, or whose true alignment (refined as any hypothesis) clears the match's "
              "threshold: what a perfect search would localize with this evidence model; the pairs beyond it lack "
              "the evidence, not the search."]  # fmt: skip
    bins = [f"{key} " + ", ".join(f"{r['common']}: {r['localized']} of {r['pairs']} ({r['search_ceiling']})"
                                  for r in s["by_common"])
            for key, s in summary.items() if s["by_common"]]  # fmt: skip
    if bins:
        lines += ["", "Localized by objects the two maps share (overlapping pairs; the search ceiling in brackets): "
                  + "; ".join(bins) + "."]
    shares = [f"{key} {100 * s['within_2_sigma']:.0f} %" for key, s in summary.items()
              if s["within_2_sigma"] is not None]  # fmt: skip
    if shares:
        lines += ["", "Predicted precision: accepted overlapping pairs whose error at B's centroid is within twice the "
                  "RMS error their match predicts there (`centroid_sigma_m`): " + ", ".join(shares) + "."]
    lines += _claims_listed(results)
    return "\n".join(lines) + "\n"


def _claims_listed(results: SparseResults) -> list[str]:
    """Markdown lines naming every wrong claim and accepted negative (seed/pair, DoF, error at B's centroid),
    farthest first, so that each can be matched again and looked at; none when there are none."""
    wrong = sorted((o for o in results.outcomes if o.success and (not o.overlapping or not o.correct)),
                   key=lambda o: (not o.overlapping, -o.trans_err_m, o.seed, o.index, o.dof))  # fmt: skip
    if not wrong:
        return []
    named = [f"{o.seed}/{o.index} {o.dof}dof " + (f"{o.trans_err_m:.1f} m" if o.overlapping else "negative")
             + (f" (predicted {o.sigma_m:.1f} m)" if np.isfinite(o.sigma_m) else "") for o in wrong]  # fmt: skip
    return ["", "Wrong claims and accepted negatives (seed/pair, matching, error at B's centroid, and the RMS error "
            "the match predicted there): " + ", ".join(named) + "."]  # fmt: skip


def _share(flags: list[bool]) -> float | None:
    """The share of True in ``flags``, None when empty."""
    return sum(flags) / len(flags) if flags else None


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _wrong(summary: dict) -> str:
    """The wrong claims of one summary row, with the farthest one's translation error when there are any."""
    worst = summary["worst_wrong_m"]
    return f"{summary['wrong_claims']}" if worst is None else f"{summary['wrong_claims']} (<= {worst:.1f} m)"
