"""Depth-quality study (``shgm-slam bench depth-quality``): how good must predicted depth be, per odometry?

True rendered depth is corrupted the way a monocular network errs (``sim.depth_errors``) at chosen
AbsRel levels, and the demo depth model's own output is the last level. For each level and each world:

* odometry alone (no health check, no segments) of every kind studied (KISS-ICP on the pseudo-LiDAR,
  the visual odometry, the hybrid): drift in % of the distance driven (``metrics.drift_percent``) and
  SE(3)-aligned ATE per robot;
* the whole system with each kind forced: the share of overlapping robots placed right by graph
  matching and the false merges, judged like the held-out benchmark (``heldout_judge.judge_run``).

Labels are the rendered ones throughout, so depth is the only thing that changes between levels.
Worlds are the held-out benchmark's (same cache); every finished piece is cached as JSON, so an
interrupted study resumes. Nothing here prints; the CLI renders the returned dict.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from shgm_slam.bench.heldout import REPORT_SEEDS, RESOLUTION, ensure_world
from shgm_slam.bench.heldout_judge import PLACED_RIGHT_M, InputMode, Outcome, judge_run
from shgm_slam.bench.report import write_report
from shgm_slam.bench.stopping import run_to_end
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.demo import demo_model_paths
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.io.json_text import to_json_text
from shgm_slam.metrics import AlignMode, ate, drift_percent, trajectory_length
from shgm_slam.odometry.clouds import depth_to_cloud
from shgm_slam.odometry.sources import make_odometry
from shgm_slam.scene_scale import resolve_robot_config, sample_scene_scale
from shgm_slam.sim.depth_errors import (
    ErrorFieldSequence,
    NetworkDepthErrors,
    abs_rel,
    apply_network_errors,
    calibrate_amplitude,
)
from shgm_slam.types import Frame, Intrinsics, Sequence

CALIBRATION_FRAMES = 12
"""Frames (evenly spread over a robot's sequence) on which the error amplitude is calibrated."""


@dataclass(frozen=True)
class DepthLevel:
    """One row of the study: true depth, network-like errors at an AbsRel, or the demo depth model."""

    name: str
    abs_rel: float | None = None
    model: bool = False


TRUE_DEPTH = DepthLevel("true")
DEMO_MODEL = DepthLevel("demo model", model=True)
LEVELS = (TRUE_DEPTH, *(DepthLevel(f"{a:.2f}", a) for a in (0.03, 0.05, 0.08, 0.12)), DEMO_MODEL)


def parse_level(text: str) -> DepthLevel:
    """A depth level from its name: ``true``, ``model`` (the demo depth model) or an AbsRel in (0, 1).

    Raises:
        ConfigError: anything else.
    """
    t = text.strip().lower()
    if t == TRUE_DEPTH.name:
        return TRUE_DEPTH
    if t in ("model", DEMO_MODEL.name):
        return DEMO_MODEL
    try:
        value = float(t)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < 1.0:
        raise ConfigError(f"depth level {text!r}: write true, model, or an AbsRel between 0 and 1 such as 0.05")
    return DepthLevel(f"{value:.2f}", value)


class DepthReplacedSequence:
    """A sequence whose frames carry another depth (``depth_fn(frame)``), everything else as ``base``."""

    def __init__(self, base: Sequence, depth_fn: Callable[[Frame], np.ndarray], tag: str) -> None:
        self.base = base
        self.depth_fn = depth_fn
        self.name = f"{base.name}[{tag}]"
        self.intrinsics: Intrinsics = base.intrinsics

    def __len__(self) -> int:
        return len(self.base)

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))

    def __getitem__(self, index: int) -> Frame:
        frame = self.base[index]
        frame.depth_m = self.depth_fn(frame)
        return frame

    @property
    def timestamps_s(self) -> np.ndarray:
        return self.base.timestamps_s

    @property
    def gt_poses(self) -> np.ndarray | None:
        return self.base.gt_poses

    @property
    def has_depth(self) -> bool:
        return True

    @property
    def has_labels(self) -> bool:
        return self.base.has_labels


