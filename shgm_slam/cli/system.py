"""The multi-robot system: ``run``, ``server``, ``robot``, ``demo`` and ``eval`` of a results folder."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated

import typer

from shgm_slam.cli.app import app, handle_errors
from shgm_slam.cli.maps import simulate_with_progress
from shgm_slam.cli.options import JobsOption, bounded, nonempty_path
from shgm_slam.cli.render import console, eval_table, lit, placed_text, render_summary
from shgm_slam.cli.signals import stop_signals_as_interrupt
from shgm_slam.config import OdometryKind
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE
from shgm_slam.io.json_text import to_json_text
from shgm_slam.transport.keys import DEFAULT_ENDPOINT


@contextlib.contextmanager
def _frame_progress(total: int) -> Iterator[Callable[[int, int], None]]:
    """A progress callback for ``api.run``: a bar of frames (all robots together) with ETA, shown from the first
    frame on (the checks before the run log without it) and gone when the block ends."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    bar = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                   TimeRemainingColumn(), console=console, transient=True)  # fmt: skip
    task = None

    def update(done: int, _total: int) -> None:
        nonlocal task
        if task is None:
            bar.start()
            task = bar.add_task("frames", total=total)
        bar.update(task, completed=done)

    try:
        yield update
    finally:
        if task is not None:
            bar.stop()


@app.command("run")
@handle_errors
def run(
    robot: Annotated[
        list[str],
        typer.Option("--robot", "-r", help="NAME=PATH[:start-end]; repeat per robot (the first is the shared frame). "
                     "Ranges are half-open: car=08:0-1500 is frames 0..1499, 08:1500- the rest"),
    ],
    odometry: Annotated[
        str | None,
        typer.Option(
            help="auto | kiss-icp | visual | hybrid | gt | a KITTI/TUM poses file ({robot} in the path = robot "
            "name); auto = visual odometry on model depth, KISS-ICP on depth files (the run says which and why); "
            "hybrid = KISS-ICP seeded by and fused with the visual odometry",
            show_default="the config's, auto",
        ),
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    out: Annotated[Path | None, typer.Option("--out", parser=nonempty_path,
                                             help="results folder", show_default="results/<time>")] = None,
    rerun: Annotated[str, typer.Option("--rerun", help="spawn | save | connect | off")] = "save",
    rerun_url: Annotated[str | None, typer.Option(help="gRPC URL for --rerun connect")] = None,
    depth_model: Annotated[Path | None, typer.Option(help="ONNX depth model (card next to it)")] = None,
    seg_model: Annotated[Path | None, typer.Option(help="ONNX segmentation model (card next to it)")] = None,
    gt_shared_frame: Annotated[bool, typer.Option(help="ground truths of all robots share one world frame")] = True,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="reuse an --out holding an earlier run's results: remove them first")
    ] = False,
    jobs: JobsOption = None,
) -> None:
    """Run the multi-robot system: odometry, semantic graphs, cross-robot matching, fused trajectories."""
    from shgm_slam.config import load_config

    cfg = _apply_run_options(load_config(config), odometry, depth_model, seg_model)
    summary = _run_command(robot, cfg, out, rerun, rerun_url, gt_shared_frame, overwrite, jobs)
    render_summary(summary)
    _exit_for(summary)


FRONT_END_LOST_EXIT_CODE = 1
"""``run`` and ``demo`` exit with this when a robot's front end was lost mid-run (``RobotReport.front_end_lost``):
the results are written, but hold that robot only up to where it was lost."""


def _exit_for(summary) -> None:
    """End a finished ``run`` or ``demo`` with its exit code: 130 when it was stopped, ``FRONT_END_LOST_EXIT_CODE``
    when a robot's front end was lost (said in red first), else 0."""
    if summary.interrupted:
        raise typer.Exit(INTERRUPTED_EXIT_CODE)
    for why in summary.front_ends_lost:
        console.print(f"[red]a robot's front end was lost {lit(why)}[/]: the results hold that robot only up to "
                      "there; run again (--jobs 1 shows the error where it happens)")  # fmt: skip
    if summary.front_ends_lost:
        raise typer.Exit(FRONT_END_LOST_EXIT_CODE)


