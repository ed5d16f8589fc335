"""Held-out evaluation (``shgm-slam bench heldout``): the system on many worlds nobody tuned it on.

For every scenario (airsim-like, disjoint, synthia-like, kitti-paths) and every world seed, the
world is rendered once into a cache and the whole system runs with the **default configuration**:
on the rendered depth and labels (``files``: KISS-ICP odometry) and from RGB alone (``rgb``: the demo
ONNX models). Each robot of each world is then judged against ground truth (``heldout_judge``; the
tables: ``heldout_summary``):

* ``right``: placed in the shared frame within ``PLACED_RIGHT_M`` of its mode (2 m from files, 5 m
  from RGB): the rigid transform that best lays its fused trajectory onto the truth (the shared frame's
  gauge fixed by the reference's trajectory, see ``judge_run``) moves it less than that; its fused ATE,
  which adds its own odometry drift, is reported beside it; or, for a robot that shares no view with
  any other robot (the disjoint worlds), correctly left apart;
* ``wrong``: placed, but farther than that (a false merge);
* ``not placed``: an overlapping robot that never joined the shared frame.

The first robot defines the shared frame; it is not placed by matching, so it is counted apart
(``reference within``: its own fused ATE, aligned, against the tolerance, which catches its own odometry
drifting or failing).

Odometry failures: the system reports the divergences it detected (``metrics.json``; each cuts the
trajectory into a new segment), and ground truth shows the ones it missed: ``odometry_breaks`` counts
1 s windows of the reported odometry, inside one segment, whose motion is grossly wrong.

Tuning and report seeds must be disjoint (README): the defaults are tuned on ``TUNING_SEEDS`` and
reported on ``REPORT_SEEDS``. Every finished run is cached as JSON, so an interrupted benchmark
resumes where it stopped. Nothing here prints; the CLI renders the returned dict.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import shutil
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from shgm_slam.agents import agent_robot
from shgm_slam.bench.heldout_judge import GROSS_ERROR_M, PLACED_RIGHT_M, InputMode, judge_run
from shgm_slam.bench.heldout_summary import heldout_markdown, summarize
from shgm_slam.bench.match_truth import judge_matches
from shgm_slam.bench.report import write_report
from shgm_slam.bench.stopping import run_to_end
from shgm_slam.config import ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.demo import demo_model_paths
from shgm_slam.environment import environment
from shgm_slam.errors import ConfigError, DataError, RunError, SimulationError
from shgm_slam.io.json_text import to_json_text
from shgm_slam.robot.remote import default_jobs
from shgm_slam.runner import open_robots, replay_backend
from shgm_slam.server.map_server import MapServer
from shgm_slam.sim.cache import simulate_cached
from shgm_slam.sim.corruption import CorruptionLevels
from shgm_slam.sim.simulate import DEFAULT_MAX_DEPTH_M

SCENARIOS = ("airsim-like", "disjoint", "synthia-like", "kitti-paths")
TUNING_SEEDS = tuple(range(10, 30))
"""World seeds the defaults may be tuned on (plus 0 and 1, used by earlier sessions; 20-29 since the
anchoring rule, README)."""
REPORT_SEEDS = tuple(range(210, 220))
"""World seeds the README reports; never looked at while tuning."""
RESOLUTION = (320, 96)
"""Render size: the demo models' input size, and fast enough for ~80 runs in an hour on 2 cores."""
FPS = 10.0
"""Frame rate the worlds are rendered at, Hz (the simulator's default, KITTI's rate; every default was tuned at it)."""
MAX_FPS = 100.0
"""Highest frame rate a benchmark may ask for, Hz (as ``simulate --fps``)."""
MAX_DEPTH_M = DEFAULT_MAX_DEPTH_M
"""Depth range the worlds are rendered with (the simulator's; a UAV's altitude must keep its ground within it)."""
KITTI_DRIVE_PAIRS = (
    ("00:2600-2901", "07:0-351"),  # the same street on two days (the scenario's default)
    ("00:546-763", "08:0-301"),
    ("09:333-593", "10:0-301"),
    ("00:1369-1590", "08:3450-3751"),
    ("00:378-629", "08:1950-2251"),  # driven in opposite directions
    ("09:392-572", "10:900-1201"),
    ("00:385-624", "08:1200-1501"),
)
"""kitti-paths drive pairs, one per world seed in turn: real KITTI motion, 83-258 m of shared street once
laid into one world by ``sim.kitti_paths.align_drive`` (found by aligning 300-frame pieces of 08 and 10
onto 00 and 09; the generated city grows around both drives). Frame ranges are half-open (END excluded):
the ends are the inclusive ends these worlds were first rendered with, plus one."""


