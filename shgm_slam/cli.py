"""The ``shgm-slam`` command line: parse -> validate -> call one library function -> render.

This is the only module that catches ``ShgmError`` (one clear line, exit code 2) and talks to the
user. Each command is a thin wrapper over a library function that tests call directly.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console

from shgm_slam import __version__
from shgm_slam.errors import ShgmError

console = Console()
err_console = Console(stderr=True)

app = typer.Typer(
    name="shgm-slam",
    help="Multi-robot global localization and map fusion with semantic histogram graph matching.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks that measure speed and accuracy; results go to JSON and markdown.",
                        no_args_is_help=True)
app.add_typer(bench_app, name="bench")

F = TypeVar("F", bound=Callable[..., Any])


def handle_errors(fn: F) -> F:
    """Turn ``ShgmError`` into one red line on stderr and exit code 2 (the CLI's error boundary)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ShgmError as exc:
            err_console.print(f"[bold red]error:[/] {exc}")
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    if value:
        console.print(f"shgm-slam {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """shgm_slam: several robots find each other and fuse their maps from camera images alone."""


@app.command("dump-config")
@handle_errors
def dump_config(
    config: Annotated[Path | None, typer.Option("--config", help="Show this YAML merged over the defaults.")] = None,
) -> None:
    """Print the effective configuration as YAML (defaults, or a file merged over them)."""
    from shgm_slam.config import load_config

    typer.echo(load_config(config).to_yaml(), nl=False)


# --- simulate (sim/) -------------------------------------------------------------------------------
# --- graph / match (graph/, descriptors/, matching/) -----------------------------------------------


@app.command("graph")
@handle_errors
def graph(
    sequence: Annotated[str, typer.Argument(help="SEQ[:start-end] with depth/, semantic/ and poses.txt")],
    out: Annotated[Path, typer.Option("--out", "-o", help="graph file to write (shgm-graph/1 JSON)")],
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    connectivity: Annotated[float | None, typer.Option(help="edge threshold, metres [config: 10]")] = None,
    merge_radius: Annotated[float | None, typer.Option(help="same-label merge radius, m [config: 5]")] = None,
    keyframe_every: Annotated[float | None, typer.Option(help="keyframe spacing, metres [config: 2]")] = None,
) -> None:
    """Build a sequence's semantic graph from its ground-truth poses, depth and labels; write it as JSON."""
    from pydantic import ValidationError
    from rich.progress import BarColumn, MofNCompleteColumn, Progress

    from shgm_slam.config import GraphConfig, load_config
    from shgm_slam.data import open_sequence
    from shgm_slam.errors import ConfigError
    from shgm_slam.graph.build import build_graph_from_sequence
    from shgm_slam.io.graph_json import write_graph

    cfg = load_config(config)
    overrides = {"connectivity_m": connectivity, "merge_radius_m": merge_radius}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if overrides:
        try:
            cfg.graph = GraphConfig.model_validate({**cfg.graph.model_dump(), **overrides})
        except ValidationError as exc:
            raise ConfigError(f"--connectivity/--merge-radius: {exc.errors()[0]['msg']}") from None
    seq = open_sequence(sequence)
    with Progress("{task.description}", BarColumn(), MofNCompleteColumn(), console=err_console,
                  transient=True) as bar:  # fmt: skip
        task = bar.add_task("keyframes", total=None)
        sg = build_graph_from_sequence(
            seq, cfg, keyframe_every_m=keyframe_every,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )  # fmt: skip
    path = write_graph(out, sg.arrays())
    console.print(
        f"{seq.name}: {len(sg.keyframe_ids)} keyframes -> {len(sg)} nodes, {sg.num_edges} edges "
        f"(connectivity {cfg.graph.connectivity_m:g} m); wrote [bold]{path}[/]"
    )


# --- run / demo (pipeline.py) -----------------------------------------------------------------------


def _render_summary(summary) -> None:
    """Print the run summary as rich tables."""
    from rich.table import Table

    t = Table(title="shgm-slam run", title_style="bold")
    for col in ("robot", "frames", "skipped", "keyframes", "nodes", "localized", "path m",
                "ATE odom (aligned) m", "ATE fused (shared frame) m"):
        t.add_column(col, justify="right" if col != "robot" else "left")
    for r in summary.robots:
        t.add_row(
            r.name, str(r.frames), str(r.frames_skipped), str(r.keyframes), str(r.nodes),
            "[green]yes[/]" if r.localized else "[red]no[/]", f"{r.path_length_m:.0f}",
            f"{r.ate_odometry_m:.2f}", f"{r.ate_fused_m:.2f}",
        )
    console.print(t)
    console.print(
        f"inter-robot matches tried {summary.matches_tried}, closures accepted "
        f"[green]{summary.closures_accepted}[/], rejected [yellow]{summary.closures_rejected}[/]"
    )
    tt = Table(title="per-stage time (mean ms per call)")
    tt.add_column("stage")
    tt.add_column("ms", justify="right")
    for k, v in sorted(summary.timings_ms.items()):
        tt.add_row(k, f"{v:.2f}")
    tt.add_row("[bold]front end + back end per keyframe[/]", f"{summary.per_keyframe_ms:.1f}")
    console.print(tt)
    if summary.skipped_reasons:
        console.print(f"[yellow]{len(summary.skipped_reasons)} frame(s) skipped[/], first: "
                      f"{summary.skipped_reasons[0]}")
    if summary.interrupted:
        console.print("[yellow]interrupted: results written so far are kept[/]")
    console.print(f"results in [bold]{summary.out_dir}[/]")


def _run_with_progress(robots, cfg, out_dir, viz, gt_shared_frame: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from shgm_slam.runner import run_slam

    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("frames", total=sum(len(s) for s in robots.values()))
        return run_slam(robots, cfg, out_dir, viz=viz, gt_shared_frame=gt_shared_frame,
                        progress=lambda done, total: bar.update(task, completed=done))


@app.command("run")
@handle_errors
def run(
    robot: Annotated[list[str], typer.Option("--robot", "-r", help="NAME=PATH[:start-end]; repeat per robot. "
                                             "The first robot defines the shared frame.")],
    odometry: Annotated[str, typer.Option(help="kiss-icp | gt | PATH to a KITTI/TUM poses file")] = "kiss-icp",
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    out: Annotated[Path | None, typer.Option("--out", help="results folder [default: results/<time>]")] = None,
    rerun: Annotated[str, typer.Option("--rerun", help="spawn | save | connect | off")] = "save",
    rerun_url: Annotated[str | None, typer.Option(help="gRPC URL for --rerun connect")] = None,
    depth_model: Annotated[Path | None, typer.Option(help="ONNX depth model (card next to it)")] = None,
    seg_model: Annotated[Path | None, typer.Option(help="ONNX segmentation model (card next to it)")] = None,
    gt_shared_frame: Annotated[bool, typer.Option(help="ground truths of all robots share one world frame")] = True,
) -> None:
    """Run the multi-robot system: odometry, semantic graphs, cross-robot matching, fused trajectories."""
    summary = _run_command(robot, odometry, config, out, rerun, rerun_url, depth_model, seg_model,
                           gt_shared_frame)
    _render_summary(summary)
    if summary.interrupted:
        raise typer.Exit(130)


def _run_command(robot_args, odometry, config, out, rerun_mode, rerun_url, depth_model, seg_model,
                 gt_shared_frame):
    from shgm_slam.config import OdometryKind, load_config
    from shgm_slam.errors import ConfigError
    from shgm_slam.io.export import make_results_dir
    from shgm_slam.runner import open_robots
    from shgm_slam.viz.rerun_logger import RerunMode, make_viz

    cfg = load_config(config)
    kinds = {k.value: k for k in OdometryKind if k is not OdometryKind.FILE}
    if odometry in kinds:
        cfg.odometry.kind = kinds[odometry]
    else:
        if not Path(odometry).is_file():
            raise ConfigError(f"--odometry {odometry!r}: not kiss-icp, gt, or an existing poses file")
        cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, Path(odometry)
    if depth_model is not None:
        cfg.perception.depth_model = depth_model
    if seg_model is not None:
        cfg.perception.seg_model = seg_model
    robots = open_robots(robot_args)
    try:
        mode = RerunMode(rerun_mode)
    except ValueError:
        raise ConfigError(f"--rerun {rerun_mode!r}: choose spawn, save, connect or off") from None
    out_dir = make_results_dir(out)
    viz = make_viz(mode, robots=list(robots), save_path=out_dir / "run.rrd", connect_url=rerun_url)
    return _run_with_progress(robots, cfg, out_dir, viz, gt_shared_frame)


@app.command("demo")
@handle_errors
def demo(
    out: Annotated[Path, typer.Option(help="results folder")] = Path("results/demo"),
    cache: Annotated[Path, typer.Option(help="where the simulated world is cached")] = Path("cache"),
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    rgb_only: Annotated[bool, typer.Option("--rgb-only", help="depth and labels from the ONNX demo models")] = False,
    rerun: Annotated[str, typer.Option("--rerun", help="spawn | save | connect | off")] = "save",
) -> None:
    """Simulate the airsim-like world (car, car, UAV) once, then run the whole system on it."""
    from shgm_slam.sim.scenarios import simulate

    world = cache / f"airsim-like-seed{seed}"
    if not (world / "scenario.json").is_file():
        console.print(f"simulating the airsim-like world into [bold]{world}[/] (once; cached afterwards)")
        result = _simulate_with_progress("airsim-like", world, seed)
        robots = list(result.sequences)
    else:
        import json

        robots = list(json.loads((world / "scenario.json").read_text())["robots"])
        console.print(f"using the cached world in [bold]{world}[/]")
    robot_args = [f"{r}={world / r}" for r in robots]
    depth_model = seg_model = None
    if rgb_only:
        depth_model, seg_model = Path("models/demo_depth.onnx"), Path("models/demo_seg.onnx")
    summary = _run_command(robot_args, "kiss-icp", None, out, rerun, None, depth_model, seg_model, True)
    _render_summary(summary)
    if (out / "run.rrd").is_file():
        console.print(f"open the recording with: [bold].venv/bin/rerun {out / 'run.rrd'}[/]")

# --- check-model (perception/) ----------------------------------------------------------------------
# --- bench (bench.py) -------------------------------------------------------------------------------