def network_like(sequence: Sequence, abs_rel_target: float, seed: int, errors: NetworkDepthErrors | None = None):
    """``sequence`` with network-like depth errors calibrated to ``abs_rel_target`` on its own frames.

    Returns:
        (the wrapped sequence, the calibrated ``NetworkDepthErrors``).
    """
    errors = errors or NetworkDepthErrors(seed=seed)
    n = len(sequence)
    idx = sorted({round(k) for k in np.linspace(0, n - 1, min(CALIBRATION_FRAMES, n))})
    depths = [sequence[i].depth_m for i in idx]
    if any(d is None for d in depths):
        raise DataError(f"{sequence.name} has no depth files: the depth-quality study corrupts true depth")
    errors = errors.with_amplitude(calibrate_amplitude(depths, idx, errors, abs_rel_target))
    fields = ErrorFieldSequence(np.shape(depths[0]), errors)

    def depth_fn(frame: Frame) -> np.ndarray:
        return apply_network_errors(frame.depth_m, fields.field(frame.index), errors)

    return DepthReplacedSequence(sequence, depth_fn, f"absrel {abs_rel_target:g}"), errors


def model_depth(sequence: Sequence, model_path: Path | None = None, threads: int = 1) -> DepthReplacedSequence:
    """``sequence`` with its depth predicted by an ONNX depth model (default: the demo model)."""
    from shgm_slam.perception.depth import DepthModel

    model = DepthModel(model_path or demo_model_paths()[0], threads=threads)

    def depth_fn(frame: Frame) -> np.ndarray:
        return model.predict(frame.image_rgb, frame.intrinsics)

    return DepthReplacedSequence(sequence, depth_fn, "demo model")


def level_sequence(base: Sequence, level: DepthLevel, seed: int) -> Sequence:
    """``base`` with the depth of ``level`` (true: ``base`` itself)."""
    if level.model:
        return model_depth(base)
    if level.abs_rel is None:
        return base
    return network_like(base, level.abs_rel, seed)[0]


def robot_config(sequence: Sequence, cfg: ShgmConfig) -> ShgmConfig:
    """``cfg`` with the robot's data-derived values from its own (possibly corrupted) first frames."""
    scale = sample_scene_scale(sequence, lambda f: (f.depth_m, f.label_ids))
    return resolve_robot_config(cfg, scale)


@dataclass
class OdometryTrack:
    """One odometry kind alone over one robot's frames, judged against ground truth."""

    kind: str
    frames: int
    frames_not_measured: int  # the source coasted (no ICP / PnP result)
    path_length_m: float
    drift_percent: float
    ate_aligned_m: float
    abs_rel: float  # of the depth it saw (every 10th frame against the true depth)
    seconds: float


def run_odometry(
    sequence: Sequence, cfg: ShgmConfig, kind: OdometryKind, true_depth: Sequence | None = None
) -> tuple[OdometryTrack, np.ndarray]:
    """One odometry kind alone over ``sequence`` (no health check, no segments).

    Args:
        sequence: the robot's frames with the depth to test (and ground truth).
        cfg: the fleet configuration; the robot's derived values come from its own first frames.
        kind: the odometry to run.
        true_depth: the uncorrupted sequence, to measure the AbsRel of the depth the odometry saw.

    Returns:
        (the track's errors, (N, 4, 4) ``T_odom_cam`` of every frame).
    """
    gt = sequence.gt_poses
    if gt is None:
        raise DataError(f"{sequence.name} has no ground truth: the depth-quality study needs poses.txt")
    o = robot_config(sequence, cfg).odometry.model_copy(update={"kind": kind})
    source = make_odometry(o, len(sequence))
    n = len(sequence)
    poses, ok, rel = np.zeros((n, 4, 4)), np.zeros(n, bool), []
    t0 = time.perf_counter()
    for i in range(n):
        frame = sequence[i]
        pts, _ = depth_to_cloud(frame.depth_m, frame.intrinsics, stride=o.cloud_stride, min_range_m=o.min_range_m,
                                max_range_m=o.max_range_m)  # fmt: skip
        est = source.update(frame, pts, frame.depth_m, frame.label_ids)
        poses[i], ok[i] = est.T_odom_cam, est.ok
        if true_depth is not None and i % 10 == 0:
            rel.append(abs_rel(true_depth[i].depth_m, frame.depth_m))
    track = OdometryTrack(
        kind.value, n, int((~ok).sum()), trajectory_length(gt), drift_percent(gt, poses),
        ate(gt, poses, align=AlignMode.SE3).rmse, float(np.mean(rel)) if rel else float("nan"),
        time.perf_counter() - t0,
    )  # fmt: skip
    return track, poses