Progress = Callable[[str], None]


@dataclass(frozen=True)
class HeldoutOptions:
    """What to run. ``max_frames`` cuts every robot's sequence (quick runs)."""

    scenarios: tuple[str, ...] = SCENARIOS
    seeds: tuple[int, ...] = REPORT_SEEDS
    modes: tuple[InputMode, ...] = (InputMode.FILES, InputMode.RGB)
    resolution: tuple[int, int] = RESOLUTION
    max_frames: int | None = None
    cache: Path = Path("cache/heldout")
    supersample: int = 1
    """Rays per pixel side of the rendered colour (``sim.render.Renderer``; worlds of another value are cached
    apart)."""
    uav_altitude_m: tuple[float, float] | None = None
    """airsim-like worlds: the UAV's altitude range, metres (None: the simulator's 44-54 m; other ranges are
    cached apart). Every default was tuned on UAVs at 44-54 m: this asks how they hold higher up."""
    corruption: CorruptionLevels = field(default_factory=CorruptionLevels)
    """Depth and label corruption of the rendered frames (``sim.corruption``; none by default, other levels are
    cached apart): the files mode then reads noisy depth and labels, as from a stereo camera or a LiDAR with a
    segmentation network, between perfect renders and the RGB mode's predictions. Every default was chosen on
    perfect renders and on the demo models: this asks how they hold in between."""
    replay_from: Path | None = None
    """An earlier benchmark folder: run only the map server again on each run's recorded keyframes
    (``runner.replay_backend``), for matching and back-end changes; worlds are not rendered or run."""
    kitti_root: Path | None = None
    """KITTI folder with ``poses/`` for the kitti-paths worlds (None: ``sim.kitti_paths.DEFAULT_KITTI_ROOT``, the
    checkout's ``../shared/data/kitti``)."""
    front_end_jobs: int | None = 1
    """Worker processes for each run's robot front ends (``run_slam(jobs=...)``; None: one per robot up to the
    cores, ``remote.default_jobs``): the same results, sooner when the worlds run one at a time."""
    fps: float = FPS
    """Frame rate the worlds are rendered at, Hz (other rates are cached apart): every default was tuned at 10 Hz;
    this asks how they hold on KITTI subsampled to every 2nd or 3rd frame (5, 3.3 Hz), as kitti-paths worlds then
    are (``sim.kitti_paths.at_frame_rate``)."""

    def __post_init__(self) -> None:
        """Raises ConfigError: ``fps`` not a finite rate above 0 and at most ``MAX_FPS`` (the simulator would refuse
        every world, and each would be skipped as one that cannot be built)."""
        if not (math.isfinite(self.fps) and 0.0 < self.fps <= MAX_FPS):
            raise ConfigError(f"frame rate {self.fps} Hz: give a finite rate above 0 and at most {MAX_FPS:g} (--fps)")


def world_folder(
    cache: Path, scenario: str, seed: int, resolution: tuple[int, int], supersample: int = 1,
    uav_altitude_m: tuple[float, float] | None = None, corruption: CorruptionLevels | None = None,
    fps: float = FPS,
) -> Path:  # fmt: skip
    """Where the world ``scenario``/``seed`` is cached: ``cache/<scenario>-s<seed>-<W>x<H>`` (``-ss<S>`` added
    for S x S rays per pixel, ``-uav<LO>-<HI>`` for an airsim-like UAV at another altitude, ``-d<D>-l<L>`` for
    frames corrupted by ``CorruptionLevels.from_levels(D, L)``, ``-fps<F>`` for frames at F Hz other than
    ``FPS``: ``-fps5``, ``-fps3.3``)."""
    tail = f"-ss{supersample}" if supersample > 1 else ""
    altitude = _uav_altitude(scenario, uav_altitude_m)
    if altitude is not None:
        tail += f"-uav{altitude[0]:g}-{altitude[1]:g}"
    if corruption is not None and corruption.active:
        tail += f"-d{corruption.depth_noise:g}-l{corruption.label_confusion:g}"
    if fps != FPS:
        tail += f"-fps{_compact(fps)}"
    return Path(cache) / f"{scenario}-s{seed}-{resolution[0]}x{resolution[1]}{tail}"


