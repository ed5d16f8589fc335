"""Cost with the number of robots (``shgm-slam bench robots``).

``bench scale`` measures how the cost grows with distance; this measures how it grows with the fleet.
A whole KITTI sequence as a ``kitti-paths`` world (default 00: ``bench scale``'s world, 4541 frames,
3.7 km, a generated city; 320x96) is cut into ``STRETCHES`` contiguous stretches of equal frames (about
460 m each on 00); 00 comes back to its own streets many times, so some later stretches drive where
earlier ones did, and others nowhere near any other. For each fleet size N the first N stretches are run
**at once** (every robot's clock starts at its first frame, so N robots drive the same 57 s side by side)
by ``run_slam`` with the default configuration and no viewer. Per fleet size: the keyframes of all
robots, the time per keyframe of the front end, graph matching and the pose graph
(``run_report.FrameStats``), the matches tried per keyframe and their mean cost, the CPU the whole fleet
needs per second of driving (one process runs every robot's front end and the server; below 1 it keeps
up in real time on one core), and the peak memory of the same run alone in a fresh process. Side by side
in one invocation, so the ratios between fleet sizes are measured on one machine under one load.

Many robots are also a test of correctness: every pair is a chance for a false match. Each stretch's
path within ``OVERLAP_M`` of another's (ground truth) says which robots could be placed at all; the
robots placed within ``PLACED_RIGHT_M`` (as ``bench heldout`` judges placement) or farther (wrong), and the
accepted graph matches judged at their own place (``match_truth``: farther off than ``GROSS_ERROR_M`` is an
alias) come from the run's journal. Nothing here prints; the CLI renders the dict.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.bench.heldout_judge import GROSS_ERROR_M, InputMode, placement_errors, poses_by_time
from shgm_slam.bench.heldout_judge import PLACED_RIGHT_M as PLACED_RIGHT_BY_MODE_M
from shgm_slam.bench.match_truth import judge_matches
from shgm_slam.bench.report import write_report
from shgm_slam.bench.scale import StepCost
from shgm_slam.bench.stopping import run_to_end
from shgm_slam.bench.system import _world, peak_rss_runs
from shgm_slam.config import ShgmConfig
from shgm_slam.errors import ConfigError
from shgm_slam.robot.remote import default_jobs
from shgm_slam.run_report import FrameStats
from shgm_slam.runner import open_robots
from shgm_slam.types import Sequence

Progress = Callable[[str], None]

SCALE_DRIVES = ("00", "07")
"""KITTI drives of ``bench scale``'s world: cutting 00 reuses it (rendered once for both benchmarks)."""
SEQUENCE = "00"
"""The KITTI sequence cut into robots by default."""
OVERLAP_M = 10.0
"""A stretch overlaps another where its ground-truth path passes within this of the other's."""
OVERLAP_MIN_M = 40.0
"""... along at least this much of its path: enough shared street for a graph match to stand on."""
PLACED_RIGHT_M = PLACED_RIGHT_BY_MODE_M[InputMode.FILES]
"""A placed robot is right when its placement error (``placement_errors``) is within this (rendered depth)."""
STRETCHES = 8
"""Equal stretches 00 is cut into: the largest fleet."""
FLEETS = (1, 2, 4, 8)
"""Fleet sizes run by default (1: the cost of one robot without any partner to match)."""


