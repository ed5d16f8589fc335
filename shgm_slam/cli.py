"""The ``shgm-slam`` command line: parse -> validate -> call one library function -> render.

This is the only module that catches ``ShgmError`` (one clear line, exit code 2) and talks to the
user. Each command is a thin wrapper over a library function that tests call directly.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from shgm_slam import __version__
from shgm_slam.config import DescriptorKind, Dof, OdometryKind, OutlierMode
from shgm_slam.errors import ShgmError
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE
from shgm_slam.io.json_text import to_json_text

console = Console()
err_console = Console(stderr=True)


def _nonempty_path(text: str) -> Path:
    """An output path from the command line; an empty one is refused (it would mean the current folder)."""
    if not str(text).strip():
        raise typer.BadParameter("is empty: give a folder or file path (for the current folder, '.')")
    return Path(text)


def _out_folder(text: str) -> Path:
    """An output folder from the command line: not empty (``_nonempty_path``) and not an existing file."""
    path = _nonempty_path(text)
    if path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{text} is a file; give a folder (it is created if missing)")
    return path


def _float_in(low: float, high: float) -> Callable[[str], float]:
    """A parser of a float option bounded to [low, high]: NaN and infinities are refused as such (a range
    check alone called NaN "not less than or equal to" the bound), then the range is checked."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise typer.BadParameter(f"{text!r} is not a number") from None
        if not math.isfinite(value):
            raise typer.BadParameter(f"{text} is not a finite number; give one in {low:g}..{high:g}")
        if not low <= value <= high:
            raise typer.BadParameter(f"{value:g} is out of range {low:g}..{high:g}")
        return value

    return parse


def _bounded(low: float, high: float, *names: str, **kwargs: Any) -> Any:
    """``typer.Option`` for a float in [low, high] (``_float_in``), its range shown in ``--help``."""
    return typer.Option(*names, parser=_float_in(low, high), metavar=f"<float {low:g}..{high:g}>", **kwargs)


def lit(value: object) -> str:
    """``value`` as text that rich prints literally (paths, names and messages may hold ``[...]``)."""
    return escape(str(value))

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

MAX_FRAMES = 1_000_000
"""Upper bound of every frame-count option (KITTI's longest sequence has 4,661 frames)."""


def handle_errors(fn: F) -> F:
    """Turn ``ShgmError`` into one red line on stderr and exit code 2 (the CLI's error boundary)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ShgmError as exc:
            err_console.print(f"[bold red]error:[/] {lit(exc)}", soft_wrap=True)  # one line: paths stay whole
            raise typer.Exit(2) from None
        except KeyboardInterrupt:  # before a run's loop (which keeps its results itself) or in another command
            err_console.print("[yellow]interrupted[/]")
            raise typer.Exit(INTERRUPTED_EXIT_CODE) from None

    return wrapper  # type: ignore[return-value]


def stops_like_ctrl_c(fn: F) -> F:
    """Run a command with SIGTERM and SIGHUP stopping it as Ctrl-C does (``_stop_signals_as_interrupt``): a
    benchmark stopped by ``timeout``, a job scheduler or a closed terminal writes what it finished and exits 130,
    instead of dying by the signal with its report unwritten."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with _stop_signals_as_interrupt():
            return fn(*args, **kwargs)

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