@dataclass(frozen=True)
class DepthQualityOptions:
    """What to run. ``max_frames`` cuts every robot's sequence (quick looks)."""

    scenarios: tuple[str, ...] = ("airsim-like", "synthia-like")
    seeds: tuple[int, ...] = REPORT_SEEDS
    levels: tuple[DepthLevel, ...] = LEVELS
    odometry_kinds: tuple[OdometryKind, ...] = (OdometryKind.KISS_ICP, OdometryKind.VISUAL, OdometryKind.HYBRID)
    system_kinds: tuple[OdometryKind, ...] = (OdometryKind.VISUAL, OdometryKind.HYBRID)
    resolution: tuple[int, int] = RESOLUTION
    max_frames: int | None = None
    cache: Path = Path("cache/heldout")


Progress = Callable[[str], None]


def _quiet(_msg: str) -> None:
    pass


def _slug(level: DepthLevel) -> str:
    return "model" if level.model else "true" if level.abs_rel is None else f"absrel{level.abs_rel:g}"


def _robot_names(world: Path) -> list[str]:
    return [r["name"] for r in json.loads((world / "scenario.json").read_text())["robots"]]


def _nan_for_null(value: object) -> object:
    """``value`` read back from strict JSON with every null as NaN, recursively: the cached records hold only
    numbers, strings and booleans, and a null there is a number that was not measurable."""
    if value is None:
        return float("nan")
    if isinstance(value, dict):
        return {k: _nan_for_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_for_null(v) for v in value]
    return value


def _cached(path: Path, compute: Callable[[], dict]) -> dict:
    """``path``'s JSON when it exists, else ``compute()`` written there as strict JSON (the study resumes;
    non-finite numbers are written as null and read back as NaN)."""
    if path.is_file():
        return _nan_for_null(json.loads(path.read_text()))
    result = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_json_text(result) + "\n")
    return result


def system_config(kind: OdometryKind) -> ShgmConfig:
    """The default configuration with the odometry kind forced (depth and labels come from the frames)."""
    cfg = ShgmConfig()
    cfg.odometry.kind = kind
    return ShgmConfig.model_validate(cfg.model_dump())


def _world_rows(scenario: str, seed: int, options: DepthQualityOptions, out: Path, progress: Progress) -> list[dict]:
    """Every level, odometry and system run of one world; one row per (robot, level, kind) measured."""
    world = ensure_world(options.cache, scenario, seed, options.resolution, progress)
    names = _robot_names(world)
    cut = f":0-{options.max_frames}" if options.max_frames else ""
    bases = {n: open_sequence(f"{world / n}{cut}") for n in names}
    tag = f"{scenario}-s{seed}"
    rows = []
    for level in options.levels:
        seqs = {n: level_sequence(b, level, seed=1000 * seed + k) for k, (n, b) in enumerate(bases.items())}
        for kind in options.odometry_kinds:
            for n, seq in seqs.items():
                progress(f"{tag} depth {level.name}: {kind.value} odometry alone, {n}")

                def track(seq=seq, kind=kind, n=n) -> dict:
                    return asdict(run_odometry(seq, ShgmConfig(), kind, true_depth=bases[n])[0])

                t = _cached(out / "odometry" / tag / _slug(level) / f"{kind.value}-{n}.json", track)
                rows.append({"scenario": scenario, "seed": seed, "level": level.name, "robot": n, "what": "odometry",
                             **t})  # fmt: skip
        for kind in options.system_kinds:
            run_dir = out / "runs" / f"{tag}-{_slug(level)}-{kind.value}"
            progress(f"{tag} depth {level.name}: the system with {kind.value} odometry")

            def system(seqs=seqs, kind=kind, run_dir=run_dir) -> dict:
                summary = run_to_end(seqs, system_config(kind), run_dir)  # a stopped run is not cached
                metrics = json.loads(json.dumps(summary.to_json_dict(), default=float))
                verdicts = judge_run(run_dir, world, names, InputMode.RGB, scenario, seed, metrics)
                return {"wall_s": summary.wall_s, "verdicts": [vars(v) for v in verdicts]}

            done = _cached(run_dir / "verdicts.json", system)
            for v in done["verdicts"]:
                rows.append({"scenario": scenario, "seed": seed, "level": level.name, "robot": v["robot"],
                             "what": "system", "kind": kind.value, **{k: v[k] for k in SYSTEM_FIELDS}})  # fmt: skip
    return rows