class FleetCost(StepCost):
    """Sums over every step of one fleet's run (all robots); a ``run_slam`` ``on_frame`` callback."""

    def __call__(self, s: FrameStats) -> None:
        self.add(s)

    def row(self, robots: int, driven_s: float) -> dict:
        """Per-keyframe costs (ms) of the fleet; ``driven_s`` the seconds the fleet drove (its longest robot)."""
        n = max(self.keyframes, 1)
        return {
            "robots": robots,
            "frames": self.frames,
            "keyframes": self.keyframes,
            "front_end_ms_per_kf": self.front_end_ms / n,
            "match_ms_per_kf": self.match_ms / n,
            "backend_ms_per_kf": self.backend_ms / n,
            "server_other_ms_per_kf": (self.server_ms - self.match_ms - self.backend_ms) / n,
            "total_ms_per_kf": (self.step_ms - self.load_ms) / n,
            "cpu_ms_per_kf": self.cpu_ms / n,
            "matches_per_kf": self.matches / n,
            "ms_per_match": self.match_ms / self.matches if self.matches else 0.0,
            "nodes_per_match": float(np.mean(self.match_nodes)) if self.match_nodes else 0.0,
            "cpu_s_per_driven_s": self.cpu_ms / 1e3 / driven_s if driven_s > 0 else float("nan"),
        }


def stretch_specs(sequence: Path, frames: int, stretches: int = STRETCHES) -> list[str]:
    """``NAME=PATH:a-b`` robot specs of ``stretches`` contiguous, equal, half-open frame ranges of the
    ``frames`` frames of the rendered ``sequence`` folder (names r1, r2, ...; the last frames that do not
    fill a stretch are left out).

    Raises:
        ConfigError: fewer frames than stretches.
    """
    size = frames // stretches
    if size < 1:
        raise ConfigError(f"{sequence.name} has {frames} frames: too few to cut into {stretches} robots")
    return [f"r{i + 1}={sequence}:{i * size}-{(i + 1) * size}" for i in range(stretches)]


def overlaps_m(paths_xyz: list[np.ndarray], within_m: float = OVERLAP_M) -> np.ndarray:
    """(R, R) metres of robot i's path (ground truth, (N_i, 3) positions in one world frame) that pass
    within ``within_m`` of robot j's path (0 on the diagonal; not symmetric)."""
    r = len(paths_xyz)
    out = np.zeros((r, r))
    for i, p in enumerate(paths_xyz):
        step = np.r_[0.0, np.linalg.norm(np.diff(p, axis=0), axis=1)]
        for j, q in enumerate(paths_xyz):
            if i != j:
                near = cKDTree(q).query(p, distance_upper_bound=within_m)[0] < within_m
                out[i, j] = step[near].sum()
    return out


def overlapping(overlap_m: np.ndarray, min_m: float = OVERLAP_MIN_M) -> np.ndarray:
    """(R,) bool: robot i shares at least ``min_m`` of street (either way) with some robot that is itself
    connected to robot 0 (r1, the shared frame) through such pairs: the robots that could be placed."""
    linked = np.maximum(overlap_m, overlap_m.T) >= min_m
    reach = np.zeros(len(overlap_m), dtype=bool)
    if len(reach):
        reach[0] = True
    grown = True
    while grown:
        new = reach | linked[reach].any(axis=0)
        grown = bool((new != reach).any())
        reach = new
    return reach


def placement(summary_json: dict, can_place: dict[str, bool], run_dir: Path, robots: dict[str, Sequence]) -> dict:
    """How the fleet was placed, judged as ``bench heldout`` judges (``placement_errors``): robots that
    could be placed (``can_place``: name -> bool, the reference included), placed right (the best rigid fit of
    its trajectory, the shared frame's gauge fixed by the reference r1, moves it less than ``PLACED_RIGHT_M``;
    r1 itself: its gauge-fixed fused ATE within that), placed wrong (farther; robots that could not be placed
    count here too when placed), not placed; the fused ATE in the shared frame, median and max over the placed.

    Args:
        summary_json: the run's ``metrics.json`` content.
        can_place: robot -> whether it shares enough street with a robot linked to r1.
        run_dir: the run's results folder (its ``<robot>_fused_tum.txt``).
        robots: robot -> its sequence (ground truth in the world frame), in run order.
    """
    reports = {r["name"]: r for r in summary_json["robots"]}
    names = [n for n in robots if n in can_place]
    fused = [poses_by_time(run_dir / f"{n}_fused_tum.txt", np.asarray(robots[n].timestamps_s)) for n in names]
    errors = dict(zip(names, placement_errors(fused, [robots[n].gt_poses for n in names]), strict=True))
    placed = [n for n in names if reports[n]["localized"]]
    right = [
        n for n in placed
        if can_place[n] and (errors[n].ate_m if n == names[0] else errors[n].placement_m) <= PLACED_RIGHT_M
    ]  # fmt: skip
    ates = [reports[n]["ate_fused_m"] for n in placed if np.isfinite(reports[n]["ate_fused_m"])]
    return {
        "can_place": sum(can_place.values()),
        "placed": len(placed),
        "placed_right": len(right),
        "placed_wrong": len(placed) - len(right),
        "not_placed_could": sum(1 for n in names if can_place[n] and not reports[n]["localized"]),
        "placement_m": {n: errors[n].placement_m for n in placed},
        "fused_ate_median_m": float(np.median(ates)) if ates else float("nan"),
        "fused_ate_max_m": float(np.max(ates)) if ates else float("nan"),
        "matches_tried": summary_json["matches_tried"],
        "closures_accepted": summary_json["closures_accepted"],
        "wall_s": summary_json["wall_s"],
    }