def _simulate_with_progress(scenario: str, out: Path, seed: int = 0, *, cached: bool = False, **kwargs: Any) -> Any:
    """``sim.simulate`` with one rich progress bar per robot; returns its ``ScenarioResult``. ``cached``: a world
    of a cache folder (``sim.cache.simulate_cached``, returns the folder): rendered beside it and renamed when
    finished, so an interrupted render is replaced by the next run instead of blocking it."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from shgm_slam.sim.cache import simulate_cached
    from shgm_slam.sim.simulate import simulate

    with Progress("[bold]{task.description}", BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=console) as bar:
        tasks: dict[str, Any] = {}

        def progress(robot: str, done: int, total: int) -> None:
            if robot not in tasks:
                tasks[robot] = bar.add_task(robot, total=total)
            bar.update(tasks[robot], completed=done)

        return (simulate_cached if cached else simulate)(scenario, out, seed=seed, progress=progress, **kwargs)


@app.command("simulate")
@handle_errors
def simulate_command(
    scenario: Annotated[str, typer.Option("--scenario", "-s", help="synthia-like | airsim-like | disjoint | "
                                          "kitti-paths")],
    out: Annotated[Path, typer.Option("--out", "-o", parser=_nonempty_path,
                                      help="output folder (one sequence per robot)")],
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world and trajectory seed")] = 0,
    resolution: Annotated[str, typer.Option(help="image size WIDTHxHEIGHT")] = "640x192",
    fps: Annotated[float, _bounded(0.1, 100.0, help="frame rate, Hz")] = 10.0,
    max_frames: Annotated[int | None, typer.Option(min=1, max=MAX_FRAMES, help="cut every robot's sequence")] = None,
    depth_noise: Annotated[float, _bounded(0.0, 1.0, help="relative depth error std (0.05 = 5 %)")] = 0.0,
    label_noise: Annotated[float, _bounded(0.0, 1.0, help="segment confusion probability "
                                               "(boundaries also jitter by 10x this many px)")] = 0.0,
    world_size: Annotated[float | None, _bounded(150.0, 20000.0, help="city side length, metres")] = None,
    max_depth: Annotated[float, _bounded(1.0, 10000.0, help="depth range, metres (farther = 0)")] = 200.0,
    compact: Annotated[bool, typer.Option("--compact", help="small world, short paths")] = False,
    kitti_root: Annotated[Path | None, typer.Option(help="KITTI folder with poses/ (kitti-paths)")] = None,
    kitti_drive: Annotated[list[str] | None, typer.Option(
        "--kitti-drive", help="kitti-paths: one robot per drive SEQ:START-END of KITTI 00-10 ground truth, "
        "repeatable. Frame ranges are half-open: frames START..END-1; SEQ alone = the whole sequence. Drives of "
        "one sequence share its frame (robots kitti08a, kitti08b, ...); other sequences are aligned onto the "
        "first. Default: 00:2600-2901 and 07:0-351")] = None,
    supersample: Annotated[int, typer.Option(min=1, max=8, help="colour from SxS rays per pixel, averaged as a "
                                             "camera's pixel integrates light (1: one ray, aliased)")] = 1,
    uav_altitude: Annotated[str | None, typer.Option(help="airsim-like: the UAV's altitude above the ground, "
                                                     "LOW-HIGH metres it varies between (default 44-54)")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing scenario")] = False,
) -> None:
    """Render a synthetic multi-robot scenario (RGB, depth, labels, GT poses) into sequence folders."""
    from rich.table import Table

    from shgm_slam.sim.corruption import CorruptionLevels
    from shgm_slam.sim.simulate import parse_altitude, parse_resolution

    size = parse_resolution(resolution)
    altitude = parse_altitude(uav_altitude) if uav_altitude is not None else None
    corruption = CorruptionLevels.from_levels(depth_noise=depth_noise, label_noise=label_noise)
    with _stop_signals_as_interrupt():  # SIGTERM/SIGHUP stop it like Ctrl-C: "interrupted", exit 130
        result = _simulate_with_progress(
            scenario, out, seed, resolution=size, fps=fps, max_frames=max_frames, corruption=corruption,
            world_size_m=world_size, max_depth_m=max_depth, compact=compact, kitti_root=kitti_root,
            kitti_robots=tuple(kitti_drive) if kitti_drive else None,
            overwrite=overwrite, supersample=supersample, uav_altitude_m=altitude,
        )
    table = Table(title=f"{lit(scenario)} (seed {seed}, {size[0]}x{size[1]} @ {fps:g} Hz) -> {lit(out)}")
    for col in ("robot", "kind", "frames", "path m", "shares view with (m)", "folder"):
        table.add_column(col, justify="right" if col in ("frames", "path m") else "left")
    for r in result.robots:
        shared = ", ".join(f"{b} {v:.0f}" for b, v in result.shared_view_m[r.name].items())
        table.add_row(lit(r.name), r.kind, str(r.frames), f"{r.path_length_m:.0f}", shared, lit(r.folder))
    console.print(table)
    console.print(f"{result.total_frames} frames at {result.frames_per_s:.1f} frames/s; world: {result.world_objects} "
                  f"objects, {result.world_triangles} triangles -> {lit(out / 'world.json')}")
# --- graph / match (graph/, descriptors/, matching/) -----------------------------------------------


@app.command("graph")
@handle_errors
def graph(
    sequence: Annotated[str, typer.Argument(help="SEQ[:start-end] with depth/, semantic/ and poses.txt; the range "
                                            "is half-open: frames start..end-1 (08:0-1500 = 1500 frames)")],
    out: Annotated[Path, typer.Option("--out", "-o", parser=_nonempty_path,
                                      help="graph file to write (shgm-graph/1 JSON)")],
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    connectivity: Annotated[float | None, typer.Option(help="edge threshold, metres (config: 10)")] = None,
    merge_radius: Annotated[float | None, typer.Option(help="same-label merge radius, m (config: 5)")] = None,
    keyframe_every: Annotated[
        float | None, _bounded(0.1, 1000.0, help="keyframe spacing, metres (config: 2)")
    ] = None,
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
    from shgm_slam.data.base import parse_sequence_spec
    from shgm_slam.errors import GraphError
    from shgm_slam.io.export import check_outside_sequence
    from shgm_slam.perception.perceive import depth_model_of

    seq = open_sequence(sequence)
    check_outside_sequence(out, parse_sequence_spec(sequence)[0])  # (a graph over its poses.txt, say)
    with Progress("{task.description}", BarColumn(), MofNCompleteColumn(), console=err_console,
                  transient=True) as bar:  # fmt: skip
        task = bar.add_task("keyframes", total=None)
        sg = build_graph_from_sequence(
            seq, cfg, keyframe_every_m=keyframe_every, depth_predicted=depth_model_of(seq) is not None,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )  # fmt: skip
    if len(sg) == 0:
        raise GraphError(
            f"{seq.name}: {len(sg.keyframe_ids)} keyframes gave no object (no valid depth with an object label in "
            f"range, extraction.max_depth_m); nothing written to {out}"
        )
    path = write_graph(out, sg.arrays())
    console.print(
        f"{seq.name}: {len(sg.keyframe_ids)} keyframes -> {len(sg)} nodes, {sg.num_edges} edges "
        f"(connectivity {cfg.graph.connectivity_m:g} m); wrote [bold]{path}[/]"
    )


@app.command("match")
@handle_errors
def match(
    graph_a: Annotated[Path, typer.Argument(help="graph A (shgm-graph/1 JSON): the reference frame")],
    graph_b: Annotated[Path, typer.Argument(help="graph B: the result maps its coordinates into A's frame")],
    descriptor: Annotated[
        DescriptorKind | None, typer.Option("--descriptor", help="node descriptor (default: the config's, histogram)")
    ] = None,
    mode: Annotated[
        OutlierMode | None, typer.Option("--mode", help="outlier rejection (default: the config's, clique)")
    ] = None,
    dof: Annotated[
        Dof, typer.Option("--dof", help="rotation freedom: 4 (gravity-aligned yaw), 6 (any), or auto: 4 about the "
                          "vertical both graphs lie flat along (maps, ground robots), else the config's")
    ] = Dof.AUTO,
    json_output: Annotated[bool, typer.Option("--json", help="print the match result as JSON")] = False,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """Match two semantic graphs: T_a_b (B -> A), the inlier node pairs and the stage timings."""

    from shgm_slam.config import load_config
    from shgm_slam.io.graph_json import read_graph
    from shgm_slam.matching import match_graphs
    from shgm_slam.matching.gravity import choose_dof

    cfg = load_config(config)
    descriptor_cfg = cfg.descriptor.model_copy(update={"kind": descriptor}) if descriptor else cfg.descriptor
    matching_cfg = cfg.matching.model_copy(update={"outlier_mode": mode}) if mode else cfg.matching
    a = read_graph(graph_a, connectivity_m=cfg.graph.connectivity_m)
    b = read_graph(graph_b, connectivity_m=cfg.graph.connectivity_m)
    matching_cfg, dof_note = choose_dof(dof, a.positions_xyz, b.positions_xyz, matching_cfg)
    result = match_graphs(a, b, descriptor_cfg, matching_cfg)
    if json_output:
        dof_fields = {"dof": 4 if matching_cfg.gravity_aligned else 6, "dof_note": dof_note}
        if matching_cfg.gravity_aligned:
            dof_fields["up_axis"] = list(matching_cfg.up_axis)
        typer.echo(to_json_text({**result.to_json_dict(), **dof_fields}, indent=None))
        return
    _render_match(result, len(a), len(b), descriptor_cfg.kind, matching_cfg.outlier_mode, dof_note)


def _render_match(
    result, nodes_a: int, nodes_b: int, kind: DescriptorKind, mode: OutlierMode, dof_note: str
) -> None:
    """Print a match result as a short rich summary."""
    import numpy as np
    from rich.table import Table

    from shgm_slam.geometry.se3 import rotation_angle

    verdict = "[bold green]match[/]" if result.success else f"[bold red]no match[/] ({lit(result.reason)})"
    console.print(f"{verdict}: {nodes_a} and {nodes_b} nodes, {kind.value} descriptors, {mode.value}")
    t = Table(show_header=False, box=None)
    t.add_column(style="bold")
    t.add_column()
    t.add_row("rotation", lit(dof_note))
    t.add_row("candidates", str(result.candidates))
    rmse = f"{result.rmse_m:.2f} m" if np.isfinite(result.rmse_m) else "-"
    judged = f"(rmse {rmse}, spread {result.spread_m:.1f} m, support {result.support} vs rival {result.rival_support})"
    if result.success:
        t.add_row("inliers", f"{result.num_inliers} {judged}")
    else:  # the rejected best hypothesis: its partners are not inliers of any match
        llr = f", LLR {result.llr:.1f} (threshold {result.llr_threshold:.1f})" if np.isfinite(result.llr) else ""
        best = f"best hypothesis: {result.num_inliers} partners {judged}{llr}"
        t.add_row("rejected", best if result.num_inliers else "no hypothesis")
    if result.T_a_b is not None:
        T = result.T_a_b
        t.add_row("T_a_b", f"translation {np.round(T[:3, 3], 2).tolist()} m, "
                           f"rotation {np.degrees(rotation_angle(T)):.1f} deg")  # fmt: skip
        t.add_row("", "\n".join("  ".join(f"{v:9.4f}" for v in row) for row in T))
    t.add_row("ms", ", ".join(f"{k} {v:.2f}" for k, v in result.timings_ms.items()))
    console.print(t)


# --- run / demo (pipeline.py) -----------------------------------------------------------------------


def _metres(value: float) -> str:
    """A distance in metres for an 80-column table: 2 decimals below 100 m, whole metres above, '-' for NaN."""
    if value != value:
        return "-"
    return f"{value:.2f}" if abs(value) < 100 else f"{value:.0f}"


def _summary_table(summary):
    """The per-robot run table; fits 80 columns (two-line headers, no vertical rules, long names fold)."""
    from rich import box
    from rich.table import Table

    t = Table(title="shgm-slam run", title_style="bold", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    t.add_column("robot", overflow="fold")
    numbers = ("frames", "kf", "nodes", "odo\nfail", "fused", "path\nm", "ATE\nodo", "ATE\nfused", "aligned\nodo/fused")
    for col in numbers:
        t.add_column(col, justify="right", no_wrap=True)
    for r in summary.robots:
        colour = "[yellow]" if r.provisional else "[green]" if r.localized else "[red]"
        fused = "yes" if r.localized else "no"
        if r.segments > 1:  # after odometry failures: which trajectory segments are in the shared frame
            fused = f"{r.segments_placed}/{r.segments}"
        fused = f"{colour}{fused}{' prov' if r.provisional else ''}[/]"
        t.add_row(
            lit(r.name), str(r.frames), str(r.keyframes), str(r.nodes),
            f"[yellow]{r.odometry_failures}[/]" if r.odometry_failures else "0", fused, _metres(r.path_length_m),
            _metres(r.ate_odometry_m), _metres(r.ate_fused_m),
            f"{_metres(r.ate_odometry_aligned_m)}/{_metres(r.ate_fused_aligned_m)}",
        )  # fmt: skip
    t.caption = ("ATE: metres in the shared frame (odo = odometry alone, started at its true pose; per trajectory "
                 "segment after odometry failures); aligned = SE(3)-aligned per robot; fused a/b = trajectory "
                 "segments placed / segments; prov = placed provisionally, no independent graph match confirms it yet "
                 "(see its warning)")
    return t


def _render_summary(summary) -> None:
    """Print the run summary as rich tables."""
    from rich.table import Table

    t = _summary_table(summary)
    console.print(t)
    joint = [f"{r.name} {_metres(r.ate_fused_joint_m)}" for r in summary.robots if not math.isnan(r.ate_fused_joint_m)]
    if len(joint) > 1:
        console.print(f"fused ATE after one SE(3) fit of the {len(joint)} placed robots together (how well they agree, "
                      f"without the first robot's own drift), metres: {lit(', '.join(joint))}; "
                      f"{_metres(summary.ate_joint_m)} over all")  # fmt: skip
    chosen: dict[tuple[str, str], list[str]] = {}
    for r in summary.robots:
        if r.odometry:
            chosen.setdefault((r.odometry, r.odometry_reason), []).append(r.name)
    for (kind, reason), names in chosen.items():
        console.print(f"odometry {lit(kind)} for {lit(', '.join(names))}: {lit(reason)}")
    shares = [f"{r.name} {100 * r.planar_turn_share:.0f} %" for r in summary.robots if r.planar_turn_share is not None]
    if shares:
        console.print("turns from planar (car-like) motion, share of measured frames: " + lit(", ".join(shares)))
    roads = [f"{r.name} {100 * r.road_step_share:.0f} %" for r in summary.robots if r.road_step_share is not None]
    slips = [f"{r.name} {r.image_steps}" for r in summary.robots if r.image_steps]
    if slips:
        console.print("KISS-ICP steps that slipped against the image motion, replaced by the step from image "
                      "tracks (frames): " + lit(", ".join(slips)))  # fmt: skip
    slides = [f"{r.name} {r.image_windows}" for r in summary.robots if r.image_windows]
    if slides:
        console.print("KISS-ICP seconds that slid against the image motion, corrected by the motion from image "
                      "tracks (frames): " + lit(", ".join(slides)))  # fmt: skip
    if roads:
        console.print("steps from the road's image motion, share of measured frames: " + lit(", ".join(roads)))
    drifts = [f"{r.name} {r.measured_drift_deg_per_100m:.1f}" for r in summary.robots
              if r.measured_drift_deg_per_100m is not None]  # fmt: skip
    if drifts:
        console.print("odometry heading drift measured by the robot's own loop closures, beyond the pose graph's "
                      "prior (deg per 100 m; its odometry weighs that much less): " + lit(", ".join(drifts)))
    scaled = [
        f"{r.name} x{r.depth_scale:.3f} ({100 * r.depth_scale_share:.0f} % of frames)" if r.depth_scale is not None
        else f"{r.name} not scaled (no level road at that height: a UAV or a tilted camera)"
        for r in summary.robots if r.depth_scale_share is not None
    ]  # fmt: skip
    if scaled:
        console.print("predicted depth scaled to the camera height above the road (perception.camera_height_m): "
                      + lit(", ".join(scaled)))  # fmt: skip
    noisy = [f"{r.name} {100 * r.depth_noise_rel:.1f} % (voxel {r.voxel_size_m:g} m)" for r in summary.robots
             if r.depth_noise_rel and r.voxel_size_m is not None
             and r.odometry in (OdometryKind.KISS_ICP.value, OdometryKind.HYBRID.value)]
    if noisy:
        console.print("depth noise, relative to the depth (measured on the first frames; KISS-ICP's voxel and spacing "
                      "filter follow it, odometry.depth_noise_rel): " + lit(", ".join(noisy)))  # fmt: skip
    for r in summary.robots:
        if r.odometry_failures:
            more = f" (+{r.odometry_failures - 3} more in metrics.json)" if r.odometry_failures > 3 else ""
            console.print(
                f"[yellow]{lit(r.name)}: odometry diverged {r.odometry_failures}x[/], restarted as new trajectory "
                f"segments: " + lit("; ".join(r.failure_reasons[:3]) + more)
            )
        for text in r.warnings:  # degenerate data (also in metrics.json and the viewer's log)
            console.print(f"[yellow]{lit(r.name)}: warning:[/] {lit(text)}")
    console.print(
        f"inter-robot matches tried {summary.matches_tried}, closures accepted "
        f"[green]{summary.closures_accepted}[/], rejected [yellow]{summary.closures_rejected}[/]"
    )
    for line in filter(None, (p.never_met() for p in summary.pairs)):
        console.print(f"[yellow]{lit(line)}[/]")
    for line in summary.last_looks:  # robots that rested on one piece of evidence at the end
        console.print(lit(line))
    tt = Table(title="per-stage time (mean ms per call)")
    tt.add_column("stage")
    tt.add_column("ms", justify="right")
    for k, v in sorted(summary.timings_ms.items()):
        tt.add_row(k, f"{v:.2f}")
    tt.add_row("[bold]front end + back end per keyframe[/]", f"{summary.per_keyframe_ms:.1f}")
    console.print(tt)
    if summary.skipped_reasons:
        console.print(f"[yellow]{len(summary.skipped_reasons)} frame(s) skipped[/], first: "
                      f"{lit(summary.skipped_reasons[0])}")
    if summary.interrupted:
        console.print("[yellow]interrupted: results written so far are kept[/]")
    console.print(f"results in [bold]{lit(summary.out_dir)}[/]")


def _run_with_progress(robots, cfg, out_dir, viz, gt_shared_frame: bool, fronts=None, jobs: int | None = None):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from shgm_slam.robot.remote import default_jobs
    from shgm_slam.runner import run_slam

    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("frames", total=sum(len(s) for s in robots.values()))
        return run_slam(robots, cfg, out_dir, viz=viz, gt_shared_frame=gt_shared_frame, fronts=fronts,
                        progress=lambda done, total: bar.update(task, completed=done),
                        jobs=default_jobs(len(robots), jobs))


JobsOption = Annotated[
    int | None,
    typer.Option("--jobs", "-j", min=1, max=256, show_default="one per robot, at most one per core",
                 help="worker processes for the robots' front ends (the same results, sooner); 1: everything in "
                 "this one process"),
]


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
    out: Annotated[Path | None, typer.Option("--out", parser=_nonempty_path,
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
    _render_summary(summary)
    if summary.interrupted:
        raise typer.Exit(INTERRUPTED_EXIT_CODE)


def _apply_run_options(cfg, odometry: str | None, depth_model: Path | None, seg_model: Path | None):
    from shgm_slam.config import OdometryKind
    from shgm_slam.errors import ConfigError

    kinds = {k.value: k for k in OdometryKind if k is not OdometryKind.FILE}
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
    from shgm_slam.errors import ConfigError
    from shgm_slam.io.export import claimed_results_dir
    from shgm_slam.runner import check_out_outside_sequences, open_robots, prepare_frontends
    from shgm_slam.viz.rerun_logger import DEFAULT_CONNECT_URL, RerunMode, make_viz, viewer_address

    robots = open_robots(robot_args)
    if out is not None:
        check_out_outside_sequences(out, robot_args)
    try:
        mode = RerunMode(rerun_mode)
    except ValueError:
        raise ConfigError(f"--rerun {rerun_mode!r}: choose spawn, save, connect or off") from None
    if mode is RerunMode.CONNECT:
        viewer_address(rerun_url or DEFAULT_CONNECT_URL)  # a malformed URL is refused before any work
    # everything that can refuse the run (config, models, first frames) before --out gets a file: a refused
    # run must not leave files that make the next run with the same --out ask for --overwrite
    fronts = prepare_frontends(robots, cfg)
    with claimed_results_dir(out, overwrite=overwrite) as out_dir:  # locked: a second run on it is refused
        viz = make_viz(mode, robots=list(robots), save_path=out_dir / "run.rrd", connect_url=rerun_url,
                       max_cloud_points=8000)
        with _stop_signals_as_interrupt():
            return _run_with_progress(robots, cfg, out_dir, viz, gt_shared_frame, fronts, jobs)


@contextlib.contextmanager
def _stop_signals_as_interrupt():
    """SIGTERM and SIGHUP stop a run like Ctrl-C does: the results so far are written, with the summary."""

    def interrupt(signum, _frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    stops = [sig for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)) if sig is not None]
    previous = {sig: signal.signal(sig, interrupt) for sig in stops}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, _late_stop if _OWN_PROCESS else handler)


_OWN_PROCESS = False
"""True when this module's ``main`` runs the process (the ``shgm-slam`` command), not a test calling it."""


