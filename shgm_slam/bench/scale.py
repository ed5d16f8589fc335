"""Cost with distance on a kilometre drive (``shgm-slam bench scale``).

The whole of KITTI 00 (4541 frames, 3.7 km, many loops) with 07 beside it, as a ``kitti-paths`` world
(real KITTI motion, a generated city; 320x96), run once by ``run_slam`` with the default configuration
and no viewer. Every step's cost is recorded (``run_report.FrameStats``) and binned by how far the 00 robot
has driven (ground-truth path length): per kilometre, the time per keyframe of the front end (cloud,
odometry, extraction, graph), graph matching and the pose graph (separately), what else the server and
the runner spent, the matches tried and their mean cost and graph sizes, and the process's resident
memory at the end of the kilometre. The targets compare the last kilometre with the first.

The memory runs compare distance, not frame rate: the first kilometre of 00 and all of it, each alone in
a fresh process (``peak RSS``). Nothing here prints; the CLI renders the dict.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shgm_slam.bench.report import write_report
from shgm_slam.bench.stopping import run_to_end
from shgm_slam.bench.system import _world, peak_rss_runs
from shgm_slam.config import ShgmConfig
from shgm_slam.io.trajectories import read_tum
from shgm_slam.run_report import FrameStats
from shgm_slam.runner import open_robots

Progress = Callable[[str], None]

DRIVES = ("00", "07")
"""KITTI drives of the world: all of 00 (the long drive whose cost is measured) and all of 07."""
ROBOT = "kitti00"
"""The robot whose distance bins the costs."""
KM_M = 1000.0


@dataclass
class StepCost:
    """Sums of ``FrameStats`` over a set of steps (a kilometre of one robot here, a whole fleet in
    ``bench robots``)."""

    keyframes: int = 0
    frames: int = 0
    front_end_ms: float = 0.0
    load_ms: float = 0.0
    match_ms: float = 0.0
    backend_ms: float = 0.0
    server_ms: float = 0.0
    step_ms: float = 0.0
    cpu_ms: float = 0.0
    write_ms: float = 0.0
    correction_ms: float = 0.0
    matches: int = 0
    match_nodes: list[int] = field(default_factory=list)

    def add(self, s: FrameStats) -> None:
        """Count one step."""
        self.frames += 1
        self.keyframes += s.keyframe
        self.front_end_ms += s.front_end_ms
        self.load_ms += s.load_ms
        self.match_ms += s.match_ms
        self.backend_ms += s.backend_ms
        self.server_ms += s.server_ms
        self.step_ms += s.step_ms
        self.cpu_ms += s.step_cpu_ms
        self.write_ms += s.write_ms
        self.correction_ms += s.correction_ms
        self.matches += len(s.matches)
        self.match_nodes += [m.nodes_a + m.nodes_b for m in s.matches]


@dataclass
class _Bin(StepCost):
    """Sums over the steps of the long robot within one kilometre."""

    rss_end_mb: float = 0.0


def _rss_mb() -> float:
    """Resident memory of this process now, MB (Linux ``/proc/self/statm``; NaN elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return float("nan")


class _Recorder:
    """Collects ``FrameStats`` of the long robot into kilometre bins (``path_m``: its ground-truth path
    length at every frame)."""

    def __init__(self, path_m: np.ndarray) -> None:
        self.path_m = path_m
        self.bins: list[_Bin] = [_Bin() for _ in range(int(path_m[-1] // KM_M) + 1)]
        self.other_robots = _Bin()
        self.rss_start_mb = float("nan")

    def __call__(self, s: FrameStats) -> None:
        if not np.isfinite(self.rss_start_mb):
            self.rss_start_mb = _rss_mb()
        if s.robot != ROBOT:
            b = self.other_robots
        else:
            b = self.bins[min(int(self.path_m[s.frame_index] // KM_M), len(self.bins) - 1)]
            b.rss_end_mb = _rss_mb()
        b.add(s)


def _bin_row(b: _Bin, km_from: float, km_to: float) -> dict:
    n = max(b.keyframes, 1)
    other = b.step_ms - b.front_end_ms - b.load_ms - b.server_ms
    return {
        "from_km": round(km_from, 2),
        "to_km": round(km_to, 2),
        "frames": b.frames,
        "keyframes": b.keyframes,
        "front_end_ms_per_kf": b.front_end_ms / n,
        "match_ms_per_kf": b.match_ms / n,
        "backend_ms_per_kf": b.backend_ms / n,
        "results_files_ms_per_kf": b.write_ms / n,
        "corrections_ms_per_kf": b.correction_ms / n,
        "server_other_ms_per_kf": (b.server_ms - b.match_ms - b.backend_ms - b.write_ms - b.correction_ms) / n,
        "runner_other_ms_per_kf": other / n,
        "total_ms_per_kf": (b.step_ms - b.load_ms) / n,
        "cpu_ms_per_kf": b.cpu_ms / n,
        "cpu_ms_per_frame": b.cpu_ms / max(b.frames, 1),
        "load_ms_per_kf": b.load_ms / n,
        "matches": b.matches,
        "ms_per_match": b.match_ms / b.matches if b.matches else 0.0,
        "nodes_per_match": float(np.mean(b.match_nodes)) if b.match_nodes else 0.0,
        "rss_end_mb": b.rss_end_mb,
    }


def height_split_m(results: Path, robot: str) -> tuple[float, float]:
    """(horizontal, vertical) RMS of ``robot``'s fused error in the shared frame, metres, from the results
    folder's ``<robot>_fused_tum.txt`` and ``<robot>_gt_tum.txt``; vertical = along the ground truth's up
    (the mean of its cameras' -y axes: KITTI cameras look level, y down). NaN when either file is missing."""
    fused, gt = results / f"{robot}_fused_tum.txt", results / f"{robot}_gt_tum.txt"
    if not (fused.is_file() and gt.is_file()):
        return float("nan"), float("nan")
    t_est, est = read_tum(fused)
    t_gt, ref = read_tum(gt)
    rows = np.searchsorted(t_gt, t_est).clip(0, len(t_gt) - 1)
    ok = np.abs(t_gt[rows] - t_est) < 1e-3
    err = est[ok, :3, 3] - ref[rows[ok], :3, 3]
    up = -ref[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    vertical = err @ up
    horizontal = err - vertical[:, None] * up
    return float(np.sqrt(np.mean(np.sum(horizontal**2, axis=1)))), float(np.sqrt(np.mean(vertical**2)))


def run_scale_benchmark(
    out: Path,
    *,
    cache: Path = Path("cache"),
    seed: int = 0,
    resolution: tuple[int, int] = (320, 96),
    kitti_root: Path | None = None,
    memory: bool = True,
    config: ShgmConfig | None = None,
    progress: Progress | None = None,
) -> dict:
    """Run the scale benchmark; writes ``out/scale.json`` and ``out/scale.md`` and returns the dict.

    The world is simulated once into ``cache`` (``kitti-paths``, drives ``DRIVES``) and reused; the run's
    results folder is ``out/run`` (fused trajectories to evaluate), the memory runs' ``out/memory_*``.
    """
    progress = progress or (lambda _msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config or ShgmConfig()
    world = _world(cache / "bench", "kitti-paths", seed, progress, resolution=resolution, kitti_robots=DRIVES,
                   **({"kitti_root": kitti_root} if kitti_root is not None else {}))  # fmt: skip
    robots = open_robots([f"kitti{d}={world / f'kitti{d}'}" for d in DRIVES])
    gt = robots[ROBOT].gt_poses
    path_m = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))]
    recorder = _Recorder(path_m)
    progress(f"running {', '.join(robots)} ({path_m[-1] / KM_M:.1f} km) with per-step costs")
    summary = run_to_end(robots, cfg, out / "run", on_frame=recorder)
    rows = [
        _bin_row(b, k, min(k + 1.0, path_m[-1] / KM_M)) for k, b in enumerate(recorder.bins) if b.frames
    ]  # fmt: skip
    results: dict = {
        "world": str(world),
        "seed": seed,
        "robot": ROBOT,
        "path_km": path_m[-1] / KM_M,
        "per_km": rows,
        "other_robots": _bin_row(recorder.other_robots, 0.0, 0.0),
        "run": {k: v for k, v in summary.to_json_dict().items() if k != "skipped"},
        "height_split_m": {r: height_split_m(out / "run", r) for r in robots},
    }
    ends = [recorder.rss_start_mb] + [r["rss_end_mb"] for r in rows]
    for r, before, after in zip(rows, ends[:-1], ends[1:], strict=True):
        r["rss_growth_mb"] = after - before
        r["rss_growth_kb_per_kf"] = (after - before) * 1024.0 / max(r["keyframes"], 1)
    first, last = rows[0], rows[-1]
    results["rss_start_mb"] = recorder.rss_start_mb
    results["targets"] = {
        "time_per_kf_last_over_first": last["total_ms_per_kf"] / first["total_ms_per_kf"],
        "cpu_per_kf_last_over_first": last["cpu_ms_per_kf"] / first["cpu_ms_per_kf"],
        "cpu_per_frame_last_over_first": last["cpu_ms_per_frame"] / first["cpu_ms_per_frame"],
        "rss_growth_per_kf_last_over_first": last["rss_growth_kb_per_kf"] / first["rss_growth_kb_per_kf"]
        if first["rss_growth_kb_per_kf"] > 0 else None,
    }  # fmt: skip

    if memory:  # distance, not frame rate: the first kilometre of 00 and all of it, each in a fresh process
        n_1km = int(np.searchsorted(path_m, KM_M)) + 1
        runs = [("1 km", f"{ROBOT}={world / ROBOT}:0-{n_1km}", "memory_1km"),
                (f"{path_m[-1] / KM_M:.1f} km", f"{ROBOT}={world / ROBOT}", "memory_all")]  # fmt: skip
        results["memory"] = peak_rss_runs(out, runs, progress)

    write_report(out, "scale", results, scale_markdown)
    return results


def scale_markdown(results: dict) -> str:
    """The benchmark's tables as markdown (what the README shows)."""
    lines = [
        f"{results['robot']}: {results['path_km']:.2f} km; per keyframe of {results['robot']} (ms), by distance driven",
        "",
        "| km | keyframes | front end | matching | pose graph | results files | corrections | server other "
        "| runner other | total | CPU | matches | ms/match | nodes/match | RSS MB at end | RSS KB/keyframe |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["per_km"]:
        lines.append(
            f"| {r['from_km']:.0f}-{r['to_km']:.1f} | {r['keyframes']} | {r['front_end_ms_per_kf']:.1f} | "
            f"{r['match_ms_per_kf']:.1f} | {r['backend_ms_per_kf']:.1f} | {r['results_files_ms_per_kf']:.1f} | "
            f"{r['corrections_ms_per_kf']:.1f} | {r['server_other_ms_per_kf']:.1f} | "
            f"{r['runner_other_ms_per_kf']:.1f} | {r['total_ms_per_kf']:.1f} | {r['cpu_ms_per_kf']:.1f} | "
            f"{r['matches']} | "
            f"{r['ms_per_match']:.0f} | {r['nodes_per_match']:.0f} | {r['rss_end_mb']:.0f} | "
            f"{r['rss_growth_kb_per_kf']:.0f} |"
        )
    t = results["targets"]
    mem = t["rss_growth_per_kf_last_over_first"]
    lines += ["", f"last km / first km: time per keyframe {t['time_per_kf_last_over_first']:.2f} (wall), "
              f"{t['cpu_per_kf_last_over_first']:.2f} (CPU; per frame {t['cpu_per_frame_last_over_first']:.2f}), "
              f"memory growth per keyframe {'n/a' if mem is None else f'{mem:.2f}'} "
              f"(RSS {results['rss_start_mb']:.0f} MB at the first frame)"]  # fmt: skip
    run = results["run"]
    lines += ["", "| robot | fused ATE shared m | horizontal / vertical m | aligned m | placed |",
              "|---|---|---|---|---|"]  # fmt: skip
    for r in run["robots"]:
        h, v = results["height_split_m"].get(r["name"], (float("nan"), float("nan")))
        lines.append(
            f"| {r['name']} | {r['ate_fused_m']:.2f} | {h:.2f} / {v:.2f} | {r['ate_fused_aligned_m']:.2f} | "
            f"{'yes' if r['localized'] else 'no'} |"
        )
    lines.append(f"\nmatches tried {run['matches_tried']}, closures accepted {run['closures_accepted']}, "
                 f"wall {run['wall_s']:.0f} s")  # fmt: skip
    if "memory" in results:
        lines += ["", "| drive | peak RSS MB | wall s |", "|---|---|---|"]
        for label, m in results["memory"].items():
            lines.append(f"| {results['robot']} {label} | {m['peak_rss_mb']:.0f} | {m['wall_s']:.0f} |")
    return "\n".join(lines) + "\n"