def _apply_run_options(cfg, odometry: str | None, depth_model: Path | None, seg_model: Path | None):
    """The configuration with ``--odometry`` (a kind, or a poses file, ``{robot}`` standing for each robot's name),
    ``--depth-model`` and ``--seg-model`` applied over it; an ``--odometry`` that is neither is a ``ConfigError``."""
    from shgm_slam.errors import ConfigError

    # (a poses file is given by its path; sequence folders carry no odometry of the robot's own to be GIVEN)
    kinds = {k.value: k for k in OdometryKind if k not in (OdometryKind.FILE, OdometryKind.GIVEN)}
    if odometry is None:
        pass
    elif odometry in kinds:
        cfg.odometry.kind = kinds[odometry]
    else:
        if "{robot}" not in odometry and not Path(odometry).is_file():
            raise ConfigError(
                f"--odometry {odometry!r}: not one of {', '.join(kinds)}, nor an existing poses file"
            )
        cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, Path(odometry)
    if depth_model is not None:
        cfg.perception.depth_model = depth_model
    if seg_model is not None:
        cfg.perception.seg_model = seg_model
    return cfg


def _run_command(robot_args, cfg, out, rerun_mode: str, rerun_url, gt_shared_frame: bool, overwrite: bool = False,
                 jobs: int | None = None):  # fmt: skip
    """Open the robots, check every input that can refuse the run (``--rerun``, config, models, first frames)
    before ``--out`` is claimed (locked, ``--overwrite`` to reuse one with results), then run with SIGTERM/SIGHUP
    stopping it as Ctrl-C does; returns the run's summary."""
    from shgm_slam import api
    from shgm_slam.robot.remote import default_jobs
    from shgm_slam.runner import open_robots

    robots = open_robots(robot_args)
    mode = _rerun_mode(rerun_mode)
    # api.run checks everything that can refuse the run (config, models, first frames) before --out gets a
    # file: a refused run must not leave files that make the next run with the same --out ask for --overwrite
    with stop_signals_as_interrupt(), _frame_progress(sum(len(s) for s in robots.values())) as progress:
        return api.run(robots, out, config=cfg, viewer=mode, viewer_url=rerun_url, gt_shared_frame=gt_shared_frame,
                       overwrite=overwrite, jobs=default_jobs(len(robots), jobs), progress=progress)  # fmt: skip


def _rerun_mode(rerun_mode: str):
    """``--rerun``'s value as a ``RerunMode``; ConfigError naming the choices for any other."""
    from shgm_slam.errors import ConfigError
    from shgm_slam.viz.rerun_logger import RerunMode

    try:
        return RerunMode(rerun_mode)
    except ValueError:
        raise ConfigError(f"--rerun {rerun_mode!r}: choose spawn, save, connect or off") from None


def _check_demo_out(out: Path, overwrite: bool) -> None:
    """Refuse an existing ``--out`` that the demo's run would refuse (an earlier run's results without
    ``--overwrite``, a file, a sequence, a folder another process is writing) before the world is rendered: the run
    itself checks it only after the render (1-2 minutes on 2 cores). Nothing in ``out`` is changed here.

    Raises:
        DataError: as ``io.export.make_results_dir`` does for such a folder.
    """
    from shgm_slam.io.export import claimed_results_dir

    if not out.exists() or (overwrite and out.is_dir()):
        return  # a new folder; or --overwrite, whose removal of the old results waits for the run
    with claimed_results_dir(out):  # refuses, or locks and releases it at once
        pass


