"""What every stored sequence shares: frames by index (negative from the end) or by range (``seq[a:b]``, a
``SequenceView``), their times and ground truth."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from shgm_slam.data.view import SequenceView, sliced
from shgm_slam.types import Frame


class IndexedFrames:
    """The ``types.Sequence`` accessors over ``_times`` ((N,) seconds, read-only) and ``_gt`` ((N, 4, 4)
    read-only ``T_world_cam`` or None) that a subclass sets, and ``odometry_poses`` over ``_odom`` (the robot's own
    odometry given with the frames, or None); the subclass gives ``name``, ``_frame`` (one frame by its index in
    0..N-1), ``has_depth`` and ``has_labels``."""

    name: str
    _times: np.ndarray
    _gt: np.ndarray | None
    _odom: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self._times.shape[0])

    def __iter__(self) -> Iterator[Frame]:
        return (self._frame(i) for i in range(len(self)))

    def __getitem__(self, index: int | slice) -> Frame | SequenceView:
        """Frame ``index`` (negative indices count from the end), or the frames of a slice as a ``SequenceView``
        re-indexed from 0 (``seq[100:200]``: frames 100..199; step 1 only).

        Raises:
            IndexError: an index outside the frames. DataError: a slice with another step or no frame.
        """
        if isinstance(index, slice):
            return sliced(self, index)  # type: ignore[arg-type]
        return self._frame(self._index(index))

    def _frame(self, i: int) -> Frame:
        """Frame ``i`` in 0..N-1 (the subclass reads or builds it)."""
        raise NotImplementedError

    @property
    def timestamps_s(self) -> np.ndarray:
        """(N,) seconds, read-only."""
        return self._times

    @property
    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ground-truth ``T_world_cam`` (read-only), or None."""
        return self._gt

    @property
    def odometry_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ``T_odom_cam`` of the robot's own odometry, given with the frames (read-only), or None
        (``odometry.sources.given_odometry``)."""
        return self._odom

    def _index(self, index: int) -> int:
        """``index`` in 0..N-1 (negative indices count from the end); IndexError outside."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {self.name} with {n} frames")
        return index % n
