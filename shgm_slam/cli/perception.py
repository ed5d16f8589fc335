"""Networks: ``check-model`` (a model and its card) and ``perceive`` (run the networks once over a sequence)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from shgm_slam.cli.app import app, handle_errors
from shgm_slam.cli.options import nonempty_path
from shgm_slam.cli.render import console, lit
from shgm_slam.cli.signals import stop_signals_as_interrupt
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE

if TYPE_CHECKING:  # the models load only when a command runs
    from shgm_slam.perception.perceive import BatchUsed

CONSTANT_OUTPUT_SPAN = 1e-6
"""Largest spread of ``check-model``'s valid output values, relative to their largest (at least 1), that is still
one value: a (1, 1) depth output resized to the image spans ~2e-7 of it in float32 and passed as a depth map."""


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
    span = report.value_max - report.value_min  # resampling a 1x1 output leaves float noise, not an image
    if span <= CONSTANT_OUTPUT_SPAN * max(abs(report.value_max), 1.0):  # `run` refuses such a model: so does its check
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
    out: Annotated[Path, typer.Option("--out", "-o", parser=nonempty_path,
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
    with stop_signals_as_interrupt(), Progress(  # SIGTERM/SIGHUP stop it like Ctrl-C: resumable
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
                  f"{result.frames} in {result.wall_s:.1f} s ({providers}" + (f"; ms/frame {speed}" if speed else "")
                  + f"; {lit(batch_text(result.batch_size, result.batch_used))})")  # fmt: skip
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


def batch_text(asked: int, used: dict[str, BatchUsed]) -> str:
    """``batch 8`` when every model was fed the batch asked for, else each model's with why (``used``: model ->
    what it was fed): ``batch depth 8, segmentation 1 (asked 8; segmentation: it failed on ...)``."""
    if all(b.size == asked for b in used.values()):
        return f"batch {asked}"
    sizes = ", ".join(f"{k} {b.size}" for k, b in used.items())
    whys = "; ".join(f"{k}: {b.why}" for k, b in used.items() if b.why)
    return f"batch {sizes} (asked {asked}; {whys})"