@app.command("server")
@handle_errors
def server_command(
    out: Annotated[Path, typer.Option("--out", parser=nonempty_path,
                                      help="results folder (a journal there is replayed: restart)")],
    listen: Annotated[
        str | None, typer.Option(help="Zenoh endpoint(s) to listen on, comma-separated",
                                  show_default=DEFAULT_ENDPOINT)
    ] = None,
    reference: Annotated[
        str | None, typer.Option(help="robot whose frame is the shared frame",
                                  show_default="the first to connect")
    ] = None,
    expect: Annotated[
        int | None,
        typer.Option(min=1, max=52, help="finish by itself once N robots connected and sent their last keyframe"),
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    rerun: Annotated[str, typer.Option("--rerun", help="spawn | save | connect | off")] = "save",
    rerun_url: Annotated[str | None, typer.Option(help="gRPC URL for --rerun connect")] = None,
    stale_after: Annotated[
        float, bounded(0.5, 3600, help="seconds of silence before a robot is stale")
    ] = 5.0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="start fresh: remove an earlier run's results "
                                            "and journal from --out first (without it a journal there is "
                                            "resumed)")] = False,
) -> None:
    """Map server for robots in separate processes (Eclipse Zenoh): fuses their maps, writes the results."""
    from shgm_slam.config import load_config
    from shgm_slam.errors import ConfigError
    from shgm_slam.io.export import claimed_results_dir
    from shgm_slam.server.serve import serve
    from shgm_slam.transport.keys import validate_robot_name
    from shgm_slam.viz.rerun_logger import RerunMode, make_viz

    cfg = load_config(config)
    if reference is not None:
        validate_robot_name(reference)
    try:
        mode = RerunMode(rerun)
    except ValueError:
        raise ConfigError(f"--rerun {rerun!r}: choose spawn, save, connect or off") from None
    # locked for the server's life: a second server on this folder would mix its files and journal into it
    with claimed_results_dir(out, overwrite=overwrite, resume_file="journal.bin") as out:  # journal: a restart
        viz = make_viz(mode, robots=[], save_path=out / "server.rrd", connect_url=rerun_url, max_cloud_points=8000)
        with stop_signals_as_interrupt():
            result = serve(cfg, out, listen=listen, reference=reference, expect=expect, viz=viz,
                           stale_after_s=stale_after, started=lambda resumed: console.print(
                               f"map server listening on {lit(listen or DEFAULT_ENDPOINT)}"
                               + (f", expecting {expect} robots" if expect else "; Ctrl-C to finish")
                               + (f"; {resumed}" if resumed else "")),
                           say=lambda line: console.print(f"  {lit(line)}"))  # fmt: skip
    s = result.summary
    for name, r in s["robots"].items():
        placed = placed_text(r["placed"], r["provisional"])
        console.print(f"  {lit(name)}: {r['keyframes']} keyframes, {r['state']}, placed: {lit(placed)}")
        for note in r.get("waiting", ()):
            console.print(f"    {lit(note)}")
    for line in s.get("never_met", ()):
        console.print(f"[yellow]{lit(line)}[/]")
    t = s["traffic"]
    per_kf = t["bytes_per_keyframe"]
    console.print(f"{s['matches_tried']} matches, {s['closures_accepted']} accepted; "
                  f"{f'{per_kf:.0f} B' if per_kf else 'no'} per keyframe; {t['refused']} messages refused; "
                  f"results in {lit(result.out_dir)}")  # fmt: skip
    if result.interrupted:
        raise typer.Exit(INTERRUPTED_EXIT_CODE)