def _compact(value: float) -> str:
    """``value`` written short and exactly (``5``, ``3.3``, ``3.3333333333333335``): two values never share a
    text (``:g`` keeps six digits), and no exponent for the frame rates asked (0.1-100)."""
    return repr(float(value)).removesuffix(".0")


def _uav_altitude(scenario: str, uav_altitude_m: tuple[float, float] | None) -> tuple[float, float] | None:
    """The UAV altitude a world of ``scenario`` is rendered with (only airsim-like has a UAV)."""
    return uav_altitude_m if scenario == "airsim-like" else None


def ensure_world(
    cache: Path, scenario: str, seed: int, resolution: tuple[int, int], progress: Progress, supersample: int = 1,
    uav_altitude_m: tuple[float, float] | None = None, corruption: CorruptionLevels | None = None,
    kitti_root: Path | None = None, fps: float = FPS,
) -> Path:  # fmt: skip
    """Render the world once (cached; ``kitti_root``: the KITTI poses of kitti-paths worlds; ``fps``: frames per
    second, Hz); returns its folder."""
    folder = world_folder(cache, scenario, seed, resolution, supersample, uav_altitude_m, corruption, fps)
    if not (folder / "scenario.json").is_file():
        progress(f"rendering {scenario} seed {seed} into {folder}")
        pair = KITTI_DRIVE_PAIRS[seed % len(KITTI_DRIVE_PAIRS)] if scenario == "kitti-paths" else None
        simulate_cached(scenario, folder, seed=seed, resolution=resolution, kitti_robots=pair,
                        supersample=supersample, uav_altitude_m=_uav_altitude(scenario, uav_altitude_m),
                        max_depth_m=MAX_DEPTH_M, corruption=corruption, fps=fps,
                        **({} if kitti_root is None else {"kitti_root": kitti_root}))  # fmt: skip
    return folder


def heldout_config(mode: InputMode) -> ShgmConfig:
    """The default configuration; RGB mode only adds the demo models (nothing tuned per world).

    Raises:
        DataError: RGB mode but the demo models are found nowhere (``demo.demo_model_paths``).
    """
    cfg = ShgmConfig()
    if mode is InputMode.RGB:
        cfg.perception.depth_model, cfg.perception.seg_model = demo_model_paths()
    return ShgmConfig.model_validate(cfg.model_dump())


def _robots_of(world: Path) -> list[str]:
    return [r["name"] for r in json.loads((world / "scenario.json").read_text())["robots"]]


def run_one(world: Path, mode: InputMode, run_dir: Path, max_frames: int | None, jobs: int | None = 1) -> dict:
    """Run the system once on ``world`` with the default configuration (front ends in ``jobs`` worker
    processes, ``remote.default_jobs``); returns ``metrics.json``'s dict.

    Raises:
        RunStopped: the run was stopped (Ctrl-C): it is neither judged nor cached, so a resume runs it again.
        RunError: a robot's front end was lost mid-run (its worker died or failed on an error): its robot would
            count as not placed, a fault of the program or the machine judged as the system's verdict. Neither
            judged nor cached: the benchmark stops, and once the fault is fixed a resume runs it again.
    """
    names = _robots_of(world)
    cut = f":0-{max_frames}" if max_frames else ""
    robots = open_robots([f"{r}={world / r}{cut}" for r in names])
    summary = run_to_end(robots, heldout_config(mode), run_dir, journal=True, jobs=default_jobs(len(robots), jobs))
    if summary.front_ends_lost:
        raise RunError(f"{run_dir.name}: a robot's front end was lost {summary.front_ends_lost[0]}; the run is "
                           "not judged (its robots would count as not placed): fix the fault, then run the same "
                           "benchmark again to resume")  # fmt: skip
    return json.loads(json.dumps(summary.to_json_dict(), default=float))


def replay_one(recorded: Path, mode: InputMode, run_dir: Path, robots: list[str]) -> dict:
    """The map server alone, again, on the keyframes of the recorded run ``recorded``; returns its
    ``metrics.json`` dict: the recorded front-end facts (segments, failures, path lengths) with this
    back end's matches and closures."""
    cfg = heldout_config(mode)
    cfg = cfg.model_copy(update={"backend": cfg.backend.for_depth(predicted_depth=mode is InputMode.RGB)})
    node = replay_backend(recorded, cfg, run_dir, robots)
    metrics = json.loads((Path(recorded) / "metrics.json").read_text())
    matches = node.map.matches
    metrics["matches_tried"] = len(matches)
    metrics["closures_accepted"] = sum(m.accepted for m in matches)
    metrics["closures_rejected"] = sum(m.success and not m.accepted and not m.duplicate for m in matches)
    metrics["replayed_from"] = str(recorded)
    metrics["recorded_environment"] = metrics.get("environment")  # the front ends ran there, this back end here
    metrics["environment"] = environment()
    _replace_placement_facts(metrics, node.map)
    for gt in Path(recorded).glob("*_gt_*.txt"):
        (Path(run_dir) / gt.name).write_bytes(gt.read_bytes())
    (Path(run_dir) / "metrics.json").write_text(to_json_text(metrics) + "\n")
    return metrics


