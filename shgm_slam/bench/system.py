"""System benchmark: the whole multi-robot pipeline on simulated worlds (``shgm-slam bench system``).

Measures the issue's targets in one run:

* airsim-like (car1, car2, UAV; KISS-ICP odometry on the rendered depth): which robots are localized,
  fused ATE in the shared frame vs odometry alone, closures accepted and rejected, front end + back end
  ms per keyframe;
* disjoint: the number of accepted inter-robot closures (must be zero);
* with ``rgb_only``: both again from RGB alone (demo ONNX models, visual odometry);
* memory: peak RSS of a 1000-frame and a 4000-frame run of one long drive, each in a fresh process.

Worlds are simulated once into ``cache`` and reused. Nothing here prints; the CLI renders the dict.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import psutil

from shgm_slam.bench.report import write_report
from shgm_slam.bench.stopping import RunStopped, run_to_end, stopped_exit_code
from shgm_slam.config import ShgmConfig
from shgm_slam.demo import demo_config, prepare_world
from shgm_slam.run_report import RunSummary
from shgm_slam.runner import open_robots
from shgm_slam.sim.cache import simulate_cached

Progress = Callable[[str], None]

RSS_SAMPLE_S = 0.2
"""How often a memory run's process tree is sampled."""


def _world(cache: Path, name: str, seed: int, progress: Progress, **options) -> Path:
    out = cache / f"{name}-seed{seed}" if not options else cache / f"{name}-seed{seed}-{_tag(options)}"
    if not (out / "scenario.json").is_file():
        progress(f"simulating {name} into {out}")
        simulate_cached(name, out, seed=seed, **options)
    return out


def _tag(options: dict) -> str:
    """Folder-name tag of simulation options, e.g. ``fps42.6-resolution320x96``."""

    def text(v: object) -> str:
        return "x".join(map(str, v)) if isinstance(v, tuple | list) else str(v)

    return "-".join(f"{k}{text(v)}" for k, v in sorted(options.items()))


def _robots_of(world: Path) -> list[str]:
    return [r["name"] for r in json.loads((world / "scenario.json").read_text())["robots"]]


def _summary_dict(summary: RunSummary) -> dict:
    d = summary.to_json_dict()
    d.pop("skipped", None)
    return d


