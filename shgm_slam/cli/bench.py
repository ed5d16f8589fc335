"""The ``bench`` commands: each runs one benchmark library function and writes its JSON and markdown."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from shgm_slam.cli.app import bench_app, handle_errors, stops_like_ctrl_c
from shgm_slam.cli.maps import simulate_with_progress
from shgm_slam.cli.options import (
    MAX_FRAMES,
    NumberRange,
    bounded,
    distinct,
    float_in,
    int_list,
    number_range,
    out_file,
    results_folder,
    world_seeds,
)
from shgm_slam.cli.render import console, err_console, lit, print_report, warn_unused
from shgm_slam.config import DescriptorKind, OdometryKind
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE


@bench_app.command("simulate")
@handle_errors
@stops_like_ctrl_c
def bench_simulate(
    out: Annotated[Path, typer.Option("--out", "-o", parser=out_file,
                                      help="results JSON")] = Path("results/bench_sim.json"),
    resolution: Annotated[str, typer.Option(help="image size WIDTHxHEIGHT")] = "640x192",
    short_frames: Annotated[int, typer.Option(min=1, max=MAX_FRAMES, help="frames per robot, speed run")] = 40,
    long_frames: Annotated[int, typer.Option(min=1, max=MAX_FRAMES, help="frames per robot, memory run")] = 300,
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed")] = 0,
) -> None:
    """Simulator frames/s (render + PNG writing) and peak RSS of a short and a long airsim-like run."""
    from shgm_slam.bench.simulate import run_simulate_benchmark, simulate_markdown
    from shgm_slam.sim.simulate import parse_resolution

    results = run_simulate_benchmark(out, resolution=parse_resolution(resolution), short_frames=short_frames,
                                     long_frames=long_frames, seed=seed)
    print_report(simulate_markdown(results))
    console.print(f"wrote {lit(out)}")


@bench_app.command("localization")
@handle_errors
@stops_like_ctrl_c
def bench_localization(
    out: Annotated[Path, results_folder("results folder: localization.json, .md, pr_curve.png")]
    = Path("results/bench_localization"),
    runs: Annotated[int | None, typer.Option(min=1, max=100000,
                                             help="random transforms per configuration [100; quick 10]")]
    = None,
    quick: Annotated[bool, typer.Option("--quick", help="compact worlds at 320x96, fewer runs (~2 min)")] = False,
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed (defaults were tuned on seed 1)")] = 0,
    cache: Annotated[Path, typer.Option(help="rendered keyframes are cached here")] = Path("cache/bench"),
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """The paper's localization experiments on simulated worlds: Table I/II, Fig. 5 PR, Fig. 8 ablations,
    partial overlap and disjoint scenes, all descriptors and both matching modes side by side."""
    from rich.table import Table

    from shgm_slam.bench.localization import BenchOptions, run_localization_benchmark
    from shgm_slam.bench.localization_report import targets_rows
    from shgm_slam.config import load_config

    overrides: dict[str, Any] = {"world_seed": seed, "cache_dir": cache}
    if runs is not None:
        overrides["runs"] = runs
    options = BenchOptions.quick_options(**overrides) if quick else BenchOptions(**overrides)
    with console.status("starting") as status:
        results = run_localization_benchmark(out, options, load_config(config),
                                             progress=lambda msg: status.update(msg))
    table = Table(title="localization targets")
    for col in ("target", "measured", "goal", ""):
        table.add_column(col)
    for row in targets_rows(results):
        table.add_row(*row)
    console.print(table)
    console.print(f"{results['wall_time_s']:.0f} s; wrote [bold]{lit(out / 'localization.md')}[/], "
                  f"{lit(out / 'localization.json')} and {lit(out / 'pr_curve.png')}")


def _condition(name: str, help_text: str, default: str) -> Any:
    """``typer.Option`` for one of ``bench sparse``'s map conditions given as a range 'A-B' (or one number)."""
    return typer.Option(name, parser=number_range, metavar="<A-B>", show_default=default, help=help_text)