def _replace_placement_facts(metrics: dict, server: MapServer) -> None:
    """The recorded run's placement facts in its ``metrics`` (each robot's ``provisional`` flag, its waiting
    and provisional lines among its warnings, its ``path_from_closures_m``, the ``last_looks``) replaced by what the
    replayed ``server`` decided: the judge reads them, and stale lines would describe the recorded back end."""
    metrics["last_looks"] = server.last_looks()
    for rep in metrics.get("robots", []):
        mine = [a for a in server.agents if agent_robot(a)[0] == rep.get("name")]
        stale = tuple(f"{a} is {what}" for a in mine for what in ("not placed in the shared frame",
                                                                  "placed provisionally"))  # fmt: skip
        lines = [w for w in rep.get("warnings", []) if not str(w).startswith(stale)]
        rep["warnings"] = lines + [note for a in mine if (note := server.placement_note(a)) is not None]
        rep["provisional"] = any(server.placement(a).provisional for a in mine)
        rep["path_from_closures_m"] = server.longest_path_from_closures_m(mine)


def _match_truth(run_dir: Path, world: Path, mode: InputMode) -> dict:
    """The run's accepted matches judged at their own place (``match_truth``), as a JSON-friendly dict."""
    gt = {name: open_sequence(str(world / name)).gt_poses for name in _robots_of(world)}
    return vars(judge_matches(run_dir, gt, PLACED_RIGHT_M[mode], GROSS_ERROR_M))


def _world_runs(scenario: str, seed: int, options: HeldoutOptions, out: Path, progress: Progress) -> list[dict]:
    """Render one world (cached) and run every mode on it; returns one dict per run (cached as JSON), or one
    ``{"scenario", "seed", "skipped"}`` dict when the world cannot be built as asked (a UAV altitude below this
    city's roofs): the other worlds' runs and the summary are kept, and the report lists the world skipped."""
    try:
        world = ensure_world(options.cache, scenario, seed, options.resolution, progress, options.supersample,
                             options.uav_altitude_m, options.corruption, options.kitti_root, options.fps)
    except SimulationError as exc:
        progress(f"skipping {scenario} seed {seed}: {exc}")
        return [{"scenario": scenario, "seed": seed, "skipped": str(exc)}]
    done_runs = []
    for mode in options.modes:
        run_dir = out / "runs" / f"{scenario}-s{seed}-{mode.value}"
        cached = run_dir / "verdicts.json"
        if cached.is_file():  # judged again: the judge may have changed, the run has not
            done = json.loads(cached.read_text())
            metrics = json.loads((run_dir / "metrics.json").read_text())
            verdicts = judge_run(run_dir, world, _robots_of(world), mode, scenario, seed, metrics)
            done_runs.append({**done, "matches": _match_truth(run_dir, world, mode),
                              "verdicts": [vars(v) for v in verdicts]})
            continue
        t_run = time.perf_counter()
        if options.replay_from is not None:
            progress(f"replaying {scenario} seed {seed} ({mode.value})")
            recorded = Path(options.replay_from) / "runs" / run_dir.name
            if not recorded.is_dir():
                held = sorted(p.name for p in recorded.parent.glob("*"))
                raise DataError(f"--replay-from {options.replay_from} has no run {run_dir.name} (its runs/ holds "
                                f"{len(held)}: {', '.join(held[:4]) or 'none'}{', ...' if len(held) > 4 else ''}); "
                                "give the recorded benchmark's --seeds, --scenario and --mode")  # fmt: skip
            metrics = replay_one(recorded, mode, run_dir, _robots_of(world))
        else:
            progress(f"running {scenario} seed {seed} ({mode.value})")
            if run_dir.exists():
                # a run that was stopped, or finished but not judged, runs again from the start: a finished run's
                # journal would recover a map server that finishes before the robots say hello, and refuses them
                shutil.rmtree(run_dir)
            metrics = run_one(world, mode, run_dir, options.max_frames, options.front_end_jobs)
        verdicts = judge_run(run_dir, world, _robots_of(world), mode, scenario, seed, metrics)
        done = {
            "scenario": scenario, "seed": seed, "mode": mode.value,
            "wall_s": round(time.perf_counter() - t_run, 1),
            "matches_tried": metrics.get("matches_tried"),
            "closures_accepted": metrics.get("closures_accepted"),
            "per_keyframe_ms": metrics.get("per_keyframe_ms"),
            "matches": _match_truth(run_dir, world, mode),
            "verdicts": [vars(v) for v in verdicts],
        }  # fmt: skip
        cached.write_text(to_json_text({**done, "asked": run_options(options)}) + "\n")
        done_runs.append(done)
    return done_runs


