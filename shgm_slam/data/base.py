"""Opening sequences: ``path[:start-end]`` specs, layout detection, the reader registry, frame-range views.

A spec is a sequence folder optionally followed by a frame range, ``start`` inclusive and ``end``
exclusive: ``data/08:0-1500`` (frames 0..1499), ``data/08:100-`` (frame 100 to the end),
``data/08:-500`` (the first 500). A range gives a view whose frames are re-indexed from 0 while
``Frame.source_index`` keeps the file index; ``timestamps_s``/``gt_poses`` are sliced alike.
"""

from __future__ import annotations

import os
import re
from enum import Enum
from pathlib import Path

from shgm_slam.data.kitti import KittiSequence, sequence_folder_problem
from shgm_slam.data.sequence import DEPTH_DIR, LABEL_DIR, ShgmSequence
from shgm_slam.data.view import SequenceView
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.types import Sequence

_RANGE = re.compile(r"^(\d*)-(\d*)$")


class SequenceLayout(str, Enum):
    KITTI = "kitti"
    """KITTI odometry: image_2/ or image_0/, calib.txt, times.txt, optional poses (extra rows tolerated)."""
    SHGM = "shgm"
    """Ours: KITTI plus depth/ and/or semantic/; all counts must agree exactly."""


SEQUENCE_READERS: dict[SequenceLayout, type[KittiSequence]] = {
    SequenceLayout.KITTI: KittiSequence,
    SequenceLayout.SHGM: ShgmSequence,
}
"""Reader class per layout; each takes the sequence folder and satisfies ``types.Sequence``."""


def parse_sequence_spec(spec: str | Path) -> tuple[Path, int, int | None]:
    """Split ``path[:start-end]`` into (folder, start, end or None = to the end).

    A suffix after the last ':' that is not ``start-end`` is a DataError unless the whole spec is an
    existing path (folders whose names contain ':').
    """
    if isinstance(spec, Path):
        return spec, 0, None
    head, sep, tail = spec.rpartition(":")
    try:
        whole = bool(sep) and Path(spec).exists()
    except OSError:  # (a name too long: an OSError traceback before; ``open_sequence`` says what is wrong)
        whole = False
    if not sep or whole:
        return Path(spec), 0, None
    if not head:
        raise DataError(f"sequence spec '{spec}' has no folder before ':'; use path:start-end")
    m = _RANGE.match(tail.strip())
    if m is None:
        raise DataError(
            f"bad frame range '{tail}' in sequence spec '{spec}'; use path:start-end, "
            "e.g. data/08:0-1500 or data/08:100-"
        )
    start = int(m.group(1)) if m.group(1) else 0
    end = int(m.group(2)) if m.group(2) else None
    if end is not None and start >= end:
        raise DataError(f"empty frame range in sequence spec '{spec}': need start < end (end is exclusive)")
    return Path(head), start, end


def detect_layout(root: Path) -> SequenceLayout:
    """SHGM when ``root`` has ``depth/`` or ``semantic/``, else KITTI."""
    ours = (root / DEPTH_DIR).is_dir() or (root / LABEL_DIR).is_dir()
    return SequenceLayout.SHGM if ours else SequenceLayout.KITTI


def sequence_root(sequence: object) -> Path | None:
    """The folder a sequence reads its files from (through any ``SequenceView``), or None (frames in memory)."""
    while getattr(sequence, "root", None) is None and getattr(sequence, "base", None) is not None:
        sequence = sequence.base  # type: ignore[attr-defined]
    root = getattr(sequence, "root", None)
    return None if root is None else Path(root)


def layout_of(layout: SequenceLayout | str | None) -> SequenceLayout | None:
    """``layout`` as a ``SequenceLayout`` (its value in any case, e.g. "KITTI", is taken), or None (detect it).

    Raises:
        ConfigError: none of the layouts.
    """
    if layout is None or isinstance(layout, SequenceLayout):
        return layout
    try:
        return SequenceLayout(str(layout).strip().lower())
    except ValueError:
        choices = ", ".join(repr(m.value) for m in SequenceLayout)
        raise ConfigError(f"sequence layout {layout!r} is none of {choices}; or leave it out to detect it") from None


def open_sequence(spec: str | Path, layout: SequenceLayout | None = None) -> Sequence:
    """Open ``path[:start-end]`` (see the module doc) with the detected (or given) layout's reader.

    Returns the whole sequence, or a ``SequenceView`` of it when a range is given.

    Raises:
        DataError: a spec that is no path (Python's AttributeError before), a missing folder or a file given for
            one (``kitti.sequence_folder_problem``), a bad range or sequence. ConfigError: a ``layout`` that is
            none of ``SequenceLayout`` (a KeyError before).
    """
    if not isinstance(spec, str | os.PathLike):
        raise DataError(f"sequence spec {spec!r} is no path; give 'path[:start-end]' (a str) or a Path")
    root, start, end = parse_sequence_spec(spec if isinstance(spec, str) else Path(spec))
    if (problem := sequence_folder_problem(root)) is not None:
        raise DataError(f"{problem} (spec '{spec}')")
    sequence: Sequence = SEQUENCE_READERS[layout_of(layout) or detect_layout(root)](root)
    if start == 0 and end is None:
        return sequence
    return SequenceView(sequence, start, len(sequence) if end is None else end)