SYSTEM_FIELDS = ("reference", "overlaps", "outcome", "placement_error_m", "ate_fused_m", "ate_odometry_aligned_m",
                 "failures_detected", "odometry_breaks", "path_length_m")  # fmt: skip
"""The held-out verdict fields kept per robot of a whole-system run."""


def run_depth_quality_benchmark(out: Path, options: DepthQualityOptions, progress: Progress | None = None) -> dict:
    """Run (or resume) the study; writes ``depth_quality.json``, ``.md`` and ``depth_quality.png`` in ``out``."""
    progress = progress or _quiet
    out = Path(out)
    t0 = time.perf_counter()
    rows = [row for sc in options.scenarios for seed in options.seeds
            for row in _world_rows(sc, seed, options, out, progress)]  # fmt: skip
    results = {
        "options": {
            "scenarios": list(options.scenarios), "seeds": list(options.seeds),
            "levels": [asdict(lv) for lv in options.levels],
            "odometry_kinds": [k.value for k in options.odometry_kinds],
            "system_kinds": [k.value for k in options.system_kinds],
            "resolution": list(options.resolution), "max_frames": options.max_frames,
            "placed_right_m": PLACED_RIGHT_M[InputMode.RGB], "error_model": asdict(NetworkDepthErrors()),
        },
        "summary": summarize(rows, options),
        "rows": rows,
        "wall_s": round(time.perf_counter() - t0, 1),
    }  # fmt: skip
    write_report(out, "depth_quality", results, depth_quality_markdown)
    plot_depth_quality(results, out / "depth_quality.png")
    return results


def _median(values: list[float]) -> float:
    v = [x for x in values if x == x]
    return float(np.median(v)) if v else float("nan")


def summarize(rows: list[dict], options: DepthQualityOptions) -> list[dict]:
    """Per level: measured AbsRel, each odometry's median drift and aligned ATE (cars and UAVs apart),
    and per system run kind the placement counts (overlapping robots that are not the reference)."""
    out = []
    for level in options.levels:
        sel = [r for r in rows if r["level"] == level.name]
        odo = [r for r in sel if r["what"] == "odometry"]
        entry = {"level": level.name, "abs_rel_target": level.abs_rel,
                 "abs_rel_measured": _median([r["abs_rel"] for r in odo]), "odometry": {}, "system": {}}  # fmt: skip
        for kind in options.odometry_kinds:
            mine = [r for r in odo if r["kind"] == kind.value]
            for group, pick in (("all", mine), ("cars", [r for r in mine if r["robot"] != "uav"]),
                                ("uav", [r for r in mine if r["robot"] == "uav"])):  # fmt: skip
                entry["odometry"].setdefault(kind.value, {})[group] = {
                    "robots": len(pick), "drift_percent": _median([r["drift_percent"] for r in pick]),
                    "ate_aligned_m": _median([r["ate_aligned_m"] for r in pick]),
                    "ms_per_frame": _median([1e3 * r["seconds"] / max(r["frames"], 1) for r in pick]),
                }  # fmt: skip
        for kind in options.system_kinds:
            mine = [r for r in sel if r["what"] == "system" and r["kind"] == kind.value]
            ovl = [r for r in mine if r["overlaps"] and not r["reference"]]
            refs = [r for r in mine if r["reference"]]
            entry["system"][kind.value] = {
                "overlapping": len(ovl),
                "placed_right": sum(r["outcome"] == Outcome.RIGHT.value for r in ovl),
                "wrong": sum(r["outcome"] == Outcome.WRONG.value for r in mine if not r["reference"]),
                "not_placed": sum(r["outcome"] == Outcome.NOT_PLACED.value for r in ovl),
                "reference_ate_fused_m": _median([r["ate_fused_m"] for r in refs]),
                "failures_detected": sum(r["failures_detected"] for r in mine),
            }  # fmt: skip
        out.append(entry)
    return out


def _seeds_text(seeds: list[int]) -> str:
    return f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]}-{seeds[-1]}"


KIND_NAMES = {OdometryKind.KISS_ICP.value: "KISS-ICP", OdometryKind.VISUAL.value: "visual",
              OdometryKind.HYBRID.value: "hybrid"}  # fmt: skip