def check_kitti_poses(options: HeldoutOptions) -> None:
    """Refuse (DataError, ConfigError: ``sim.kitti_paths.read_sequence_poses``) before any world is run when a
    kitti-paths world still to render lacks its KITTI ground truth; before, the benchmark ran every other world
    first and then stopped there."""
    from shgm_slam.sim.kitti_paths import DEFAULT_KITTI_ROOT, read_sequence_poses

    if "kitti-paths" not in options.scenarios or options.replay_from is not None:
        return
    sequences = set()
    for seed in options.seeds:
        folder = world_folder(options.cache, "kitti-paths", seed, options.resolution, options.supersample,
                              options.uav_altitude_m, options.corruption, options.fps)  # fmt: skip
        if not (folder / "scenario.json").is_file():
            sequences.update(d.split(":")[0] for d in KITTI_DRIVE_PAIRS[seed % len(KITTI_DRIVE_PAIRS)])
    for seq in sorted(sequences):
        read_sequence_poses(options.kitti_root or DEFAULT_KITTI_ROOT, seq)


def run_options(options: HeldoutOptions) -> dict:
    """What a run's results depend on beyond its world seed, scenario and mode (recorded with each cached run):
    the rendering (size, rays per pixel, UAV altitude, corruption, frame rate) and the frames run."""
    return {
        "resolution": list(options.resolution), "supersample": options.supersample,
        "uav_altitude_m": list(options.uav_altitude_m) if options.uav_altitude_m else None,
        "depth_noise": options.corruption.depth_noise, "label_noise": options.corruption.label_confusion,
        "fps": options.fps, "max_frames": options.max_frames,
    }  # fmt: skip


RENDER_FLAGS = {"resolution": "--resolution", "supersample": "--supersample", "uav_altitude_m": "--uav-altitude",
                "depth_noise": "--depth-noise", "label_noise": "--label-noise", "fps": "--fps"}  # fmt: skip
"""The ``run_options`` of the rendering, each with the ``bench heldout`` option that sets it."""


def _recorded_options(verdicts: Path) -> dict | None:
    """The ``run_options`` a cached run was made with (``verdicts.json``'s ``asked``), None for a run cached before
    they were recorded; a run recorded before the frame rate was had it at ``FPS``."""
    made = json.loads(verdicts.read_text()).get("asked")
    return None if made is None else {"fps": FPS, **made}


def check_resumable(out: Path, options: HeldoutOptions) -> None:
    """Refuse to resume into a folder whose cached runs were made with other options: their verdicts would be
    reported as this benchmark's (a resume reuses every run that has a ``verdicts.json``).

    Raises:
        ConfigError: a run of the worlds asked for was made with another resolution, rays per pixel, UAV
            altitude, corruption, frame rate or frame cut (runs cached before these were recorded are taken as they
            are).
    """
    asked = run_options(options)
    for scenario in options.scenarios:
        for seed in options.seeds:
            for mode in options.modes:
                cached = Path(out) / "runs" / f"{scenario}-s{seed}-{mode.value}" / "verdicts.json"
                if not cached.is_file():
                    continue
                made = _recorded_options(cached)
                if made is None or made == asked:
                    continue
                differ = ", ".join(f"{k} {made.get(k)} (asked: {v})" for k, v in asked.items() if made.get(k) != v)
                raise ConfigError(
                    f"{out} holds runs made with other options ({cached.parent.name}: {differ}); a resume would "
                    "report them as this benchmark's: choose another --out, or delete that folder's runs/"
                )