@app.command("robot")
@handle_errors
def robot_command(
    robot: Annotated[str, typer.Argument(help="NAME=PATH[:start-end] (frames start..end-1)")],
    connect: Annotated[
        str | None, typer.Option(help="map server's Zenoh endpoint(s), comma-separated",
                                  show_default=DEFAULT_ENDPOINT)
    ] = None,
    odometry: Annotated[
        str | None, typer.Option(help="auto | kiss-icp | visual | hybrid | gt | a KITTI/TUM poses file (as for run)")
    ] = None,
    depth_model: Annotated[Path | None, typer.Option(help="ONNX depth model (card next to it)")] = None,
    seg_model: Annotated[Path | None, typer.Option(help="ONNX segmentation model (card next to it)")] = None,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    realtime: Annotated[
        bool, typer.Option(help="pace frames by their timestamps", show_default="as fast as it can")
    ] = False,
    out: Annotated[Path | None, typer.Option("--out", parser=nonempty_path,
                                             help="write this robot's trajectories here")] = None,
    wait: Annotated[
        float, bounded(0, 3600, help="seconds to wait for the server after the last frame")
    ] = 60.0,
) -> None:
    """One robot in its own process: front end, keyframes to the map server, corrections applied."""
    from shgm_slam.config import load_config
    from shgm_slam.robot.drive import drive_robot
    from shgm_slam.runner import open_robots

    cfg = _apply_run_options(load_config(config), odometry, depth_model, seg_model)
    (name, seq), = open_robots([robot]).items()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    with stop_signals_as_interrupt(), Progress(f"{lit(name)}: frames", BarColumn(), MofNCompleteColumn(),
                                                TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("frames", total=len(seq))
        s = drive_robot(name, seq, cfg, connect=connect, realtime=realtime, out_dir=out, wait_s=wait,
                        progress=lambda done, total: bar.update(task, completed=done))  # fmt: skip
    placed = placed_text(s.placed_agents, s.provisional_agents)
    down_kb = s.bytes_received.get("correction", 0) / 1e3
    console.print(f"{lit(name)}: {s.frames_processed}/{s.frames} frames, {s.keyframes} keyframes "
                  f"({s.bytes_per_keyframe:.0f} B each, {s.resent} re-sent; {down_kb:.0f} KB of corrections), "
                  f"placed: {lit(placed)}")  # fmt: skip
    if s.waiting_agents:
        console.print(f"  not placed yet: {lit(', '.join(s.waiting_agents))} (accepted matches, but too few "
                      "independent ones to enter the shared frame; the server's summary says which)")  # fmt: skip
    if s.interrupted:
        console.print(f"interrupted after {s.frames_processed} of {s.frames} frames"
                      + (f"; its trajectories so far are in {lit(out)}" if out else "")
                      + "; the map server keeps its keyframes: start the same command again to go on")  # fmt: skip
        raise typer.Exit(INTERRUPTED_EXIT_CODE)
    if not s.acknowledged:
        console.print(_unacknowledged_text(s, connect, wait, out))
        raise typer.Exit(3)
    if not s.server_finished:
        console.print(f"[yellow]the map server had not finished after --wait {wait:g} s[/] (waiting for more "
                      "robots, --expect?): this robot's place may still change; the server's results folder "
                      "holds the final trajectories")  # fmt: skip
        raise typer.Exit(4)


def _unacknowledged_text(s, connect: str | None, wait: float, out: Path | None) -> str:
    """What ``robot`` says when the map server did not acknowledge every keyframe (``DriveSummary`` ``s``): that no
    server ever answered at ``connect``, or that the one it had stopped or was lost, with what to do."""
    kept = f"; this robot's own trajectories are in {lit(out)}" if out else ""
    if not any(s.bytes_received.values()):
        endpoint = lit(connect or DEFAULT_ENDPOINT)
        return (f"[red]no map server answered at {endpoint}[/red] (is it running there? see --connect): it holds none "
                f"of this robot's keyframes{kept}")  # fmt: skip
    return (f"[red]the map server did not acknowledge every keyframe within --wait {wait:g} s[/red]: it stopped or "
            f"could not be reached (see the lines above); start it again on its --out (it resumes) and this robot "
            f"again to send the rest{kept}")  # fmt: skip


@app.command("demo")
@handle_errors
def demo(
    out: Annotated[
        Path | None, typer.Option(help="results folder", show_default="results/demo; with --rgb-only results/demo-rgb")
    ] = None,
    cache: Annotated[Path, typer.Option(help="where the simulated world is cached")] = Path("cache"),
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world seed")] = 0,
    rgb_only: Annotated[bool, typer.Option("--rgb-only", help="depth and labels from the ONNX demo models")] = False,
    rerun: Annotated[str, typer.Option("--rerun", help="spawn | save | connect | off")] = "save",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="reuse an --out holding an earlier run's "
                                            "results: remove them first (the default folder is always "
                                            "replaced)")] = False,
    jobs: JobsOption = None,
) -> None:
    """Simulate the airsim-like world (car, car, UAV) once, then run the whole system on it."""
    from shgm_slam.demo import demo_config, demo_results_dir, prepare_world

    overwrite = overwrite or out is None  # the demo's own default folder holds the previous demo: replace it
    out = out or demo_results_dir(rgb_only=rgb_only)

    def simulate_world(folder: Path) -> None:
        console.print(f"simulating the airsim-like world into [bold]{lit(folder)}[/] (once; cached afterwards)")
        simulate_with_progress("airsim-like", folder, seed, cached=True)

    cfg = demo_config(rgb_only=rgb_only)  # before the world is rendered: missing demo models fail at once
    _rerun_mode(rerun)  # so do a bad --rerun and an --out the run would refuse
    _check_demo_out(out, overwrite)
    world, kinds = prepare_world(cache, seed, simulate_world)
    console.print(f"world: [bold]{lit(world)}[/] robots: {lit(', '.join(f'{r} ({k})' for r, k in kinds.items()))}")
    summary = _run_command([f"{r}={world / r}" for r in kinds], cfg, out, rerun, None, True, overwrite, jobs)
    render_summary(summary)
    if (out / "run.rrd").is_file():
        console.print(f"open the recording with: [bold]{lit(viewer_command())} {lit(out / 'run.rrd')}[/]")
    console.print(f"evaluate against ground truth: [bold]shgm-slam eval {lit(out)}[/] or "
                  f"[bold]evo_ape tum {lit(out / 'car2_gt_tum.txt')} {lit(out / 'car2_fused_tum.txt')}[/]")
    _exit_for(summary)


