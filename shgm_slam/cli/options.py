"""Option types and parsers shared by the commands: output paths, bounded floats, frame and seed lists."""

from __future__ import annotations

import math
import re
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

T = TypeVar("T")


def nonempty_path(text: str) -> Path:
    """An output path from the command line; an empty one is refused (it would mean the current folder)."""
    if not str(text).strip():
        raise typer.BadParameter("is empty: give a folder or file path (for the current folder, '.')")
    return Path(text)


def unusable_path(path: Path, exc: OSError) -> typer.BadParameter:
    """The refusal of an output ``path`` the OS cannot even look at (``exc``: a name too long, a parent folder
    without permission), which escaped as an OSError traceback from ``out_folder``, ``out_file`` and
    ``writable_place``."""
    return typer.BadParameter(f"{path} cannot be looked at ({exc.strerror or exc}); give another path")


def writable_place(folder: Path) -> None:
    """Refuse (``typer.BadParameter``) a ``folder`` that cannot be created or written in: its nearest existing
    folder is probed with a temporary folder, removed at once (nothing is left behind, nothing is created
    where the command is refused). Benchmarks write their results at the end: a folder under a file or in
    /proc stopped them there with a traceback, after all their work."""
    try:
        base = next((p for p in (folder, *folder.parents) if p.exists()), Path("."))
        is_folder = base.is_dir()
    except OSError as exc:
        raise unusable_path(folder, exc) from None
    if not is_folder:
        raise typer.BadParameter(f"{base} is a file, not a folder; give a path that is not under a file")
    try:
        tempfile.TemporaryDirectory(dir=base, prefix=".shgm-probe-").cleanup()
    except OSError as exc:
        raise typer.BadParameter(f"cannot write in {base} ({exc.strerror or exc}); give a writable folder") from None


def out_folder(text: str) -> Path:
    """An output folder from the command line: not empty (``nonempty_path``), not an existing file, and one
    that can be created and written in (``writable_place``)."""
    path = nonempty_path(text)
    try:
        is_file = path.exists() and not path.is_dir()
    except OSError as exc:
        raise unusable_path(path, exc) from None
    if is_file:
        raise typer.BadParameter(f"{text} is a file; give a folder (it is created if missing)")
    writable_place(path)
    return path


def out_file(text: str) -> Path:
    """An output file from the command line: not empty (``nonempty_path``), not an existing folder, in a folder
    that can be created and written in (``writable_place``); an existing file is written over."""
    path = nonempty_path(text)
    try:
        is_folder = path.is_dir()
    except OSError as exc:
        raise unusable_path(path, exc) from None
    if is_folder:
        raise typer.BadParameter(f"{text} is a folder; give the file to write, e.g. {path / 'results.json'}")
    writable_place(path.parent)
    return path


def results_folder(help_text: str) -> Any:
    """``typer.Option`` for a benchmark's ``--out``/``-o`` results folder (``out_folder``: not empty, not a file)."""
    return typer.Option("--out", "-o", parser=out_folder, help=help_text)


def float_in(low: float, high: float) -> Callable[[str], float]:
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


def bounded(low: float, high: float, *names: str, **kwargs: Any) -> Any:
    """``typer.Option`` for a float in [low, high] (``float_in``), its range shown in ``--help``."""
    return typer.Option(*names, parser=float_in(low, high), metavar=f"<float {low:g}..{high:g}>", **kwargs)


@dataclass(frozen=True)
class NumberRange:
    """A range of finite numbers given on the command line (``number_range``): ``low`` <= ``high``."""

    low: float
    high: float

    def as_tuple(self) -> tuple[float, float]:
        return (self.low, self.high)


def number_range(text: str) -> NumberRange:
    """A range of finite numbers from the command line: 'A-B' with A <= B, or one number A (the range A-A)."""
    parts = re.split(r"(?<![eE])-", str(text).strip())  # a minus after an exponent's e is the exponent's
    try:
        if len(parts) not in (1, 2):
            raise ValueError(text)
        values = (float(parts[0]), float(parts[-1]))
    except ValueError:
        raise typer.BadParameter(f"{text!r}: write a range of numbers A-B (e.g. 0.5-2) or one number") from None
    if not all(math.isfinite(v) for v in values):
        raise typer.BadParameter(f"{text!r}: the numbers must be finite")
    if values[0] > values[1]:
        raise typer.BadParameter(f"{text!r}: the range's start is above its end; write {values[1]:g}-{values[0]:g}")
    return NumberRange(*values)


MAX_FRAMES = 1_000_000
"""Upper bound of every frame-count option (KITTI's longest sequence has 4,661 frames)."""


JobsOption = Annotated[
    int | None,
    typer.Option("--jobs", "-j", min=1, max=256, show_default="one per robot, at most one per core",
                 help="worker processes for the robots' front ends (the same results, sooner); 1: everything in "
                 "this one process"),
]


def int_list(text: str, option: str) -> tuple[int, ...]:
    """Comma-separated distinct integers of ``option`` (e.g. ``--fleets 1,2,4``; ``distinct``)."""
    from shgm_slam.errors import ConfigError

    try:
        values = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"{option} {text!r}: write comma-separated whole numbers, e.g. 1,2,4,8") from None
    if not values:
        raise ConfigError(f"{option} {text!r} names no value")
    return distinct(option, values)


def _value_text(value: Any) -> str:
    """A value as the command line writes it: an enum member by its value."""
    return str(getattr(value, "value", value))


def distinct(option: str, values: Iterable[T], label: Callable[[T], str] = _value_text) -> tuple[T, ...]:
    """``values`` of a repeatable or comma-separated ``option`` as a tuple, each given once (``label``: how one
    is named in the message).

    Raises:
        ConfigError: a value given twice: its runs would be run and counted twice in the results.
    """
    from shgm_slam.errors import ConfigError

    values = tuple(values)
    twice = [v for v, n in Counter(values).items() if n > 1]
    if twice:
        raise ConfigError(f"{option} {label(twice[0])} is given more than once (its runs would count twice); "
                          "give each once")  # fmt: skip
    return values


def world_seeds(seeds: str) -> tuple[int, ...]:
    """``--seeds`` of the held-out style benchmarks: 'report', 'tuning', an inclusive range A-B or A,B,C."""
    from shgm_slam.bench import heldout
    from shgm_slam.bench.seeds import parse_seeds

    return parse_seeds(seeds, {"report": heldout.REPORT_SEEDS, "tuning": heldout.TUNING_SEEDS})