LATE_STOP_NOTE = "interrupted after the results were written (they are complete)"
"""What a stop signal that arrives after a command's results are written prints before exit code 130."""


def _late_stop(_signum, _frame) -> None:
    """A stop signal after the results are written (the summary being printed, the process exiting): end
    now with the interrupted exit code, saying the results are complete, instead of dying by the signal
    mid-shutdown."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    with contextlib.suppress(OSError):
        os.write(2, f"\n{LATE_STOP_NOTE}\n".encode())
    os._exit(INTERRUPTED_EXIT_CODE)


@app.command("server")
@handle_errors
def server_command(
    out: Annotated[Path, typer.Option("--out", parser=_nonempty_path,
                                      help="results folder (a journal there is replayed: restart)")],
    listen: Annotated[
        str | None, typer.Option(help="Zenoh endpoint(s) to listen on, comma-separated",
                                  show_default="tcp/127.0.0.1:7447")
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
        float, _bounded(0.5, 3600, help="seconds of silence before a robot is stale")
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
        with _stop_signals_as_interrupt():
            result = serve(cfg, out, listen=listen, reference=reference, expect=expect, viz=viz,
                           stale_after_s=stale_after, started=lambda resumed: console.print(
                               f"map server listening on {lit(listen or 'tcp/127.0.0.1:7447')}"
                               + (f", expecting {expect} robots" if expect else "; Ctrl-C to finish")
                               + (f"; {resumed}" if resumed else "")),
                           say=lambda line: console.print(f"  {lit(line)}"))  # fmt: skip
    s = result.summary
    for name, r in s["robots"].items():
        placed = _placed_text(r["placed"], r["provisional"])
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


def _placed_text(placed: list[str], provisional: list[str]) -> str:
    """``car2, car2#1 (provisional)``: the placed agents, provisional ones marked; "not placed" for none."""
    return ", ".join(a + (" (provisional)" if a in provisional else "") for a in placed) or "not placed"


