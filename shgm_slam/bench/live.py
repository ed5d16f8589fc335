"""Live benchmark (``shgm-slam bench live``): one world run from its recorded sequences (``run_slam``) and fed frame
by frame to a ``LiveRun`` in the order the recorded run takes them, side by side in this process.

It reports whether the two results folders hold the same trajectories, byte for byte, and what a caller of
``add_frame`` waits: the frames held before the run started (every robot's first frames set its settings) and the
call that ran them, then each call's wall time (median, 95th percentile, largest) next to the recorded run's own
per-frame step time, and both runs' wall time. The live side reads every frame from the sequence folder before its
call (the caller's camera driver would have it in memory): that reading is not counted in its calls.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from shgm_slam.bench.report import write_report
from shgm_slam.config import ShgmConfig
from shgm_slam.data.interleave import interleave
from shgm_slam.io.export import claimed_results_dir
from shgm_slam.live import LiveRun
from shgm_slam.run_report import FrameStats
from shgm_slam.runner import prepare_frontends, run_slam
from shgm_slam.types import Sequence

COMPARED_FILES = ("fused_tum", "odometry_tum", "fused_kitti")
"""Each robot's results files compared byte for byte (``<robot>_<kind>.txt``)."""


def run_live_benchmark(
    robots: dict[str, Sequence],
    out: Path,
    *,
    config: ShgmConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Run ``robots`` recorded and live (module docstring); write ``out/live.json`` and ``out/live.md``.

    Args:
        robots: robot name -> recorded sequence (the first robot defines the shared frame).
        out: benchmark folder; the two results folders go to ``out/recorded`` and ``out/live``.
        config: the configuration of both runs (None: the defaults).
        progress: called with a line saying what runs now.

    Returns:
        The results (also in ``live.json``): ``identical``, ``files``, ``recorded``/``live`` walls and per-frame
        milliseconds, ``held_frames``, ``start_call_ms``, placements of both.
    """
    say = progress or (lambda _msg: None)
    cfg = config or ShgmConfig()
    out = Path(out)
    order = list(interleave(robots))
    say(f"recorded run ({len(order)} frames)")
    steps: list[FrameStats] = []
    t0 = time.perf_counter()
    with claimed_results_dir(out / "recorded", overwrite=True) as folder:
        recorded = run_slam(robots, cfg, folder, fronts=prepare_frontends(robots, cfg), on_frame=steps.append)
    recorded_s = time.perf_counter() - t0
    say(f"live run ({len(order)} frames fed one by one)")
    calls_ms: list[float] = []
    returned: list[int] = []
    t0 = time.perf_counter()
    live = LiveRun({r: s.intrinsics for r, s in robots.items()}, out / "live", config=cfg, overwrite=True)
    for robot, index in order:
        f = robots[robot][index]
        t_call = time.perf_counter()
        poses = live.add_frame(robot, f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                               T_world_cam=f.T_world_cam)  # fmt: skip
        calls_ms.append((time.perf_counter() - t_call) * 1e3)
        returned.append(len(poses))
    t_finish = time.perf_counter()
    summary = live.finish()
    finish_ms = (time.perf_counter() - t_finish) * 1e3
    live_s = time.perf_counter() - t0
    start = next(i for i, n in enumerate(returned) if n)  # the call that started the run
    running = np.asarray(calls_ms[start + 1:])
    stepped = np.asarray([s.step_ms for s in steps[start + 1:]])
    files = {}
    for robot in robots:
        for kind in COMPARED_FILES:
            a, b = recorded.out_dir / f"{robot}_{kind}.txt", summary.out_dir / f"{robot}_{kind}.txt"
            if a.is_file() or b.is_file():
                files[a.name] = a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()
    results = {
        "robots": list(robots),
        "frames": len(order),
        "identical": all(files.values()),
        "files": files,
        "held_frames": start + 1,
        "held_per_robot": {r: sum(1 for name, _ in order[: start + 1] if name == r) for r in robots},
        "start_call_ms": calls_ms[start],
        "live_call_ms": _spread(running),
        "recorded_step_ms": _spread(stepped),
        "finish_ms": finish_ms,
        "recorded_wall_s": recorded_s,
        "live_wall_s": live_s,
        "placed": {k: {r.name: r.localized for r in s.robots} for k, s in (("recorded", recorded), ("live", summary))},
        "fused_ate_m": {k: {r.name: r.ate_fused_m for r in s.robots}
                        for k, s in (("recorded", recorded), ("live", summary))},
    }
    write_report(out, "live", results, live_markdown)
    return results


def _spread(ms: np.ndarray) -> dict[str, float]:
    """Median, 95th percentile, largest and mean of per-frame milliseconds (NaN when there are none)."""
    if ms.size == 0:
        return dict.fromkeys(("median", "p95", "max", "mean"), float("nan"))
    return {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "max": float(ms.max()),
            "mean": float(ms.mean())}  # fmt: skip


def live_markdown(results: dict) -> str:
    """The benchmark as markdown: the per-frame table and the line on identity."""
    call, step = results["live_call_ms"], results["recorded_step_ms"]
    same = "the same, byte for byte" if results["identical"] else "NOT the same: " + ", ".join(
        name for name, ok in results["files"].items() if not ok)  # fmt: skip
    lines = [
        f"## Frames fed one by one: {', '.join(results['robots'])}, {results['frames']} frames",
        "",
        "| | median ms | p95 ms | max ms | mean ms | wall s |",
        "|---|---|---|---|---|---|",
        f"| recorded run, per frame step | {step['median']:.1f} | {step['p95']:.1f} | {step['max']:.1f} | "
        f"{step['mean']:.1f} | {results['recorded_wall_s']:.1f} |",
        f"| live, per add_frame call | {call['median']:.1f} | {call['p95']:.1f} | {call['max']:.1f} | "
        f"{call['mean']:.1f} | {results['live_wall_s']:.1f} |",
        "",
        f"Frames held until every robot had sent its first frames: {results['held_frames']} ("
        + ", ".join(f"{r} {n}" for r, n in results["held_per_robot"].items())
        + f"; the call that ran them "
        f"took {results['start_call_ms']:.0f} ms); finish {results['finish_ms']:.0f} ms. Per-frame rows are the "
        "frames after that call. Trajectory files of the two runs: " + same + ".",
    ]
    return "\n".join(lines) + "\n"
