"""Frame ranges of a sequence: ``SequenceView`` (``path:start-end`` specs, ``sequence[start:end]`` in Python)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from shgm_slam.errors import DataError
from shgm_slam.types import Frame, Intrinsics, Sequence


class SequenceView:
    """Frames ``start`` (inclusive) to ``end`` (exclusive) of another sequence, re-indexed from 0."""

    def __init__(self, base: Sequence, start: int, end: int) -> None:
        n = len(base)
        if not 0 <= start < end <= n:
            raise DataError(
                f"frame range {start}-{end} does not fit {base.name} with {n} frames; "
                f"use 0 <= start < end <= {n}"
            )
        self.base, self.start, self.end = base, start, end
        self.name = f"{base.name}:{start}-{end}"
        self.intrinsics: Intrinsics = base.intrinsics

    def __len__(self) -> int:
        return self.end - self.start

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))

    def __getitem__(self, index: int | slice) -> Frame | SequenceView:
        """Frame ``index`` re-indexed from 0 (negative indices count from the end), or a range of this view as a
        view of the same base (``view[a:b]``, ``sliced``)."""
        if isinstance(index, slice):
            start, end = slice_range(index, len(self), self.name)
            return SequenceView(self.base, self.start + start, self.start + end)
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {self.name} with {n} frames")
        i = index % n
        frame = self.base[self.start + i]
        frame.index = i
        return frame

    @property
    def timestamps_s(self) -> np.ndarray:
        return self.base.timestamps_s[self.start : self.end]

    @property
    def gt_poses(self) -> np.ndarray | None:
        gt = self.base.gt_poses
        return None if gt is None else gt[self.start : self.end]

    @property
    def odometry_poses(self) -> np.ndarray | None:
        """The base sequence's own odometry poses in this range (``IndexedFrames.odometry_poses``), or None."""
        odom = getattr(self.base, "odometry_poses", None)
        return None if odom is None else odom[self.start : self.end]

    @property
    def has_depth(self) -> bool:
        return self.base.has_depth

    @property
    def has_labels(self) -> bool:
        return self.base.has_labels


def slice_range(key: slice, n: int, name: str) -> tuple[int, int]:
    """(start, end) of the frames ``key`` takes from a sequence of ``n`` frames (Python's slice rules: negative
    bounds count from the end, bounds past the end are clipped).

    Raises:
        DataError: a step other than 1 (the frames of a run are consecutive in time; a robot would see its
            frames skipped as motion too fast for its odometry), or no frame taken.
    """
    start, end, step = key.indices(n)
    if step != 1:
        raise DataError(
            f"{name}[{_shown(key)}]: only consecutive frames can be taken (step 1); "
            "to run at a lower frame rate, write the frames you want into a folder of their own"
        )
    if start >= end:
        raise DataError(f"{name}[{_shown(key)}] takes no frame of its {n}; need start < end")
    return start, end


def _shown(key: slice) -> str:
    """``key`` as written in Python (``a:b``, ``:b``, ``a::2``)."""
    parts = ["" if v is None else str(v) for v in (key.start, key.stop, key.step)]
    return ":".join(parts if key.step is not None else parts[:2])


def sliced(sequence: Sequence, key: slice) -> SequenceView:
    """The frames ``key`` takes from ``sequence`` as a view re-indexed from 0 (``sequence[a:b]``)."""
    start, end = slice_range(key, len(sequence), sequence.name)
    return SequenceView(sequence, start, end)