def check_replayable(options: HeldoutOptions) -> None:
    """Refuse to replay (``replay_from``) runs recorded on worlds rendered otherwise than asked: their keyframes
    would be judged against the asked worlds' ground truth (at another frame rate, other poses at other times) and
    reported under the asked options.

    Raises:
        ConfigError: a recorded run of the worlds asked for was made with another resolution, rays per pixel, UAV
            altitude, corruption or frame rate (runs recorded before these were recorded are taken as they are;
            ones recorded before the frame rate was, as at ``FPS``).
    """
    if options.replay_from is None:
        return
    asked = {k: v for k, v in run_options(options).items() if k in RENDER_FLAGS}
    for scenario in options.scenarios:
        for seed in options.seeds:
            for mode in options.modes:
                name = f"{scenario}-s{seed}-{mode.value}"
                cached = Path(options.replay_from) / "runs" / name / "verdicts.json"
                made = _recorded_options(cached) if cached.is_file() else None
                differ = [k for k, v in asked.items() if made is not None and made.get(k) != v]
                if differ:
                    raise ConfigError(
                        f"--replay-from {options.replay_from} holds runs made with other options ({name}: "
                        + ", ".join(f"{k} {made.get(k)} (asked: {asked[k]})" for k in differ)
                        + "); a replay would judge their keyframes against worlds rendered as asked: give the "
                        "recorded benchmark's " + ", ".join(RENDER_FLAGS[k] for k in differ)
                    )


def _quiet(_msg: str) -> None:
    pass


def _finished(future: Future) -> bool:
    """The future ran to its end without an exception (not cancelled, not stopped)."""
    return future.done() and not future.cancelled() and future.exception() is None


def run_heldout_benchmark(
    out: Path, options: HeldoutOptions, progress: Progress | None = None, *, jobs: int = 1
) -> dict:
    """Run (or resume) the held-out evaluation; writes ``out/heldout.json`` and ``out/heldout.md``.

    Each (scenario, seed, mode) run keeps its results folder under ``out/runs/`` and its verdicts in
    ``verdicts.json`` there; runs that already have one are not repeated. With ``jobs`` > 1 worlds
    run in that many worker processes at once (each world's modes stay in one worker).

    A Ctrl-C (KeyboardInterrupt, or a run stopped by one) ends the benchmark after writing the worlds
    finished, with ``interrupted`` true; the run it stopped is not cached, so the same command resumes it.
    Stopped before any world finished, the KeyboardInterrupt is raised again.
    """
    progress = progress or _quiet
    out = Path(out)
    check_resumable(out, options)
    check_replayable(options)
    check_kitti_poses(options)
    t0 = time.perf_counter()
    worlds = [(sc, seed) for sc in options.scenarios for seed in options.seeds]
    runs_by_world: list[list[dict]] = []
    interrupted = False
    if jobs > 1:
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(_world_runs, sc, seed, options, out, _quiet) for sc, seed in worlds]
            try:
                for k, f in enumerate(futures):
                    progress(f"world {k + 1}/{len(worlds)}: {worlds[k][0]} seed {worlds[k][1]}")
                    runs_by_world.append(f.result())
            except KeyboardInterrupt:  # a worker's run or this process stopped: keep the worlds finished
                interrupted = True
                for f in futures:
                    f.cancel()
                runs_by_world += [f.result() for f in futures[len(runs_by_world) + 1 :] if _finished(f)]
    else:
        try:
            for sc, seed in worlds:
                runs_by_world.append(_world_runs(sc, seed, options, out, progress))
        except KeyboardInterrupt:
            interrupted = True
    if interrupted and not runs_by_world:
        raise KeyboardInterrupt("stopped before any world was finished")
    skipped = [r for world_runs in runs_by_world for r in world_runs if "skipped" in r]
    done_runs = [r for world_runs in runs_by_world for r in world_runs if "skipped" not in r]
    runs = [{k: v for k, v in d.items() if k != "verdicts"} for d in done_runs]
    rows = [v for d in done_runs for v in d["verdicts"]]
    results = {
        "options": {
            "scenarios": list(options.scenarios), "seeds": list(options.seeds),
            "modes": [m.value for m in options.modes], **run_options(options),
            "tuning_seeds": list(TUNING_SEEDS),
            "report_seeds": list(REPORT_SEEDS), "placed_right_m": {m.value: v for m, v in PLACED_RIGHT_M.items()},
        },
        "summary": summarize(rows, runs),
        "runs": runs,
        "skipped_worlds": skipped,
        "robots": rows,
        "wall_s": round(time.perf_counter() - t0, 1),
        "interrupted": interrupted,
    }  # fmt: skip
    write_report(out, "heldout", results, heldout_markdown)
    return results