@app.command("robot")
@handle_errors
def robot_command(
    robot: Annotated[str, typer.Argument(help="NAME=PATH[:start-end] (frames start..end-1)")],
    connect: Annotated[
        str | None, typer.Option(help="map server's Zenoh endpoint(s), comma-separated",
                                  show_default="tcp/127.0.0.1:7447")
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
    out: Annotated[Path | None, typer.Option("--out", parser=_nonempty_path,
                                             help="write this robot's trajectories here")] = None,
    wait: Annotated[
        float, _bounded(0, 3600, help="seconds to wait for the server after the last frame")
    ] = 60.0,
) -> None:
    """One robot in its own process: front end, keyframes to the map server, corrections applied."""
    from shgm_slam.config import load_config
    from shgm_slam.robot.drive import drive_robot
    from shgm_slam.runner import open_robots

    cfg = _apply_run_options(load_config(config), odometry, depth_model, seg_model)
    (name, seq), = open_robots([robot]).items()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    with _stop_signals_as_interrupt(), Progress(f"{lit(name)}: frames", BarColumn(), MofNCompleteColumn(),
                                                TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task("frames", total=len(seq))
        s = drive_robot(name, seq, cfg, connect=connect, realtime=realtime, out_dir=out, wait_s=wait,
                        progress=lambda done, total: bar.update(task, completed=done))  # fmt: skip
    placed = _placed_text(s.placed_agents, s.provisional_agents)
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
        console.print("[red]the map server did not acknowledge every keyframe (is it running? see --connect)[/red]")
        raise typer.Exit(3)
    if not s.server_finished:
        console.print(f"[yellow]the map server had not finished after --wait {wait:g} s[/] (waiting for more "
                      "robots, --expect?): this robot's place may still change; the server's results folder "
                      "holds the final trajectories")  # fmt: skip
        raise typer.Exit(4)


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
        _simulate_with_progress("airsim-like", folder, seed, cached=True)

    world, kinds = prepare_world(cache, seed, simulate_world)
    console.print(f"world: [bold]{lit(world)}[/] robots: {lit(', '.join(f'{r} ({k})' for r, k in kinds.items()))}")
    cfg = demo_config(rgb_only=rgb_only)
    summary = _run_command([f"{r}={world / r}" for r in kinds], cfg, out, rerun, None, True, overwrite, jobs)
    _render_summary(summary)
    if (out / "run.rrd").is_file():
        console.print(f"open the recording with: [bold].venv/bin/rerun {lit(out / 'run.rrd')}[/]")
    console.print(f"evaluate against ground truth: [bold]shgm-slam eval {lit(out)}[/] or "
                  f"[bold]evo_ape tum {lit(out / 'car2_gt_tum.txt')} {lit(out / 'car2_fused_tum.txt')}[/]")


@app.command("eval")
@handle_errors
def eval_command(
    results: Annotated[Path, typer.Argument(help="results folder of run or demo")],
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
        console.print(_eval_table(result))
    if nothing:  # a script must not read this as a measured result
        raise DataError(f"no robot of {results} could be evaluated (the notes say why): no ATE was measured")
    if json_output:
        return
    if result.interrupted:
        console.print("[yellow]this run was interrupted[/]: its trajectories end where it was stopped "
                      "(metrics.json: interrupted)")  # fmt: skip
    if result.gt_files_written:
        console.print(f"wrote {len(result.gt_files_written) // 2} ground-truth trajectories; e.g. evo_ape tum "
                      f"{lit(result.gt_files_written[0])} {lit(results / (result.reference_robot + '_fused_tum.txt'))}")


def _eval_table(result):
    """The per-robot ``eval`` table; fits 80 columns (numbers never wrap, long names and notes fold)."""
    from rich import box
    from rich.table import Table

    table = Table(title=f"fused ATE in the shared frame ({lit(result.reference_robot)}'s), metres",
                  box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)  # fmt: skip
    table.add_column("robot", overflow="fold")
    for col in ("poses", "ATE", "aligned", "joint", "max"):
        table.add_column(col, justify="right", no_wrap=True)
    table.add_column("note", overflow="fold", ratio=1)
    for r in result.robots:
        table.add_row(lit(r.name), f"{r.evaluated_poses}/{r.fused_poses}", _metres(r.ate_fused_m),
                      _metres(r.ate_fused_aligned_m), _metres(r.ate_fused_joint_m), _metres(r.max_error_m),
                      lit(r.note))  # fmt: skip
    table.caption = (
        f"ground truth from the {result.gt_source}; aligned = SE(3)-aligned per robot; joint = one SE(3) fit "
        f"of all {result.joint_robots} placed robots together ({_metres(result.ate_joint_m)} m over all their "
        "poses): how well they agree, without the first robot's own drift"
    )
    return table


# --- check-model (perception/) ----------------------------------------------------------------------
@app.command("check-model")
@handle_errors
def check_model_command(
    model: Annotated[Path, typer.Argument(help="the .onnx model")],
    card: Annotated[Path | None, typer.Option("--card", help="card YAML (default: beside model)")] = None,
    image: Annotated[Path | None, typer.Option("--image", help="image (default: synthetic)")] = None,
    preview: Annotated[Path | None, typer.Option("--preview", help="write image | output PNG")] = None,
    runs: Annotated[int, typer.Option(min=1, max=1000, help="timed runs (median reported)")] = 5,
    threads: Annotated[int, typer.Option(min=0, max=256, help="onnxruntime intra-op threads (0 = all cores)")] = 2,
) -> None:
    """Validate a model card against its ONNX model, run it, show shapes, value ranges and speed; with
    --preview FILE.png also write a preview (image | output side by side)."""
    from rich.table import Table

    from shgm_slam.perception.preview import check_model

    report = check_model(model, card, image, preview, runs=runs, threads=threads)
    table = Table(title=f"{lit(report.model_path.name)}: {report.task.value} model", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    table.add_row("card", lit(report.card_path))
    table.add_row("providers", ", ".join(report.providers))
    table.add_row("input", lit(f"{report.input_name} {list(report.input_shape)} {report.input_type}"))
    table.add_row("output", lit(f"{report.output_name} {list(report.output_shape)} {report.output_type}"))
    table.add_row("image", lit(f"{report.image_source} ({report.image_wh[0]}x{report.image_wh[1]})"))
    table.add_row("ran on", lit(f"input {list(report.fed_shape)} -> output {list(report.raw_output_shape)}"))
    unit = " m" if report.label_fractions == {} else " (train ids)"
    table.add_row("values", f"{report.value_min:.3g} .. {report.value_max:.3g}{unit}, "
                            f"valid {100 * report.valid_fraction:.1f} %")
    if report.label_fractions:
        top = list(report.label_fractions.items())[:8]
        table.add_row("labels", lit(", ".join(f"{name} {100 * f:.1f} %" for name, f in top)))
    t = report.timings_ms
    table.add_row("ms/frame", f"{t['total_ms']:.1f} (pre {t['preprocess_ms']:.1f}, model "
                              f"{t['inference_ms']:.1f}, post {t['postprocess_ms']:.1f}; median of {runs})")
    for note in report.notes:
        table.add_row("note", lit(note))
    if report.preview_path is not None:
        table.add_row("preview", lit(report.preview_path))
    console.print(table)
    if report.valid_fraction == 0.0:  # a model that gives nothing usable is an error, not a report
        from shgm_slam.errors import ModelError

        what = "depth (all non-finite or <= 0)" if not report.label_fractions else "label (all ignore, 255)"
        raise ModelError(f"{model}: valid output 0 %: every {what} on {report.image_source}; check the card "
                         "(output kind, scale, classes) and the model")
    if report.value_min == report.value_max:  # `run` refuses such a model: so does its check
        from shgm_slam.errors import ModelError

        what = f"{report.value_min:.3g} m" if not report.label_fractions else f"train id {report.value_min:.0f}"
        why = " (a graph of one class cannot be matched)" if report.label_fractions else ""
        raise ModelError(f"{model}: constant output ({what} wherever valid) on {report.image_source}; `run` and "
                         f"`perceive` refuse such a model{why}: check the card (output kind, scale, clamp range, "
                         "classes) and the model")


@app.command("perceive")
@handle_errors
def perceive_command(
    sequence: Annotated[str, typer.Argument(help="SEQ[:start-end]; the range is half-open: frames start..end-1")],
    out: Annotated[Path, typer.Option("--out", "-o", parser=_nonempty_path,
                                      help="output sequence folder (run it again to resume)")],
    depth_model: Annotated[Path | None, typer.Option(help="ONNX depth model (card next to it)")] = None,
    seg_model: Annotated[Path | None, typer.Option(help="ONNX segmentation model (card next to it)")] = None,
    batch_size: Annotated[int, typer.Option(min=1, max=256, help="frames per model call")] = 8,
    threads: Annotated[int, typer.Option(min=0, max=256, help="onnxruntime intra-op threads (0 = all cores)")] = 0,
    provider: Annotated[str, typer.Option(help="auto (CUDA when onnxruntime-gpu has it) | cpu | cuda")] = "auto",
    copy_images: Annotated[bool, typer.Option("--copy-images", help="copy the images instead of linking")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="redo every frame of an existing --out")] = False,
) -> None:
    """Run the depth and segmentation networks once over a sequence; write depth/ and semantic/ into a
    complete sequence folder (images linked, calib, times, poses) that `run --robot NAME=OUT` reads."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    from shgm_slam.errors import ConfigError
    from shgm_slam.perception.perceive import ImageMode, Provider, perceive

    try:
        chosen = Provider(provider)
    except ValueError:
        raise ConfigError(f"--provider {provider!r}: choose auto, cpu or cuda") from None
    with _stop_signals_as_interrupt(), Progress(  # SIGTERM/SIGHUP stop it like Ctrl-C: resumable
        "[bold]{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
        console=console, transient=True,
    ) as bar:  # fmt: skip
        task = bar.add_task("frames", total=None)
        result = perceive(
            sequence, out, depth_model=depth_model, seg_model=seg_model, batch_size=batch_size, threads=threads,
            provider=chosen, images=ImageMode.COPY if copy_images else ImageMode.LINK, overwrite=overwrite,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )  # fmt: skip
    providers = ", ".join(f"{k} {v[0].removesuffix('ExecutionProvider')}" for k, v in result.providers.items())
    speed = ", ".join(f"{k} {v:.1f}" for k, v in result.inference_ms_per_frame.items())
    console.print(f"{lit(result.source)}: {result.computed} frame(s) computed, {result.reused} reused of "
                  f"{result.frames} in {result.wall_s:.1f} s ({providers}" + (f"; ms/frame {speed})" if speed else ")"))
    for note in result.notes:
        console.print(f"[yellow]note[/]: {lit(note)}")
    if result.unreadable:
        first, why = min(result.unreadable.items())
        console.print(f"[yellow]skipped[/]: {len(result.unreadable)} unreadable image(s), first frame {first}: "
                      f"{lit(why)}; written without depth or labels (`run` skips them); fix the file(s) and run "
                      "the same command again to redo them")  # fmt: skip
    if result.interrupted:
        console.print(f"[yellow]interrupted[/]: run the same command again to finish {lit(out)}")
        raise typer.Exit(INTERRUPTED_EXIT_CODE)
    console.print(f"wrote [bold]{lit(out)}[/]; use it with: shgm-slam run --robot NAME={lit(out)}"
                  + (" --odometry visual (predicted depth)" if result.providers.get("depth") else ""))


# --- bench (bench.py) -------------------------------------------------------------------------------


def markdown_tables(text: str, width: int):
    """``text`` (a benchmark's markdown report) as rich renderables for a terminal ``width`` columns wide:
    each markdown table whose rows are wider becomes a table that folds its cells (nothing cut), other
    lines stay as they are."""
    from rich import box
    from rich.table import Table
    from rich.text import Text

    out, rows = [], []

    def flush() -> None:
        if not rows:
            return
        cells = [[c.strip() for c in row.strip().strip("|").split("|")] for row in rows]
        if len(cells) < 2 or max(map(len, rows)) <= width or not set("".join(cells[1])) <= set("-: "):
            out.extend(Text(row) for row in rows)
        else:
            t = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
            longest = [max((len(w) for row in (cells[0], *cells[2:]) if k < len(row) for w in row[k].split()),
                           default=1) for k in range(len(cells[0]))]  # fmt: skip
            whole_words = sum(longest) + 3 * len(longest) <= width  # else rich folds words to fit
            for k, (head, rule) in enumerate(zip(cells[0], cells[1], strict=False)):
                t.add_column(head, overflow="fold", justify="right" if rule.endswith(":") else "left",
                             min_width=longest[k] if whole_words else None)
            for row in cells[2:]:
                t.add_row(*row[: len(cells[0])])
            out.append(t)
        rows.clear()

    for line in text.splitlines():
        if line.lstrip().startswith("|"):
            rows.append(line)
            continue
        flush()
        out.append(Text(line))
    flush()
    return out


def print_report(text: str) -> None:
    """Print a benchmark's markdown report: raw markdown when piped (the .md file is written anyway), tables
    that fit the terminal when it is one."""
    if not console.is_terminal:
        typer.echo(text)
        return
    for item in markdown_tables(text, console.width):
        console.print(item)


@bench_app.command("simulate")
@handle_errors
@stops_like_ctrl_c
def bench_simulate(
    out: Annotated[Path, typer.Option("--out", "-o", parser=_nonempty_path,
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder: localization.json, .md, pr_curve.png")]
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


@bench_app.command("sparse")
@handle_errors
@stops_like_ctrl_c
def bench_sparse(
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder: sparse.json, sparse.md")]
    = Path("results/bench_sparse"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'A-B' or 'A,B,C' (tuning 10-19; report 210-219)")]
    = "10-19",
    pairs: Annotated[int, typer.Option(min=1, max=10000, help="overlapping pairs per world (as many negatives)")] = 10,
    full_rotation: Annotated[bool, typer.Option(help="also match every pair 6-DoF")] = True,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
) -> None:
    """Sparse, map-like localization (no rendering): map classes only, 30-60 % missed, 0.5-2 m noise,
    label confusions, drives sharing 50-300 m, far-apart negatives; localized / wrong / negatives / ms."""

    from shgm_slam.bench.localization_sparse import SparseOptions, run_sparse_benchmark, sparse_markdown
    from shgm_slam.bench.report import write_report
    from shgm_slam.bench.seeds import parse_seeds
    from shgm_slam.config import load_config

    cfg = load_config(config)
    seed_list = parse_seeds(seeds)
    options = SparseOptions(seeds=seed_list, pairs_per_seed=pairs, full_rotation=full_rotation)
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder")] = Path("results/bench_system"),
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder")] = Path("results/bench_scale"),
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder")] = Path("results/bench_robots"),
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

    sizes = _int_list(fleets, "--fleets")
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder")] = Path("results/bench_distributed"),
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
    from shgm_slam.demo import prepare_world
    from shgm_slam.errors import ConfigError

    try:
        modes = [Fault(f.strip()) for f in faults.split(",") if f.strip()]
    except ValueError:
        raise ConfigError(f"--faults {faults!r}: comma-separated none, robot, server") from None
    world, _ = prepare_world(cache, seed, lambda folder: _simulate_with_progress("airsim-like", folder, seed,
                                                                                   cached=True))
    with console.status("starting") as status:
        result = run_distributed_benchmark(world, out, faults=modes, config=config,
                                           progress=lambda msg: status.update(msg))  # fmt: skip
    print_report(distributed_markdown(result))
    console.print(f"wrote {lit(out / 'distributed.json')} and {lit(out / 'distributed.md')}")


def _int_list(text: str, option: str) -> tuple[int, ...]:
    """Comma-separated integers of ``option`` (e.g. ``--fleets 1,2,4``)."""
    from shgm_slam.errors import ConfigError

    try:
        values = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"{option} {text!r}: write comma-separated whole numbers, e.g. 1,2,4,8") from None
    if not values:
        raise ConfigError(f"{option} {text!r} names no value")
    return values


def _world_seeds(seeds: str) -> tuple[int, ...]:
    """``--seeds`` of the held-out style benchmarks: 'report', 'tuning', an inclusive range A-B or A,B,C."""
    from shgm_slam.bench import heldout
    from shgm_slam.bench.seeds import parse_seeds

    return parse_seeds(seeds, {"report": heldout.REPORT_SEEDS, "tuning": heldout.TUNING_SEEDS})


@bench_app.command("heldout")
@handle_errors
@stops_like_ctrl_c
def bench_heldout(
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder (resumes the runs already in it)")]
    = Path("results/bench_heldout"),
    seeds: Annotated[str, typer.Option(help="world seeds: 'report' (210-219), 'tuning' (10-29), A-B or A,B,C")]
    = "report",
    scenario: Annotated[list[str] | None, typer.Option(help="scenario (repeatable)", show_default="all four")] = None,
    mode: Annotated[list[str] | None, typer.Option(help="files | rgb (repeatable)", show_default="both")] = None,
    max_frames: Annotated[
        int | None, typer.Option(min=10, max=MAX_FRAMES, help="cut every robot's sequence (quick looks)")
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
    depth_noise: Annotated[float, _bounded(0.0, 0.5, help="relative depth error std of the renders the "
                                               "files mode reads (0.05 = 5 %; cached apart)")] = 0.0,
    label_noise: Annotated[float, _bounded(0.0, 1.0, help="segment confusion probability of the "
                                               "renders' labels (boundaries jitter by 10x this many px)")] = 0.0,
    replay_from: Annotated[
        Path | None,
        typer.Option(help="an earlier benchmark folder: run only the map server again on its recorded keyframes "
                     "(matching and back-end changes; no rendering, perception or odometry)"),
    ] = None,
) -> None:
    """The system with the default configuration on many unseen worlds: placed right, false merges,
    not placed, odometry failures (ground truth and detected), accepted matches and placements judged
    at their own place (false ones withdrawn later included), per scenario and input."""
    from shgm_slam.bench import heldout
    from shgm_slam.errors import ConfigError
    from shgm_slam.sim.corruption import CorruptionLevels
    from shgm_slam.sim.simulate import check_uav_altitude, parse_altitude, parse_resolution

    seed_list = _world_seeds(seeds)
    size = parse_resolution(resolution)
    altitude = parse_altitude(uav_altitude) if uav_altitude is not None else None
    if altitude is not None:
        check_uav_altitude("airsim-like", altitude, heldout.MAX_DEPTH_M)
    for s in scenario or ():
        if s not in heldout.SCENARIOS:
            raise ConfigError(f"--scenario {s!r}: choose from {', '.join(heldout.SCENARIOS)}")
    try:
        modes = tuple(heldout.InputMode(m) for m in (mode or [m.value for m in heldout.InputMode]))
    except ValueError:
        raise ConfigError(f"--mode {mode}: choose files or rgb") from None
    options = heldout.HeldoutOptions(scenarios=tuple(scenario or heldout.SCENARIOS), seeds=seed_list, modes=modes,
                                     max_frames=max_frames, cache=cache, replay_from=replay_from, resolution=size,
                                     supersample=supersample, uav_altitude_m=altitude,
                                     corruption=CorruptionLevels.from_levels(depth_noise, label_noise),
                                     front_end_jobs=None if jobs == 1 else 1)  # fmt: skip
    if replay_from is not None and not (replay_from / "runs").is_dir():
        raise ConfigError(f"--replay-from {replay_from}: no runs/ folder there (a `bench heldout` results folder)")
    with console.status("starting") as status:
        results = heldout.run_heldout_benchmark(out, options, progress=lambda msg: status.update(msg), jobs=jobs)
    print_report(heldout.heldout_markdown(results))
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder (resumes the runs already in it)")]
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

    for s in scenario or ():
        if s not in heldout.SCENARIOS:
            raise ConfigError(f"--scenario {s!r}: choose from {', '.join(heldout.SCENARIOS)}")
    levels = dq.LEVELS if not level else tuple(dq.parse_level(x) for x in level)
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
        return chosen

    options = dq.DepthQualityOptions(
        scenarios=tuple(scenario or dq.DepthQualityOptions.scenarios), seeds=_world_seeds(seeds), levels=levels,
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=_out_folder,
                                      help="results folder: table3.json, table3.md")]
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
    depth_noise: Annotated[float, _bounded(0.0, 1.0, help="relative depth error std of the renders")] = 0.0,
    label_noise: Annotated[float, _bounded(0.0, 1.0, help="label confusion of the renders")] = 0.0,
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
        seeds=table3.parse_seeds(seeds), runs=runs, kinds=tuple(descriptor or DescriptorKind),
        splits=tuple(split or (s.name for s in table3.SPLITS)), resolution=parse_resolution(resolution),
        max_frames=max_frames, mode=bench_mode, depth_noise=depth_noise, label_noise=label_noise, cache=cache,
    )  # fmt: skip
    with console.status("starting") as status:
        results = table3.run_table3(options, progress=lambda msg: status.update(msg), jobs=jobs,
                                    kitti_root=kitti_root)  # fmt: skip
    json_path, md_path = table3.write_table3(results, out)
    print_report(table3.table3_markdown(results))
    console.print(f"wrote {lit(json_path)} and {lit(md_path)} ({results.wall_s:.0f} s)")


_EXIT_CODE = 1
"""The command's exit code for ``_skip_teardown`` (1 until the command ends normally or by SystemExit)."""


def _skip_teardown() -> None:
    """The last exit hook: end the process with the command's exit code, skipping the interpreter's teardown.

    Python puts the default signal handlers back for that teardown (finalizers of modules and objects), so a
    stop signal arriving then killed a finished run by the signal (exit -15, results written, summary
    printed) instead of ending it with 0 or 130. Non-daemon threads are joined and the other exit hooks
    (logging, Rerun) have run before this one, which ``main`` registers first so that it runs last.
    """
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(_EXIT_CODE)


def main() -> None:
    """The ``shgm-slam`` command (entered through ``shgm_slam.__main__``, which loads this module)."""
    import atexit

    global _OWN_PROCESS, _EXIT_CODE
    _OWN_PROCESS = True
    atexit.register(_skip_teardown)
    try:
        app()
        _EXIT_CODE = 0
    except SystemExit as exc:
        _EXIT_CODE = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        raise


if __name__ == "__main__":
    main()