@bench_app.command("sparse")
@handle_errors
@stops_like_ctrl_c
def bench_sparse(
    out: Annotated[Path, results_folder("results folder: sparse.json, sparse.md")]
    = Path("results/bench_sparse"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'A-B' or 'A,B,C' (tuning 10-19; report 210-219)")]
    = "10-19",
    pairs: Annotated[int, typer.Option(min=1, max=10000, help="overlapping pairs per world (as many negatives)")] = 10,
    full_rotation: Annotated[bool, typer.Option(help="also match every pair 6-DoF")] = True,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    miss: Annotated[NumberRange | None, _condition("--miss", "share of objects each robot misses, drawn per "
                    "robot from A-B (0..0.95)", "0.3-0.6")] = None,
    noise_m: Annotated[NumberRange | None, _condition("--noise-m", "horizontal centroid noise (RMS, metres), "
                       "drawn per robot from A-B (0..10)", "0.5-2")] = None,
    confusion: Annotated[float | None, typer.Option(parser=float_in(0.0, 1.0), metavar="<float 0..1>",
                         show_default="0.05", help="share of each robot's nodes given a confusable class")] = None,
    share_m: Annotated[NumberRange | None, _condition("--share-m", "street two overlapping drives share, "
                       "metres, drawn per pair from A-B (10..1000)", "50-300")] = None,
    heights: Annotated[bool, typer.Option(help="--no-heights: every node at height 0, as a map layer without "
                                               "heights is read")] = True,
) -> None:
    """Sparse, map-like localization (no rendering): map classes only, 30-60 % missed, 0.5-2 m noise,
    label confusions, drives sharing 50-300 m, far-apart negatives; localized / wrong / negatives / ms.
    --miss, --noise-m, --confusion and --share-m make the maps unlike that, to see how it degrades; --no-heights
    drops the objects' heights."""

    from shgm_slam.bench.localization_sparse import SparseOptions, run_sparse_benchmark, sparse_markdown
    from shgm_slam.bench.report import write_report
    from shgm_slam.bench.seeds import parse_seeds
    from shgm_slam.config import load_config

    cfg = load_config(config)
    seed_list = parse_seeds(seeds)
    given = {"miss_range": miss, "noise_range_m": noise_m, "confusion_rate": confusion, "share_range_m": share_m}
    conditions = {k: v.as_tuple() if isinstance(v, NumberRange) else v for k, v in given.items() if v is not None}
    options = SparseOptions(seeds=seed_list, pairs_per_seed=pairs, full_rotation=full_rotation, heights=heights,
                            **conditions)
    with console.status("starting") as status:
        results = run_sparse_benchmark(options, cfg.descriptor, cfg.matching, cfg.graph,
                                       progress=lambda msg: status.update(msg))
    text = sparse_markdown(results, seed_list)
    write_report(out, "sparse", results.to_json(), lambda _: text)
    print_report(text)
    console.print(f"wrote {lit(out / 'sparse.json')} and {lit(out / 'sparse.md')}")
    if results.interrupted:
        err_console.print(f"[yellow]interrupted[/]: the files hold the {len(results.seeds_done)} seeds finished "
                          f"of {len(seed_list)}")  # fmt: skip
        raise typer.Exit(INTERRUPTED_EXIT_CODE)


@bench_app.command("system")
@handle_errors
@stops_like_ctrl_c
def bench_system(
    out: Annotated[Path, results_folder("results folder")] = Path("results/bench_system"),
    cache: Annotated[Path, typer.Option(help="simulated worlds are cached here")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed")] = 0,
    memory: Annotated[bool, typer.Option(help="also the 1000- vs 4000-frame peak-RSS runs")] = True,
    rgb_only: Annotated[
        bool, typer.Option(help="also both worlds RGB only: demo ONNX models + visual odometry")
    ] = False,
) -> None:
    """The whole system on airsim-like (fused ATE, closures, ms/keyframe), disjoint (no merges), and memory."""
    from shgm_slam.bench.system import run_system_benchmark, system_markdown

    with console.status("starting") as status:
        results = run_system_benchmark(out, cache=cache, seed=seed, memory=memory, rgb_only=rgb_only,
                                       progress=lambda msg: status.update(msg))
    print_report(system_markdown(results))
    console.print(f"wrote {lit(out / 'system.json')} and {lit(out / 'system.md')}")


@bench_app.command("scale")
@handle_errors
@stops_like_ctrl_c
def bench_scale(
    out: Annotated[Path, results_folder("results folder")] = Path("results/bench_scale"),
    cache: Annotated[Path, typer.Option(help="simulated worlds are cached here")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed")] = 0,
    memory: Annotated[bool, typer.Option(help="also the 1 km vs whole-drive peak-RSS runs (fresh processes)")]
    = True,
    kitti_root: Annotated[Path | None, typer.Option(help="KITTI folder with poses/")] = None,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """Cost with distance: all of KITTI 00 (3.7 km) with 07 as kitti-paths; per kilometre, the time per keyframe
    of the front end, matching and the pose graph, matches and their cost, memory; 1 km vs 3.7 km peak RSS."""
    from shgm_slam.bench.scale import run_scale_benchmark, scale_markdown
    from shgm_slam.config import load_config

    with console.status("starting") as status:
        results = run_scale_benchmark(out, cache=cache, seed=seed, memory=memory, kitti_root=kitti_root,
                                      config=load_config(config), progress=lambda msg: status.update(msg))  # fmt: skip
    print_report(scale_markdown(results))
    console.print(f"wrote {lit(out / 'scale.json')} and {lit(out / 'scale.md')}")


@bench_app.command("robots")
@handle_errors
@stops_like_ctrl_c
def bench_robots(
    out: Annotated[Path, results_folder("results folder")] = Path("results/bench_robots"),
    fleets: Annotated[str, typer.Option(help="comma-separated fleet sizes, 1-8")] = "1,2,4,8",
    sequence: Annotated[str, typer.Option(help="KITTI sequence cut into the robots (00-10; 00: bench scale's world)")]
    = "00",
    cache: Annotated[Path, typer.Option(help="simulated worlds are cached here")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed")] = 0,
    memory: Annotated[bool, typer.Option(help="also each fleet's peak RSS alone in a fresh process")] = True,
    kitti_root: Annotated[Path | None, typer.Option(help="KITTI folder with poses/")] = None,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    jobs: Annotated[int | None, typer.Option(min=1, max=256, show_default="the cores",
                                             help="worker processes of the fleets' second run (run --jobs)")] = None,
) -> None:
    """Cost with the number of robots: a KITTI sequence cut into 8 stretches, the first N driving at once; per
    keyframe, the front end, matching and the pose graph, matches per keyframe, CPU per second driven, memory;
    robots placed right / wrong and aliases among the accepted matches."""
    from shgm_slam.bench.robots import robots_markdown, run_robots_benchmark
    from shgm_slam.config import load_config

    sizes = int_list(fleets, "--fleets")
    with console.status("starting") as status:
        results = run_robots_benchmark(out, fleets=sizes, sequence=sequence, cache=cache, seed=seed, memory=memory,
                                       kitti_root=kitti_root, config=load_config(config), jobs=jobs,
                                       progress=lambda msg: status.update(msg))  # fmt: skip
    print_report(robots_markdown(results))
    console.print(f"wrote {lit(out / 'robots.json')} and {lit(out / 'robots.md')}")
    _exit_if_interrupted(results, f"the files hold the {len(results['fleets'])} fleets finished")


@bench_app.command("distributed")
@handle_errors
@stops_like_ctrl_c
def bench_distributed(
    out: Annotated[Path, results_folder("results folder")] = Path("results/bench_distributed"),
    cache: Annotated[Path, typer.Option(help="simulated worlds are cached here")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="demo world seed")] = 0,
    faults: Annotated[
        str, typer.Option(help="comma-separated distributed runs: none, robot (killed + restarted), server (same)")
    ] = "none,robot,server",
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """The demo world in one process and as server + robot processes over Zenoh (with faults): placement,
    fused ATE, bytes per keyframe, KB/s per robot."""
    from shgm_slam.bench.distributed import Fault, distributed_markdown, run_distributed_benchmark
    from shgm_slam.config import load_config
    from shgm_slam.demo import prepare_world
    from shgm_slam.errors import ConfigError

    try:
        modes = list(distinct("--faults", (Fault(f.strip()) for f in faults.split(",") if f.strip())))
    except ValueError:
        modes = []
    if not modes:
        raise ConfigError(f"--faults {faults!r}: comma-separated none, robot, server")
    load_config(config)  # refused before the demo world is rendered (the runs read the file themselves)
    world, _ = prepare_world(cache, seed, lambda folder: simulate_with_progress("airsim-like", folder, seed,
                                                                                   cached=True))
    with console.status("starting") as status:
        result = run_distributed_benchmark(world, out, faults=modes, config=config,
                                           progress=lambda msg: status.update(msg))  # fmt: skip
    print_report(distributed_markdown(result))
    console.print(f"wrote {lit(out / 'distributed.json')} and {lit(out / 'distributed.md')}")


@bench_app.command("live")
@handle_errors
@stops_like_ctrl_c
def bench_live(
    out: Annotated[Path, results_folder("benchmark folder")] = Path("results/bench_live"),
    robot: Annotated[
        list[str] | None,
        typer.Option("--robot", "-r", help="NAME=PATH[:start-end]; repeat per robot", show_default="the demo world"),
    ] = None,
    cache: Annotated[Path, typer.Option(help="the demo world is cached here")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="demo world seed")] = 0,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """The same robots run from their recorded sequences and fed frame by frame to a LiveRun, side by side: the
    same results?, frames held before the run starts, each add_frame call's wall time against the recorded run's
    per-frame step."""
    from shgm_slam.bench.live import live_markdown, run_live_benchmark
    from shgm_slam.config import load_config
    from shgm_slam.demo import prepare_world
    from shgm_slam.runner import open_robots

    cfg = load_config(config)  # refused before the demo world is rendered
    if not robot:
        world, kinds = prepare_world(cache, seed, lambda folder: simulate_with_progress("airsim-like", folder, seed,
                                                                                           cached=True))
        robot = [f"{name}={world / name}" for name in kinds]
    robots = open_robots(robot)
    with console.status("starting") as status:
        results = run_live_benchmark(robots, out, config=cfg, progress=lambda msg: status.update(msg))
    print_report(live_markdown(results))
    console.print(f"wrote {lit(out / 'live.json')} and {lit(out / 'live.md')}")


@bench_app.command("heldout")
@handle_errors
@stops_like_ctrl_c
def bench_heldout(
    out: Annotated[Path, results_folder("results folder (resumes the runs already in it)")]
    = Path("results/bench_heldout"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'report' (210-219), 'tuning' (10-29), A-B or A,B,C")]
    = "report",
    scenario: Annotated[list[str] | None, typer.Option(help="scenario (repeatable)", show_default="all four")] = None,
    mode: Annotated[list[str] | None, typer.Option(help="files | rgb (repeatable)", show_default="both")] = None,
    max_frames: Annotated[
        int | None, typer.Option(min=10, max=MAX_FRAMES, help="cut every robot's sequence to its first N frames "
                                 "(quick looks; at a lower --fps the same drive has fewer frames, so N cover more "
                                 "of it)")
    ] = None,
    cache: Annotated[Path, typer.Option(help="rendered worlds are cached here")] = Path("cache/heldout"),
    resolution: Annotated[str, typer.Option(help="render size WIDTHxHEIGHT (every default was chosen at 320x96; "
                                            "other sizes are cached apart)")] = "320x96",
    jobs: Annotated[int, typer.Option(min=1, max=64, help="worlds run in this many processes at once (1: one world "
                                      "at a time, its robots' front ends in worker processes, up to the cores)")] = 1,
    supersample: Annotated[int, typer.Option(min=1, max=8, help="render the worlds' colour with SxS rays per pixel "
                                             "(antialiased; cached apart)")] = 1,
    uav_altitude: Annotated[str | None, typer.Option(help="airsim-like worlds: the UAV's altitude, LOW-HIGH metres "
                                                     "(default 44-54; cached apart)")] = None,
    depth_noise: Annotated[float, bounded(0.0, 0.5, help="relative depth error std of the renders the "
                                               "files mode reads (0.05 = 5 %; cached apart)")] = 0.0,
    label_noise: Annotated[float, bounded(0.0, 1.0, help="segment confusion probability of the "
                                               "renders' labels (boundaries jitter by 10x this many px)")] = 0.0,
    replay_from: Annotated[
        Path | None,
        typer.Option(help="an earlier benchmark folder: run only the map server again on its recorded keyframes "
                     "(matching and back-end changes; no rendering, perception or odometry)"),
    ] = None,
    kitti_root: Annotated[Path | None, typer.Option(help="KITTI folder with poses/ (kitti-paths worlds)")] = None,
    fps: Annotated[float, bounded(0.1, 100.0, help="frame rate of the rendered worlds, Hz (every default was "
                                  "chosen at 10; KITTI subsampled to every 2nd or 3rd frame is 5 or 3.3, which "
                                  "kitti-paths worlds then are; cached apart)")] = 10.0,
) -> None:
    """The system with the default configuration on many unseen worlds: placed right, false merges,
    not placed, odometry failures (ground truth and detected), accepted matches and placements judged
    at their own place (false ones withdrawn later included), per scenario and input."""
    from shgm_slam.bench import heldout
    from shgm_slam.bench.heldout_judge import InputMode
    from shgm_slam.bench.heldout_summary import heldout_markdown
    from shgm_slam.errors import ConfigError
    from shgm_slam.sim.corruption import CorruptionLevels
    from shgm_slam.sim.simulate import check_uav_altitude, parse_altitude, parse_resolution

    seed_list = world_seeds(seeds)
    size = parse_resolution(resolution)
    altitude = parse_altitude(uav_altitude) if uav_altitude is not None else None
    if altitude is not None:
        check_uav_altitude("airsim-like", altitude, heldout.MAX_DEPTH_M)
    for s in distinct("--scenario", scenario or ()):
        if s not in heldout.SCENARIOS:
            raise ConfigError(f"--scenario {s!r}: choose from {', '.join(heldout.SCENARIOS)}")
    for given in distinct("--mode", mode or ()):
        if given not in {m.value for m in InputMode}:
            raise ConfigError(f"--mode {given!r}: choose files or rgb")
    modes = tuple(InputMode(m) for m in (mode or [m.value for m in InputMode]))
    if replay_from is not None and replay_from.resolve() == out.resolve():
        raise ConfigError(f"--replay-from {replay_from} is the --out folder: its runs would be taken as done, not "
                          "replayed; give another --out")  # fmt: skip
    options = heldout.HeldoutOptions(scenarios=tuple(scenario or heldout.SCENARIOS), seeds=seed_list, modes=modes,
                                     max_frames=max_frames, cache=cache, replay_from=replay_from, resolution=size,
                                     supersample=supersample, uav_altitude_m=altitude,
                                     corruption=CorruptionLevels.from_levels(depth_noise, label_noise),
                                     kitti_root=kitti_root, front_end_jobs=None if jobs == 1 else 1,
                                     fps=fps)  # fmt: skip
    if replay_from is not None and not (replay_from / "runs").is_dir():
        raise ConfigError(f"--replay-from {replay_from}: no runs/ folder there (a `bench heldout` results folder)")
    if kitti_root is not None and "kitti-paths" not in options.scenarios:
        warn_unused("--kitti-root", kitti_root, "no kitti-paths world is selected (--scenario)")
    with console.status("starting") as status:
        results = heldout.run_heldout_benchmark(out, options, progress=lambda msg: status.update(msg), jobs=jobs)
    print_report(heldout_markdown(results))
    console.print(f"wrote {lit(out / 'heldout.json')} and {lit(out / 'heldout.md')}")
    _exit_if_interrupted(results, f"the files hold the {len(results['runs'])} runs finished; the same command "
                                  "resumes the rest")  # fmt: skip


def _exit_if_interrupted(results: dict, kept: str) -> None:
    """Exit with ``INTERRUPTED_EXIT_CODE`` (saying what was kept) when a benchmark's results are ``interrupted``."""
    if results.get("interrupted"):
        err_console.print(f"[yellow]interrupted[/]: {kept}")
        raise typer.Exit(INTERRUPTED_EXIT_CODE)


@bench_app.command("depth-quality")
@handle_errors
@stops_like_ctrl_c
def bench_depth_quality(
    out: Annotated[Path, results_folder("results folder (resumes the runs already in it)")]
    = Path("results/bench_depth_quality"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'report' (210-219), 'tuning' (10-29), A-B or A,B,C")]
    = "report",
    scenario: Annotated[
        list[str] | None, typer.Option(help="scenario (repeatable)", show_default="airsim-like, synthia-like")
    ] = None,
    level: Annotated[
        list[str] | None,
        typer.Option(help="depth level (repeatable): true, an AbsRel such as 0.05, or model",
                     show_default="true 0.03 0.05 0.08 0.12 model"),
    ] = None,
    odometry: Annotated[
        str, typer.Option(help="odometry kinds run alone (comma-separated: kiss-icp, visual, hybrid)")
    ] = "kiss-icp,visual,hybrid",
    system: Annotated[
        str, typer.Option(help="odometry kinds the whole system runs with (comma-separated; 'none' for none)")
    ] = "visual,hybrid",
    max_frames: Annotated[
        int | None, typer.Option(min=10, max=MAX_FRAMES, help="cut every robot's sequence (quick looks)")
    ] = None,
    cache: Annotated[Path, typer.Option(help="rendered worlds are cached here (shared with bench heldout)")]
    = Path("cache/heldout"),
) -> None:
    """What depth quality each odometry needs: true depth corrupted the way networks err (smooth scale
    field, error growing with range, blurred edges, flicker) at AbsRel levels, plus the demo model's
    depth; drift and ATE of each odometry alone, and robots placed by the whole system."""
    from shgm_slam.bench import depth_quality as dq
    from shgm_slam.bench import heldout
    from shgm_slam.config import OdometryKind
    from shgm_slam.errors import ConfigError

    for s in distinct("--scenario", scenario or ()):
        if s not in heldout.SCENARIOS:
            raise ConfigError(f"--scenario {s!r}: choose from {', '.join(heldout.SCENARIOS)}")
    levels = dq.LEVELS if not level else distinct("--level", (dq.parse_level(x) for x in level), lambda v: v.name)
    studied = (OdometryKind.KISS_ICP, OdometryKind.VISUAL, OdometryKind.HYBRID)

    def kinds(option: str, text: str) -> tuple[OdometryKind, ...]:
        if text.strip() == "none":
            return ()
        try:
            chosen = tuple(OdometryKind(k.strip()) for k in text.split(",") if k.strip())
        except ValueError:
            chosen = ()
        if not chosen or any(k not in studied for k in chosen):
            raise ConfigError(f"--{option} {text!r}: comma-separated kiss-icp, visual, hybrid (or none)")
        return distinct(f"--{option}", chosen)

    options = dq.DepthQualityOptions(
        scenarios=tuple(scenario or dq.DepthQualityOptions.scenarios), seeds=world_seeds(seeds), levels=levels,
        odometry_kinds=kinds("odometry", odometry), system_kinds=kinds("system", system), max_frames=max_frames,
        cache=cache,
    )  # fmt: skip
    with console.status("starting") as status:
        results = dq.run_depth_quality_benchmark(out, options, progress=lambda msg: status.update(msg))
    print_report(dq.depth_quality_markdown(results))
    console.print(f"wrote {lit(out / 'depth_quality.json')}, {lit(out / 'depth_quality.md')} and "
                  f"{lit(out / 'depth_quality.png')}")  # fmt: skip


@bench_app.command("table3")
@handle_errors
@stops_like_ctrl_c
def bench_table3(
    out: Annotated[Path, results_folder("results folder: table3.json, table3.md")]
    = Path("results/bench_table3"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'report' (200-209), 'tuning' (10-19), A-B or A,B")]
    = "report",
    runs: Annotated[
        int, typer.Option(min=1, max=100000, help="random transforms per split, descriptor and world")
    ] = 10,
    split: Annotated[
        list[str] | None, typer.Option(help="02 | 08A | 08B | 00-07 (repeatable)", show_default="all")
    ] = None,
    descriptor: Annotated[
        list[DescriptorKind] | None, typer.Option(help="descriptor (repeatable)", show_default="all three")
    ] = None,
    max_frames: Annotated[int | None, typer.Option(min=2, max=MAX_FRAMES, help="cut every drive to its first frames "
                                                   "(quick looks; may cut the overlap away)")] = None,
    resolution: Annotated[str, typer.Option(help="render size WIDTHxHEIGHT")] = "320x96",
    mode: Annotated[str, typer.Option(help="robust (the default configuration) | paper (Alg. 2 RANSAC over "
                                      "the best candidate per node, as the authors' release)")] = "robust",
    depth_noise: Annotated[float, bounded(0.0, 1.0, help="relative depth error std of the renders")] = 0.0,
    label_noise: Annotated[float, bounded(0.0, 1.0, help="label confusion of the renders")] = 0.0,
    kitti_root: Annotated[Path | None, typer.Option(help="KITTI folder with poses/")] = None,
    cache: Annotated[Path, typer.Option(help="rendered worlds are cached here")] = Path("cache/table3"),
    jobs: Annotated[int, typer.Option(min=1, max=64, help="world seeds run in this many processes at once")] = 1,
) -> None:
    """The paper's Table III protocol on kitti-paths: 08 cut into three robots (08A, 08B), 02 into two driven
    in opposite directions, 00 against 07; whole-graph localization error per descriptor, next to the paper's."""
    from shgm_slam.bench import table3
    from shgm_slam.bench.localization import BenchMode
    from shgm_slam.errors import ConfigError
    from shgm_slam.sim.simulate import parse_resolution

    try:
        bench_mode = BenchMode(mode)
    except ValueError:
        raise ConfigError(f"--mode {mode!r}: choose robust or paper") from None
    options = table3.Table3Options(
        seeds=table3.parse_seeds(seeds), runs=runs, kinds=distinct("--descriptor", descriptor or DescriptorKind),
        splits=tuple(split or (s.name for s in table3.SPLITS)), resolution=parse_resolution(resolution),
        max_frames=max_frames, mode=bench_mode, depth_noise=depth_noise, label_noise=label_noise, cache=cache,
    )  # fmt: skip
    with console.status("starting") as status:
        results = table3.run_table3(options, progress=lambda msg: status.update(msg), jobs=jobs,
                                    kitti_root=kitti_root)  # fmt: skip
    json_path, md_path = table3.write_table3(results, out)
    print_report(table3.table3_markdown(results))
    console.print(f"wrote {lit(json_path)} and {lit(md_path)} ({results.wall_s:.0f} s)")

