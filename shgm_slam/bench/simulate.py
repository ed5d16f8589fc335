"""Simulator speed and memory: rendered-and-written frames per second and peak RSS.

Two runs of the airsim-like scenario at the target resolution: a short one (speed) and a long one
(memory must not grow with sequence length, since frames stream to disk). Rendering alone is timed
as well, so the PNG-writing share is visible. The machine load at the start is recorded because the
benchmark machine is shared.
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from pathlib import Path

import psutil

from shgm_slam.environment import environment
from shgm_slam.io.json_text import to_json_text
from shgm_slam.sim.render import Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario
from shgm_slam.sim.simulate import simulate

TARGET_FPS = 20.0


def _run(
    scenario: str, out: Path, resolution: tuple[int, int], max_frames: int, seed: int, compact: bool
) -> dict:
    proc = psutil.Process()
    peak = [proc.memory_info().rss]
    cpu: list[float] = []  # process CPU seconds after each frame (world building excluded)

    def progress(_robot: str, done: int, _total: int) -> None:
        cpu.append(time.process_time())
        if done % 10 == 0:
            peak[0] = max(peak[0], proc.memory_info().rss)

    result = simulate(
        scenario,
        out,
        seed=seed,
        resolution=resolution,
        max_frames=max_frames,
        compact=compact,
        progress=progress,
    )
    frames = result.total_frames
    peak[0] = max(peak[0], proc.memory_info().rss)
    t = result.timings_s
    return {
        "frames": frames,
        "robots": {r.name: r.frames for r in result.robots},
        "build_world_s": t["build_world"],
        "prepare_renderer_s": t["prepare_renderer"],
        "render_write_s": t["render_write"],
        "fps": round(result.frames_per_s, 2),
        "ms_per_frame": round(1000 * t["render_write"] / frames, 2),
        "cpu_ms_per_frame": round(1000 * (cpu[-1] - cpu[0]) / max(len(cpu) - 1, 1), 2),
        "peak_rss_mb": round(peak[0] / 2**20, 1),
        "world_triangles": result.world_triangles,
    }


def _render_only(scenario: str, resolution: tuple[int, int], frames: int, seed: int, compact: bool) -> dict:
    plan = build_scenario(scenario, ScenarioOptions(seed=seed, compact=compact))
    poses = plan.robots[0].T_world_cam[:frames]
    with Renderer(plan.world, make_intrinsics(*resolution)) as renderer:
        renderer.render(poses[0])  # embree builds its BVH on the first query
        t0, c0 = time.perf_counter(), time.process_time()
        for T in poses:
            renderer.render(T)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "frames": len(poses),
        "fps": round(len(poses) / wall, 2),
        "ms_per_frame": round(1000 * wall / len(poses), 2),
        "cpu_ms_per_frame": round(1000 * cpu / len(poses), 2),
    }


def run_simulate_benchmark(
    out: Path | None = None,
    *,
    scenario: str = "airsim-like",
    resolution: tuple[int, int] = (640, 192),
    short_frames: int = 40,
    long_frames: int = 300,
    seed: int = 0,
    work_dir: Path | None = None,
    compact: bool = False,
) -> dict:
    """Measure the simulator; returns the results dict and writes it as JSON to ``out`` when given.

    ``short_frames``/``long_frames`` are frames *per robot* of the two runs; sequences go to a temporary
    folder inside ``work_dir`` (default: the system temp folder) that is removed afterwards. ``compact``
    uses the small world (for tests).
    """
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        short = _run(scenario, Path(tmp) / "short", resolution, short_frames, seed, compact)
        long = _run(scenario, Path(tmp) / "long", resolution, long_frames, seed, compact)
    render = _render_only(scenario, resolution, short_frames, seed, compact)
    results = {
        "benchmark": "simulate",
        "scenario": scenario,
        "resolution": list(resolution),
        "cpu_count": os.cpu_count(),
        "load_average_1min_at_start": round(load[0], 2),
        "target_fps": TARGET_FPS,
        "short": short,
        "long": long,
        "render_only": render,
        "ru_maxrss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_growth_mb": round(long["peak_rss_mb"] - short["peak_rss_mb"], 1),
        # what the CPU cost would allow if every core were free (the machine is shared): an estimate
        "cpu_bound_fps_estimate": round((os.cpu_count() or 1) * 1000.0 / short["cpu_ms_per_frame"], 1),
        "meets_target": short["fps"] >= TARGET_FPS,
        "environment": environment(),
    }
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(to_json_text(results) + "\n")
    return results


def simulate_markdown(results: dict) -> str:
    """A markdown table of ``run_simulate_benchmark`` results."""
    w, h = results["resolution"]
    rows = [
        f"### Simulator speed ({results['scenario']}, {w}x{h}, {results['cpu_count']} cores, "
        f"load {results['load_average_1min_at_start']} at start)",
        "",
        "| run | frames | fps | ms/frame | CPU ms/frame | peak RSS MB |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for key, label in (("short", "render + write (short)"), ("long", "render + write (long)")):
        r = results[key]
        rows.append(
            f"| {label} | {r['frames']} | {r['fps']} | {r['ms_per_frame']} | {r['cpu_ms_per_frame']} "
            f"| {r['peak_rss_mb']} |"
        )
    r = results["render_only"]
    rows.append(
        f"| render only | {r['frames']} | {r['fps']} | {r['ms_per_frame']} | {r['cpu_ms_per_frame']} | |"
    )
    rows += [
        "",
        f"target {results['target_fps']} fps: {'met' if results['meets_target'] else 'NOT met'} "
        f"(CPU-bound estimate on free cores: {results['cpu_bound_fps_estimate']} fps); "
        f"RSS growth long vs short: {results['rss_growth_mb']} MB",
    ]
    return "\n".join(rows) + "\n"