def depth_quality_markdown(results: dict) -> str:
    """The study's table (what the README shows): per depth level, drift and ATE of each odometry
    alone, and placement by the whole system with each odometry."""
    o = results["options"]
    odo_kinds, sys_kinds = o["odometry_kinds"], o["system_kinds"]
    head = ["depth", "AbsRel"]
    head += [f"{KIND_NAMES.get(k, k)} drift % (cars / UAV)" for k in odo_kinds]
    head += [f"{KIND_NAMES.get(k, k)} ATE m (cars / UAV)" for k in odo_kinds]
    head += [f"placed right, {KIND_NAMES.get(k, k)}" for k in sys_kinds]
    head += [f"wrong, {KIND_NAMES.get(k, k)}" for k in sys_kinds]
    head += [f"reference fused ATE m, {KIND_NAMES.get(k, k)}" for k in sys_kinds]
    lines = [
        f"Worlds: {', '.join(o['scenarios'])}, {_seeds_text(o['seeds'])}, "
        f"{o['resolution'][0]}x{o['resolution'][1]}"
        + (f", the first {o['max_frames']} frames of every robot" if o.get("max_frames") else "")
        + "; rendered labels, depth as in the first column. Drift: "
        "translation error per distance driven over 50-200 m stretches (median over robots; odometry alone, no "
        "health check); ATE: SE(3)-aligned, metres. Placed right: overlapping robots (not the reference) placed "
        f"within {o['placed_right_m']:g} m by the whole system (default configuration, odometry forced).",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|",
    ]
    for e in results["summary"]:
        cells = [e["level"], f"{e['abs_rel_measured']:.3f}"]
        for k in odo_kinds:
            g = e["odometry"][k]
            cells.append(f"{g['cars']['drift_percent']:.1f} / {g['uav']['drift_percent']:.1f}")
        for k in odo_kinds:
            g = e["odometry"][k]
            cells.append(f"{g['cars']['ate_aligned_m']:.1f} / {g['uav']['ate_aligned_m']:.1f}")
        for k in sys_kinds:
            g = e["system"][k]
            cells.append(f"{g['placed_right']}/{g['overlapping']}")
        for k in sys_kinds:
            cells.append(str(e["system"][k]["wrong"]))
        for k in sys_kinds:
            cells.append(f"{e['system'][k]['reference_ate_fused_m']:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_depth_quality(results: dict, path: Path) -> Path:
    """Drift of each odometry and the share placed right against the depth's AbsRel, as a PNG
    (matplotlib, Agg; it comes with evo)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = results["summary"]
    x = np.array([e["abs_rel_measured"] for e in summary])
    is_model = np.array([e["level"] == DEMO_MODEL.name for e in summary])
    colors = {OdometryKind.KISS_ICP.value: "tab:red", OdometryKind.VISUAL.value: "tab:blue",
              OdometryKind.HYBRID.value: "tab:green"}  # fmt: skip
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9.0, 3.6), dpi=120)
    for k in results["options"]["odometry_kinds"]:
        for group, style in (("cars", "-o"), ("uav", "--s")):
            y = np.array([e["odometry"][k][group]["drift_percent"] for e in summary])
            if np.isfinite(y).any():
                ax1.plot(x[~is_model], y[~is_model], style, color=colors.get(k), ms=4,
                         label=f"{KIND_NAMES.get(k, k)} ({group})")  # fmt: skip
                ax1.plot(x[is_model], y[is_model], "*", color=colors.get(k), ms=11)
    ax1.set_yscale("log")
    ax1.set_xlabel("AbsRel of the depth (star: the demo model)")
    ax1.set_ylabel("drift, % of distance (median)")
    ax1.grid(alpha=0.3, which="both")
    ax1.legend(fontsize=6)
    for k in results["options"]["system_kinds"]:
        share = np.array([e["system"][k]["placed_right"] / max(e["system"][k]["overlapping"], 1) for e in summary])
        ax2.plot(x[~is_model], 100 * share[~is_model], "-o", color=colors.get(k), ms=4, label=KIND_NAMES.get(k, k))
        ax2.plot(x[is_model], 100 * share[is_model], "*", color=colors.get(k), ms=11)
    ax2.set_ylim(-3, 103)
    ax2.set_xlabel("AbsRel of the depth (star: the demo model)")
    ax2.set_ylabel(f"robots placed within {results['options']['placed_right_m']:g} m, %")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=7)
    o = results["options"]
    fig.suptitle(f"Depth quality: {', '.join(o['scenarios'])}, {_seeds_text(o['seeds'])}", fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