def run_robots_benchmark(
    out: Path,
    *,
    fleets: tuple[int, ...] = FLEETS,
    sequence: str = SEQUENCE,
    cache: Path = Path("cache"),
    seed: int = 0,
    resolution: tuple[int, int] = (320, 96),
    kitti_root: Path | None = None,
    memory: bool = True,
    jobs: int | None = None,
    config: ShgmConfig | None = None,
    progress: Progress | None = None,
) -> dict:
    """Run the fleet-size benchmark; writes ``out/robots.json`` and ``out/robots.md`` and returns the dict.

    The world (simulated once into ``cache`` and reused; for 00 ``bench scale``'s) holds the whole KITTI
    ``sequence``; fleet N's results folder is ``out/fleet_N`` (with its journal, for judging the matches),
    its memory run's ``out/memory_N``. Every fleet of two or more also runs again right after with its front
    ends in ``min(N, jobs)`` worker processes (``run --jobs``; None: the cores), into ``out/fleet_N_jobs``:
    its wall time beside the one-process run's and whether every results file came out the same; with
    ``memory``, the largest fleet's memory run is repeated that way (``out/memory_N_jobs``).

    A Ctrl-C ends it after writing the fleets finished (``interrupted`` true; each stopped run keeps its own
    results folder); stopped in the first fleet, the KeyboardInterrupt is raised again.

    Raises:
        ConfigError: a fleet size outside 1..``STRETCHES``, or a sequence that is not KITTI 00-10.
    """
    bad = [n for n in fleets if not 1 <= n <= STRETCHES]
    if bad or not fleets:
        given = f"{','.join(map(str, fleets))}: {', '.join(map(str, bad))} outside" if fleets else "names no size in"
        raise ConfigError(f"--fleets {given} 1..{STRETCHES} (the sequence is cut into {STRETCHES} robots); give "
                          "comma-separated fleet sizes in that range, e.g. 1,2,4,8")  # fmt: skip
    if sequence not in {f"{k:02d}" for k in range(11)}:
        raise ConfigError(f"--sequence {sequence!r}: choose a KITTI odometry sequence with ground truth, 00-10")
    progress = progress or (lambda _msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config or ShgmConfig()
    drives = SCALE_DRIVES if sequence == SCALE_DRIVES[0] else (sequence,)
    world = _world(cache / "bench", "kitti-paths", seed, progress, resolution=resolution, kitti_robots=drives,
                   **({"kitti_root": kitti_root} if kitti_root is not None else {}))  # fmt: skip
    source = world / f"kitti{sequence}"
    frames = len(open_robots([f"whole={source}"])["whole"])
    specs = stretch_specs(source, frames)
    everyone = open_robots(specs)
    overlap = overlaps_m([seq.gt_poses[:, :3, 3] for seq in everyone.values()])
    rows: list[dict] = []
    interrupted = False
    try:  # a stopped fleet ends the benchmark; the fleets finished are kept
        for n in sorted(set(fleets)):
            robots = {name: everyone[name] for name in list(everyone)[:n]}
            can = dict(zip(robots, overlapping(overlap[:n, :n]).tolist(), strict=True))
            driven_s = max(float(seq.timestamps_s[-1] - seq.timestamps_s[0]) for seq in robots.values())
            progress(f"running {n} robot(s) at once")
            cost = FleetCost()
            summary = run_to_end(robots, cfg, out / f"fleet_{n}", on_frame=cost, journal=True)
            truth = judge_matches(out / f"fleet_{n}", {k: v.gt_poses for k, v in robots.items()}, PLACED_RIGHT_M,
                                  GROSS_ERROR_M)  # fmt: skip
            row = {**cost.row(n, driven_s), **placement(summary.to_json_dict(), can, out / f"fleet_{n}", robots),
                   "accepted_judged": truth.accepted, "accepted_gross": truth.gross,
                   "anchorings": truth.anchorings, "anchorings_gross": truth.anchorings_gross}  # fmt: skip
            workers = min(n, default_jobs(n, jobs))
            if workers > 1:
                progress(f"running {n} robot(s) at once again, front ends in {workers} worker processes")
                again = run_to_end(robots, cfg, out / f"fleet_{n}_jobs", on_frame=FleetCost(), journal=True,
                                   jobs=workers)
                row |= {"jobs": workers, "jobs_wall_s": again.wall_s, "jobs_speedup": summary.wall_s / again.wall_s,
                        "jobs_same_results": same_results(out / f"fleet_{n}", out / f"fleet_{n}_jobs")}  # fmt: skip
            rows.append(row)
    except KeyboardInterrupt:
        if not rows:
            raise
        interrupted = True
    base = rows[0]
    for r in rows:
        r["total_per_kf_over_smallest"] = r["total_ms_per_kf"] / base["total_ms_per_kf"]
        r["cpu_per_kf_over_smallest"] = r["cpu_ms_per_kf"] / base["cpu_ms_per_kf"]
    results: dict = {"world": str(world), "sequence": sequence, "seed": seed, "stretch_frames": frames // STRETCHES,
                     "stretches": specs, "overlap_m": overlap.round(0).tolist(), "fleets": rows,
                     "interrupted": interrupted}  # fmt: skip
    if memory and not interrupted:
        runs: list[tuple[str, str | list[str], str]] = [(str(r["robots"]), specs[: r["robots"]],
                                                          f"memory_{r['robots']}") for r in rows]  # fmt: skip
        try:
            results["memory"] = peak_rss_runs(out, runs, progress, extra_args=("--jobs", "1"))
            last = rows[-1]
            if last.get("jobs"):
                results["memory_jobs"] = peak_rss_runs(
                    out, [(str(last["robots"]), specs[: last["robots"]], f"memory_{last['robots']}_jobs")],
                    progress, extra_args=("--jobs", str(last["jobs"])))  # fmt: skip
        except KeyboardInterrupt:  # the fleets' rows are complete; the memory runs are left out
            results["interrupted"] = True
    write_report(out, "robots", results, robots_markdown)
    return results


def same_results(a: Path, b: Path) -> bool:
    """Two results folders hold the same trajectories (every ``*.txt``), pose graph and ``metrics.json``
    (timings aside), byte for byte."""
    files = sorted(p.name for p in Path(a).iterdir() if p.suffix in (".txt", ".g2o"))
    if files != sorted(p.name for p in Path(b).iterdir() if p.suffix in (".txt", ".g2o")):
        return False
    if any((Path(a) / f).read_bytes() != (Path(b) / f).read_bytes() for f in files):
        return False
    ma, mb = (json.loads((Path(d) / "metrics.json").read_text()) for d in (a, b))
    for m in (ma, mb):
        for k in ("timings_ms", "wall_s", "per_keyframe_ms"):
            m.pop(k, None)
    return ma == mb


def robots_markdown(results: dict) -> str:
    """The benchmark's table as markdown (what the README shows)."""
    lines = [
        ("**Interrupted**: the fleets finished before the stop (and no memory runs).\n\n"
         if results.get("interrupted") else "") +
        f"KITTI {results.get('sequence', SEQUENCE)} cut into {len(results['stretches'])} stretches of "
        f"{results['stretch_frames']} frames; the first N driving at once. Cost per keyframe of the whole fleet (ms).",
        "",
        "| robots | keyframes | front end | matching | pose graph | server other | total | CPU | vs smallest "
        "| matches / kf | ms / match | nodes / match | CPU s per s driven | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    memory = results.get("memory", {})
    for r in results["fleets"]:
        rss = memory.get(str(r["robots"]), {}).get("peak_rss_mb")
        lines.append(
            f"| {r['robots']} | {r['keyframes']} | {r['front_end_ms_per_kf']:.1f} | {r['match_ms_per_kf']:.1f} | "
            f"{r['backend_ms_per_kf']:.1f} | {r['server_other_ms_per_kf']:.1f} | {r['total_ms_per_kf']:.1f} | "
            f"{r['cpu_ms_per_kf']:.1f} | {r['total_per_kf_over_smallest']:.2f} | {r['matches_per_kf']:.2f} | "
            f"{r['ms_per_match']:.1f} | {r['nodes_per_match']:.0f} | {r['cpu_s_per_driven_s']:.2f} | "
            f"{'-' if rss is None else f'{rss:.0f}'} |"
        )
    timed = [r for r in results["fleets"] if r.get("jobs")]
    if timed:
        lines += ["", "The same fleets again with the front ends in worker processes (`run --jobs`), right after: "
                  "wall time of the whole run.", "",
                  "| robots | one process s | worker processes | s | faster | the same results |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        lines += [f"| {r['robots']} | {r['wall_s']:.1f} | {r['jobs']} | {r['jobs_wall_s']:.1f} | "
                  f"{r['jobs_speedup']:.2f}x | {'yes' if r['jobs_same_results'] else '**no**'} |" for r in timed]
        for label, m in results.get("memory_jobs", {}).items():
            one = memory.get(label, {}).get("peak_rss_mb")
            lines += ["", f"Peak memory of the {label}-robot fleet with its front ends in {timed[-1]['jobs']} worker "
                      f"processes: {m['peak_rss_mb']:.0f} MB, all processes together "
                      f"({'-' if one is None else f'{one:.0f}'} MB in one process)."]  # fmt: skip
    lines += [
        "",
        f"Placement (could be placed: shares >= {OVERLAP_MIN_M:.0f} m of street with a robot linked to r1; right: "
        f"the best rigid fit of its fused trajectory, the shared frame's gauge fixed by r1's, moves it less than "
        f"{PLACED_RIGHT_M:.0f} m (where it was placed, not its own drift; r1: its fused ATE so aligned within that), "
        f"as `bench heldout` judges; fused ATE: in the shared frame, unaligned; aliases: accepted matches more than "
        f"{GROSS_ERROR_M:.0f} m off at their place).",
        "",
        "| robots | could be placed | placed right | placed wrong | not placed (of those that could) "
        "| fused ATE median / max m | matches tried | accepted | of them aliases | placements through an alias |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["fleets"]:
        lines.append(
            f"| {r['robots']} | {r['can_place']} | {r['placed_right']} | {r['placed_wrong']} | "
            f"{r['not_placed_could']} | "
            f"{r['fused_ate_median_m']:.2f} / {r['fused_ate_max_m']:.2f} | {r['matches_tried']} | "
            f"{r['accepted_judged']} | {r['accepted_gross']} | "
            f"{r['anchorings_gross']}/{'?' if r['anchorings'] is None else r['anchorings']} |"
        )
    return "\n".join(lines) + "\n"