def _peak_rss_mb(args: list[str]) -> tuple[float, float]:
    """Run ``shgm-slam`` with ``args`` in a fresh process; returns (peak RSS in MB, wall seconds): of the
    process, or, when it starts worker processes (``run --jobs``), of the whole process tree (the sum,
    sampled every ``RSS_SAMPLE_S``) where that is more."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "shgm_slam", *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    tree_peak = 0
    top = psutil.Process(proc.pid)
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)  # reaped here only: its rusage is wanted
        if pid:
            break
        total = 0
        with contextlib.suppress(psutil.Error):  # it or a worker ended between two looks
            for p in [top, *top.children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    total += p.memory_info().rss
        tree_peak = max(tree_peak, total)
        time.sleep(RSS_SAMPLE_S)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if stopped_exit_code(code):  # stopped with this process or alone: the benchmark stops too
        raise RunStopped(f"shgm-slam {' '.join(args)} was stopped")
    if code != 0:
        err = proc.stderr.read().decode(errors="replace")[-500:] if proc.stderr else ""
        raise RuntimeError(f"shgm-slam {' '.join(args)} failed: {err}")
    return max(usage.ru_maxrss / 1024.0, tree_peak / 2**20), wall  # ru_maxrss is in KiB on Linux


def peak_rss_runs(out: Path, runs: list[tuple[str, str | list[str], str]], progress: Progress,
                  extra_args: tuple[str, ...] = ()) -> dict:  # fmt: skip
    """Each ``(label, robot spec NAME=PATH[:a-b] or a list of them, results subfolder)`` run alone (no viewer;
    ``extra_args`` added to ``run``'s) in a fresh process: label -> ``{"peak_rss_mb", "wall_s"}``."""
    mem = {}
    for label, robot, folder in runs:
        progress(f"memory run: {label}")
        specs = [robot] if isinstance(robot, str) else list(robot)
        robot_args = [a for spec in specs for a in ("--robot", spec)]
        args = ["run", *robot_args, "--rerun", "off", "--out", str(Path(out) / folder), "--overwrite", *extra_args]
        rss, wall = _peak_rss_mb(args)
        mem[label] = {"peak_rss_mb": round(rss, 1), "wall_s": round(wall, 1)}
    return mem


def run_system_benchmark(
    out: Path,
    *,
    cache: Path = Path("cache"),
    seed: int = 0,
    memory: bool = True,
    rgb_only: bool = False,
    long_frames: int = 4000,
    progress: Progress | None = None,
) -> dict:
    """Run the system benchmark; writes ``out/system.json`` and ``out/system.md`` and returns the dict.

    With ``rgb_only`` both worlds run once more with depth and labels from the ONNX demo models
    (and visual odometry): the monocular path, and whether it merges disjoint robots.
    """
    progress = progress or (lambda _msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"seed": seed}

    # 1. airsim-like, KISS-ICP odometry (the demo's world and config)
    world, kinds = prepare_world(cache, seed, lambda folder: _world(cache, "airsim-like", seed, progress))
    progress("running the system on airsim-like (KISS-ICP)")
    robots = open_robots([f"{r}={world / r}" for r in kinds])
    summary = run_to_end(robots, demo_config(), out / "airsim-like")
    results["airsim_like"] = _summary_dict(summary)

    # 2. disjoint: nothing may be merged
    dis = _world(cache / "bench", "disjoint", seed, progress)
    progress("running the system on disjoint")
    cfg = ShgmConfig()
    summary = run_to_end(open_robots([f"{r}={dis / r}" for r in _robots_of(dis)]), cfg, out / "disjoint")
    results["disjoint"] = _summary_dict(summary)

    if rgb_only:
        progress("running the system on airsim-like, RGB only (demo models, visual odometry)")
        robots = open_robots([f"{r}={world / r}" for r in kinds])
        summary = run_to_end(robots, demo_config(rgb_only=True), out / "airsim-like-rgb")
        results["airsim_like_rgb"] = _summary_dict(summary)
        progress("running the system on disjoint, RGB only")
        robots = open_robots([f"{r}={dis / r}" for r in _robots_of(dis)])
        cfg_rgb = demo_config(rgb_only=True)
        results["disjoint_rgb"] = _summary_dict(run_to_end(robots, cfg_rgb, out / "disjoint-rgb"))

    # 3. memory: one long drive, 1000 vs long_frames frames, each in a fresh process
    if memory:
        fps = 10.0 * long_frames / 940.0  # the synthia-like drive is ~950 m at ~10 m/s
        long_world = _world(cache / "bench", "synthia-like", seed, progress, fps=round(fps, 1), resolution=(320, 96))
        seq = long_world / "forward"
        n_total = sum(1 for _ in open(seq / "times.txt"))
        counts = (1000, min(long_frames, n_total))
        results["memory"] = peak_rss_runs(out, [(str(n), f"car={seq}:0-{n}", f"memory_{n}") for n in counts], progress)

    write_report(out, "system", results, system_markdown)
    return results


def system_markdown(results: dict) -> str:
    """The benchmark's tables as markdown (what the README shows)."""
    lines = [
        "| scenario | robot | frames | keyframes | localized | path m | ATE odometry m | ATE fused m |"
        " aligned ATE odometry / fused m |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    keys = [k for k in ("airsim_like", "disjoint", "airsim_like_rgb", "disjoint_rgb") if k in results]
    for key in keys:
        for r in results[key]["robots"]:
            lines.append(
                f"| {key.replace('_', '-')} | {r['name']} | {r['frames']} | {r['keyframes']} | "
                f"{'yes' if r['localized'] else 'no'} | {r['path_length_m']:.0f} | {r['ate_odometry_m']:.2f} | "
                f"{r['ate_fused_m']:.2f} | {r['ate_odometry_aligned_m']:.2f} / {r['ate_fused_aligned_m']:.2f} |"
            )
    lines += [
        "",
        "| scenario | matches tried | closures accepted | closures rejected | front+back end ms/keyframe | wall s |",
        "|---|---|---|---|---|---|",
    ]
    for key in keys:
        s = results[key]
        lines.append(
            f"| {key.replace('_', '-')} | {s['matches_tried']} | {s['closures_accepted']} | "
            f"{s['closures_rejected']} | {s['per_keyframe_ms']:.1f} | {s['wall_s']:.0f} |"
        )
    if "memory" in results:
        lines += ["", "| frames | peak RSS MB | wall s |", "|---|---|---|"]
        for n, m in results["memory"].items():
            lines.append(f"| {n} | {m['peak_rss_mb']:.0f} | {m['wall_s']:.0f} |")
    return "\n".join(lines) + "\n"
