"""Worlds and graphs: ``dump-config``, ``simulate`` (sim/), ``graph`` and ``match`` (graph/, matching/)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from shgm_slam.cli.app import app, handle_errors
from shgm_slam.cli.options import MAX_FRAMES, bounded, nonempty_path
from shgm_slam.cli.render import console, err_console, lit, render_match, warn_unused
from shgm_slam.cli.signals import stop_signals_as_interrupt
from shgm_slam.config import DescriptorKind, Dof, OutlierMode
from shgm_slam.io.json_text import to_json_text


@app.command("dump-config")
@handle_errors
def dump_config(
    config: Annotated[Path | None, typer.Option("--config", help="Show this YAML merged over the defaults.")] = None,
) -> None:
    """Print the effective configuration as YAML (defaults, or a file merged over them)."""
    from shgm_slam.config import load_config

    typer.echo(load_config(config).to_yaml(), nl=False)


def simulate_with_progress(scenario: str, out: Path, seed: int = 0, *, cached: bool = False, **kwargs: Any) -> Any:
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


def other_results(out: Path) -> str | None:
    """What another command wrote into folder ``out``, said for an error ("a run's or map server's results
    (metrics.json, ...)"), or None: none, or ``out`` holds a scenario (``scenario.json``: simulating there again
    is ``simulate``'s to judge) or is no folder. Recognised: a run's, demo's or map server's files
    (``io.export.run_output_files``, but for ``config.yaml`` alone: a user keeps theirs anywhere), a benchmark's
    report (``<stem>.json`` beside ``<stem>.md``, ``bench.report.write_report``) and a sequence
    (``io.export.SEQUENCE_MARKERS``).

    Raises:
        SimulationError: ``out`` cannot be read.
    """
    from shgm_slam.errors import SimulationError
    from shgm_slam.io.export import SEQUENCE_MARKERS, run_output_files

    try:
        if not out.is_dir() or (out / "scenario.json").exists():
            return None
        run_files = [p.name for p in run_output_files(out) if p.name != "config.yaml"]  # (a user's own config too)
        reports = sorted(p.stem for p in out.glob("*.json") if p.is_file() and p.with_suffix(".md").is_file())
    except OSError as exc:
        raise SimulationError(f"cannot read {out}: {exc.strerror or exc}; choose another folder (--out)") from None
    if run_files:
        return f"a run's or map server's results ({', '.join(run_files[:3])}{', ...' if len(run_files) > 3 else ''})"
    if reports:
        return f"a benchmark's report ({reports[0]}.json, {reports[0]}.md)"
    if all((out / name).is_file() for name in SEQUENCE_MARKERS):
        return f"a sequence ({', '.join(SEQUENCE_MARKERS)})"
    return None


@app.command("simulate")
@handle_errors
def simulate_command(
    scenario: Annotated[str, typer.Option("--scenario", "-s", help="synthia-like | airsim-like | disjoint | "
                                          "kitti-paths")],
    out: Annotated[Path, typer.Option("--out", "-o", parser=nonempty_path,
                                      help="output folder (one sequence per robot)")],
    seed: Annotated[int, typer.Option(min=0, max=2**31 - 1, help="world and trajectory seed")] = 0,
    resolution: Annotated[str, typer.Option(help="image size WIDTHxHEIGHT")] = "640x192",
    fps: Annotated[float, bounded(0.1, 100.0, help="frame rate, Hz (kitti-paths: KITTI's 10 Hz poses sampled at "
                                  "this rate: 5 = every 2nd frame)")] = 10.0,
    max_frames: Annotated[int | None, typer.Option(min=1, max=MAX_FRAMES, help="cut every robot's sequence")] = None,
    depth_noise: Annotated[float, bounded(0.0, 1.0, help="relative depth error std (0.05 = 5 %)")] = 0.0,
    label_noise: Annotated[float, bounded(0.0, 1.0, help="segment confusion probability "
                                               "(boundaries also jitter by 10x this many px)")] = 0.0,
    world_size: Annotated[float | None, bounded(150.0, 20000.0, help="city side length, metres")] = None,
    max_depth: Annotated[float, bounded(1.0, 10000.0, help="depth range, metres (farther = 0)")] = 200.0,
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

    from shgm_slam.errors import SimulationError
    from shgm_slam.sim.corruption import CorruptionLevels
    from shgm_slam.sim.simulate import parse_altitude, parse_resolution

    size = parse_resolution(resolution)
    altitude = parse_altitude(uav_altitude) if uav_altitude is not None else None
    corruption = CorruptionLevels.from_levels(depth_noise=depth_noise, label_noise=label_noise)
    if (found := other_results(out)) is not None:  # the scenario's folders and files would mix with them
        raise SimulationError(f"--out {out} holds {found}, not a scenario; give another folder for the scenario")
    if kitti_root is not None and scenario != "kitti-paths":
        warn_unused("--kitti-root", kitti_root, f"only the kitti-paths scenario reads KITTI poses, not {scenario}")
    with stop_signals_as_interrupt():  # SIGTERM/SIGHUP stop it like Ctrl-C: "interrupted", exit 130
        result = simulate_with_progress(
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


@app.command("graph")
@handle_errors
def graph(
    sequence: Annotated[str, typer.Argument(help="SEQ[:start-end] with depth/, semantic/ and poses.txt; the range "
                                            "is half-open: frames start..end-1 (08:0-1500 = 1500 frames)")],
    out: Annotated[Path, typer.Option("--out", "-o", parser=nonempty_path,
                                      help="graph file to write (shgm-graph/1 JSON)")],
    config: Annotated[Path | None, typer.Option("--config", help="YAML config (see dump-config)")] = None,
    connectivity: Annotated[float | None, typer.Option(help="edge threshold, metres (config: 10)")] = None,
    merge_radius: Annotated[float | None, typer.Option(help="same-label merge radius, m (config: 5)")] = None,
    keyframe_every: Annotated[
        float | None, bounded(0.1, 1000.0, help="keyframe spacing, metres (config: 2)")
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

    from shgm_slam import api
    from shgm_slam.config import load_config

    cfg = load_config(config)
    if descriptor:
        cfg.descriptor = cfg.descriptor.model_copy(update={"kind": descriptor})
    if mode:
        cfg.matching = cfg.matching.model_copy(update={"outlier_mode": mode})
    found = api.match(graph_a, graph_b, config=cfg, dof=dof)
    result = found.result
    if json_output:
        dof_fields = {"dof": 4 if found.gravity_aligned else 6, "dof_note": found.dof_note}
        if found.gravity_aligned:
            dof_fields["up_axis"] = list(found.up_axis)
        typer.echo(to_json_text({**result.to_json_dict(), **dof_fields, "decisive": found.decisive}, indent=None))
        return
    render_match(result, *found.nodes, cfg.descriptor.kind, cfg.matching.outlier_mode, found.dof_note,
                 cfg.matching.false_alarm_rate, cfg.backend.min_closures_to_anchor)