def viewer_command() -> str:
    """How to start the Rerun viewer that came with this environment: the ``rerun`` script beside this Python
    (``.venv/bin/rerun`` after the quick start), else ``rerun`` from the PATH."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else "rerun"


@app.command("eval")
@handle_errors
def eval_command(
    results: Annotated[Path, typer.Argument(parser=nonempty_path, help="results folder of run or demo")],
    gt: Annotated[
        list[str] | None,
        typer.Option("--gt", help="NAME=PATH[:start-end] as in the run (half-open range: frames start..end-1); "
                     "repeat per robot. Default: the <robot>_gt_tum.txt files in RESULTS"),
    ] = None,
    gt_shared_frame: Annotated[bool, typer.Option(help="ground truths of all robots share one world frame")] = True,
    json_output: Annotated[bool, typer.Option("--json", help="print the evaluation as JSON")] = False,
) -> None:
    """Fused ATE of every robot against ground truth in the shared frame (evo, no alignment) and SE(3)-aligned.
    With --gt, also writes <robot>_gt_tum.txt into RESULTS for evo_ape."""

    from shgm_slam.errors import DataError
    from shgm_slam.evaluation import evaluate_results, open_ground_truth

    sequences = open_ground_truth(gt) if gt else None
    result = evaluate_results(results, sequences, gt_shared_frame=gt_shared_frame)
    nothing = not any(r.evaluated_poses for r in result.robots)
    if json_output:
        typer.echo(to_json_text(result.to_json_dict(), indent=None))
    else:
        console.print(eval_table(result))
    if nothing:  # a script must not read this as a measured result
        raise DataError(f"no robot of {results} could be evaluated (the notes say why): no ATE was measured")
    if json_output:
        return
    if result.interrupted:
        console.print("[yellow]this run was interrupted[/]: its trajectories end where it was stopped "
                      "(metrics.json: interrupted)")  # fmt: skip
    if result.gt_files_written:
        n = len(result.gt_files_written) // 2
        console.print(f"wrote {n} ground-truth {'trajectory' if n == 1 else 'trajectories'}; e.g. evo_ape tum "
                      f"{lit(result.gt_files_written[0])} {lit(results / (result.reference_robot + '_fused_tum.txt'))}")

