"""What the commands print: the consoles, the run summary, match and evaluation tables, markdown reports."""

from __future__ import annotations

import math

import typer
from rich.console import Console
from rich.markup import escape

from shgm_slam.config import DescriptorKind, OdometryKind, OutlierMode

console = Console()
err_console = Console(stderr=True)


def lit(value: object) -> str:
    """``value`` as text that rich prints literally (paths, names and messages may hold ``[...]``)."""
    return escape(str(value))


def render_match(
    result, nodes_a: int, nodes_b: int, kind: DescriptorKind, mode: OutlierMode, dof_note: str,
    false_alarm_rate: float, pieces_to_place: int,
) -> None:
    """Print a match result as a short rich summary; an accepted one with its evidence against chance
    (``match_evidence``)."""
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
        t.add_row("evidence", match_evidence(result, false_alarm_rate, pieces_to_place))
    else:  # the rejected best hypothesis: its partners are not inliers of any match
        llr = f", LLR {result.llr:.1f} (threshold {result.llr_threshold:.1f})" if np.isfinite(result.llr) else ""
        best = f"best hypothesis: {result.num_inliers} partners {judged}{llr}"
        t.add_row("rejected", best if result.num_inliers else "no hypothesis")
    if result.T_a_b is not None:
        T = result.T_a_b
        t.add_row("T_a_b", f"translation {np.round(T[:3, 3], 2).tolist()} m, "
                           f"rotation {np.degrees(rotation_angle(T)):.1f} deg")  # fmt: skip
        t.add_row("", "\n".join("  ".join(f"{v:9.4f}" for v in row) for row in T))
        if np.isfinite(result.centroid_sigma_m):
            t.add_row("precision", f"{result.centroid_sigma_m:.2f} m RMS predicted at B's centroid (from the partners' "
                                   "residuals and layout; covariance in --json)")  # fmt: skip
    t.add_row("ms", ", ".join(f"{k} {v:.2f}" for k, v in result.timings_ms.items()))
    console.print(t)


def match_evidence(result, false_alarm_rate: float, pieces_to_place: int) -> str:
    """What an accepted match's evidence is worth, as rich text: its log likelihood ratio against the chance
    threshold, and whether it alone is as strong as the ``pieces_to_place`` independent matches a robot needs
    in the running system (``MatchResult.is_decisive``) or is one piece of evidence that a far-apart pair
    passes by chance about once in ``1 / false_alarm_rate`` (the match says so rather than claim more)."""
    head = f"log likelihood ratio {result.llr:.1f} nats, chance threshold {result.llr_threshold:.1f}"
    if result.is_decisive(pieces_to_place):
        return f"{head}: as far beyond chance as {pieces_to_place} independent matches together"
    rate = f"{1.0 / false_alarm_rate:.0f}"
    chance = f"[yellow]one piece of evidence[/] (about 1 in {rate} far-apart pairs passes this bar"
    if pieces_to_place <= 1:
        return f"{head}: {chance} by chance; backend.min_closures_to_anchor 1 places a robot on one)"
    return (
        f"{head}: {chance} by chance); a match on other objects would confirm it: the running system waits for "
        f"{pieces_to_place} before it places a robot, or one with a ratio of "
        f"{pieces_to_place * result.llr_threshold:.1f}"
    )


def warn_unused(option: str, value: object, why: str) -> None:
    """One yellow line on stderr: ``option value`` was given but is not used (``why``); the command goes on."""
    err_console.print(f"[yellow]warning:[/] {option} {lit(value)} is not used: {why}", soft_wrap=True)


def metres(value: float) -> str:
    """A distance in metres for an 80-column table: 2 decimals below 100 m, whole metres above, '-' for NaN."""
    if value != value:
        return "-"
    return f"{value:.2f}" if abs(value) < 100 else f"{value:.0f}"


def summary_table(summary):
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
            f"[yellow]{r.odometry_failures}[/]" if r.odometry_failures else "0", fused, metres(r.path_length_m),
            metres(r.ate_odometry_m), metres(r.ate_fused_m),
            f"{metres(r.ate_odometry_aligned_m)}/{metres(r.ate_fused_aligned_m)}",
        )  # fmt: skip
    t.caption = ("ATE: metres in the shared frame (odo = odometry alone, started at its true pose; per trajectory "
                 "segment after odometry failures); aligned = SE(3)-aligned per robot; fused a/b = trajectory "
                 "segments placed / segments; prov = placed provisionally, no independent graph match confirms it yet "
                 "(see its warning)")
    return t


def render_summary(summary) -> None:
    """Print the run summary as rich tables."""
    from rich.table import Table

    t = summary_table(summary)
    console.print(t)
    joint = [f"{r.name} {metres(r.ate_fused_joint_m)}" for r in summary.robots if not math.isnan(r.ate_fused_joint_m)]
    if len(joint) > 1:
        console.print(f"fused ATE after one SE(3) fit of the {len(joint)} placed robots together (how well they agree, "
                      f"without the first robot's own drift), metres: {lit(', '.join(joint))}; "
                      f"{metres(summary.ate_joint_m)} over all")  # fmt: skip
    free = [f"{r.name} {r.path_from_closures_m:.0f}" for r in summary.robots if r.path_from_closures_m is not None]
    if free:
        console.print("the longest stretch of each placed path on its own odometry (metres of path from the nearest "
                      "keyframe a closure ties to the shared frame; drift grows there): " + lit(", ".join(free)))
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
    levels = [f"{r.name} {100 * r.levelled_share:.0f} %" for r in summary.robots if r.levelled_share is not None]
    if levels:
        console.print("tilt held to the ground in view, share of tracking references turned towards level: "
                      + lit(", ".join(levels)))  # fmt: skip
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
    rest = summary.matches_tried - summary.closures_accepted - summary.closures_rejected
    console.print(
        f"graph matches tried {summary.matches_tried} (between robots and loop closures): accepted "
        f"[green]{summary.closures_accepted}[/], rejected by the verification [yellow]{summary.closures_rejected}[/], "
        f"{rest} with no alignment found or only closures already held"
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


def placed_text(placed: list[str], provisional: list[str]) -> str:
    """``car2, car2#1 (provisional)``: the placed agents, provisional ones marked; "not placed" for none."""
    return ", ".join(a + (" (provisional)" if a in provisional else "") for a in placed) or "not placed"


def eval_table(result):
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
        table.add_row(lit(r.name), f"{r.evaluated_poses}/{r.fused_poses}", metres(r.ate_fused_m),
                      metres(r.ate_fused_aligned_m), metres(r.ate_fused_joint_m), metres(r.max_error_m),
                      lit(r.note))  # fmt: skip
    table.caption = f"ground truth from the {result.gt_source}; aligned = SE(3)-aligned per robot{joint_text(result)}"
    return table


def joint_text(result) -> str:
    """The eval caption's words on the joint column, by how many robots its one fit holds (placed robots with
    ground truth in the shared frame; others may be placed without it): none for none (it said "all 0 placed
    robots together (- m ...)"), and for one that its fit is its own alignment."""
    if result.joint_robots == 1:
        return ("; joint = aligned (one placed robot has ground truth in the shared frame: one SE(3) fit of it alone "
                "is its own alignment)")  # fmt: skip
    if result.joint_robots < 2:
        return ""
    return (f"; joint = one SE(3) fit of the {result.joint_robots} placed robots with ground truth in the shared "
            "frame together "
            f"({metres(result.ate_joint_m)} m over all their poses): how well they agree, without the first "
            "robot's own drift")  # fmt: skip


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

