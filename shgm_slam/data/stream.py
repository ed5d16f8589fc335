"""A sequence whose frames arrive one by one (a camera driver, a robot's live feed): ``live.LiveRun`` appends
each frame as it comes, and the pipeline reads it like any other sequence.

Every frame is checked when it is appended (image, depth and label shapes and types as ``ArraySequence`` checks
them, labels that are train ids, a time later than the last frame's, a rigid ground-truth pose), so a bad frame is
refused at the call that brought it, naming the robot and the frame. The arrays are copied: the caller may reuse
its buffers. The first frame fixes what every later one carries (depth, labels, ground truth, the robot's own
odometry). A frame the pipeline has processed can be ``release``d: its arrays are dropped (a live run holds only
the frames still to be processed) and reading it again is an error.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.data.kitti import check_pose_units, check_times
from shgm_slam.data.memory import ArraySequence, checked_depth_origin, checked_intrinsics, checked_poses
from shgm_slam.errors import DataError
from shgm_slam.labels import IGNORE_ID, NUM_CLASSES
from shgm_slam.types import DepthOrigin, Frame, Intrinsics

UNITS_FROM_FRAMES = (3, 10)
"""Frames 3 to 10 are refused unless the median interval so far is a camera's (``kitti.check_times``: 1 ms to
30 s, as for a recorded sequence): times in milliseconds or nanoseconds are refused before they mislead the
odometry's checks of speed, and the median lets one pause of the camera pass. The robot's own odometry
(``T_odom_cam``) and the ground truth (``T_world_cam``) are checked for metres over the same frames
(``kitti.check_pose_units``: ground truth in millimetres made the run's ATE kilometres)."""

MAX_FOREIGN_LABEL_SHARE = 0.01
"""A frame whose label_ids hold more than this share of pixels that are neither a Cityscapes train id (0-18) nor
ignore (255) is refused: it is in another label space (Cityscapes' full ids 0-33, another dataset's classes), whose
values in 0-18 are the wrong classes too (``data.validate`` probes a recorded sequence's first frames the same
way; a live robot's later frames were taken unchecked)."""


class FrameStream(ArraySequence):
    """A ``types.Sequence`` that grows by ``append`` (module docstring).

    Args:
        intrinsics: the camera's pinhole intrinsics; ``width`` x ``height`` is every image's size.
        depth_origin: whether the depth it will be given is measured (KISS-ICP) or predicted by a network.
        name: the sequence's name in logs and messages (e.g. the robot's).

    Raises:
        DataError: intrinsics that are not an ``Intrinsics`` with positive focal lengths and size; a
            ``depth_origin`` that is no ``DepthOrigin``.
    """

    def __init__(
        self, intrinsics: Intrinsics, *, depth_origin: DepthOrigin = DepthOrigin.MEASURED, name: str = "live"
    ) -> None:
        self.name = name
        self.intrinsics = checked_intrinsics(intrinsics, name)
        self.depth_origin = checked_depth_origin(depth_origin, name)
        self._n = 0
        self._time_rows = np.zeros(64, dtype=np.float64)
        self._gt_rows: np.ndarray | None = None
        self._odom_rows: np.ndarray | None = None
        self._images: list[np.ndarray | None] = []
        self._depth: list[np.ndarray | None] | None = None
        self._labels: list[np.ndarray | None] | None = None
        self._released = 0  # frames before this one have been released

    def __len__(self) -> int:
        return self._n

    @property
    def _times(self) -> np.ndarray:  # type: ignore[override]
        times = self._time_rows[: self._n]
        times.flags.writeable = False
        return times

    @property
    def _gt(self) -> np.ndarray | None:  # type: ignore[override]
        return self._rows(self._gt_rows)

    @property
    def _odom(self) -> np.ndarray | None:  # type: ignore[override]
        return self._rows(self._odom_rows)

    def _rows(self, rows: np.ndarray | None) -> np.ndarray | None:
        """The appended frames' rows of ``rows`` (read-only), or None."""
        if rows is None:
            return None
        poses = rows[: self._n]
        poses.flags.writeable = False
        return poses

    def append(
        self,
        image_rgb: np.ndarray,
        timestamp_s: float,
        *,
        depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
        T_world_cam: np.ndarray | None = None,
        T_odom_cam: np.ndarray | None = None,
    ) -> int:
        """Add the next frame, checked; returns its index.

        Args:
            image_rgb: (H, W, 3) uint8 RGB or (H, W) uint8 grey.
            timestamp_s: seconds, later than the last frame's.
            depth_m: (H, W) float metres (0 or non-finite: invalid), or None.
            label_ids: (H, W) integer Cityscapes train ids (0-18, 255 = ignore; at most
                ``MAX_FOREIGN_LABEL_SHARE`` of the pixels other values), or None.
            T_world_cam: (4, 4) ground-truth camera -> world pose (KITTI camera axes), or None.
            T_odom_cam: (4, 4) the robot's own odometry's camera -> odometry-frame pose, or None.

        Raises:
            DataError: a frame that differs from the first in what it carries, a time that is not finite or not
                later than the last frame's, or an image, map or pose of the wrong shape, type or values.
        """
        i = self._n
        where = f"sequence {self.name!r} frame {i}"
        for held in (self._images, self._depth, self._labels):  # what an append stopped midway (a Ctrl-C) left
            if held is not None:
                del held[i:]
        if i == 0:
            self._depth = None if depth_m is None else []
            self._labels = None if label_ids is None else []
            self._gt_rows = None if T_world_cam is None else np.zeros((64, 4, 4))
            self._odom_rows = None if T_odom_cam is None else np.zeros((64, 4, 4))
        for what, given, held in (("depth_m", depth_m, self._depth), ("label_ids", label_ids, self._labels),
                                  ("T_world_cam", T_world_cam, self._gt_rows),
                                  ("T_odom_cam", T_odom_cam, self._odom_rows)):  # fmt: skip
            if (given is None) != (held is None):
                first = "had one" if held is not None else "had none"
                raise DataError(f"{where}: {'no ' if given is None else ''}{what} given, but the first frame {first}; "
                                f"give {what} with every frame or with none")  # fmt: skip
        try:
            t = float(timestamp_s)
        except (TypeError, ValueError):
            t = float("nan")
        if not np.isfinite(t) or (i > 0 and t <= self._time_rows[i - 1]):
            last = f" (the last frame's is {self._time_rows[i - 1]:.6f} s)" if i > 0 else ""
            raise DataError(f"{where}: timestamp {timestamp_s!r} s is not a finite time later than the last "
                            f"frame's{last}; give each frame's capture time in seconds, increasing")  # fmt: skip
        pose = None if T_world_cam is None else _checked_pose(T_world_cam, "T_world_cam", "world", where)
        odom = None if T_odom_cam is None else _checked_pose(T_odom_cam, "T_odom_cam", "odometry frame", where)
        if UNITS_FROM_FRAMES[0] <= i <= UNITS_FROM_FRAMES[1]:  # seconds (as a recorded sequence's times) and metres
            self._check_units(i, t, pose, odom, where)
        # the arrays as the pipeline will read them (checked, copied: the caller may reuse its buffers)
        given = _as_array(image_rgb, "the image", where)
        self._images.append(given)
        if depth_m is not None:
            self._depth.append(_as_array(depth_m, "depth_m", where))  # type: ignore[union-attr]
        if label_ids is not None:
            self._labels.append(_as_array(label_ids, "label_ids", where))  # type: ignore[union-attr]
        try:
            image = self._image(i, where)
            depth = None if depth_m is None else self._depth_map(i, where)
            labels = None if label_ids is None else _checked_label_space(self._label_map(i, where), where)
        except DataError:
            for held in (self._images, self._depth, self._labels):
                if held is not None and len(held) > i:
                    held.pop()
            raise
        # (the caller's array, or the view of its buffer a memmap or an ``__array__`` object gave, is copied)
        self._images[i] = image if image is not given else image.copy()
        if depth is not None:
            self._depth[i] = depth  # type: ignore[index]
        if labels is not None:
            self._labels[i] = labels  # type: ignore[index]
        if i == self._time_rows.shape[0]:
            self._time_rows = np.concatenate([self._time_rows, np.zeros_like(self._time_rows)])
            if self._gt_rows is not None:
                self._gt_rows = np.concatenate([self._gt_rows, np.zeros_like(self._gt_rows)])
            if self._odom_rows is not None:
                self._odom_rows = np.concatenate([self._odom_rows, np.zeros_like(self._odom_rows)])
        self._time_rows[i] = t
        if pose is not None:
            self._gt_rows[i] = pose  # type: ignore[index]
        if odom is not None:
            self._odom_rows[i] = odom  # type: ignore[index]
        self._n = i + 1
        return i

    def _check_units(
        self, i: int, t: float, pose: np.ndarray | None, odom: np.ndarray | None, where: str
    ) -> None:
        """Frame ``i`` (time ``t``, seconds; poses or None) refused unless the times so far are in seconds and
        the poses in metres (``UNITS_FROM_FRAMES``). The median over the frames so far passes a single wrong
        value, so a refusal means the earlier frames were in those units too: the message says to start anew."""
        try:
            times = check_times(np.append(self._time_rows[:i], t), where)
            for what, rows, T in (("T_odom_cam", self._odom_rows, odom), ("T_world_cam", self._gt_rows, pose)):
                if T is not None:
                    check_pose_units(np.concatenate([rows[:i], T[None]]), times, where, what)  # type: ignore[index]
        except DataError as exc:
            raise DataError(f"{exc}; frames 0 to {i - 1} were taken in those units and cannot be taken back: start "
                            "this camera anew (a new LiveRun or LiveRobot) with every frame in seconds and "
                            "metres") from None  # fmt: skip

    def release(self, index: int) -> None:
        """Drop the arrays of frames up to ``index`` (included): they have been processed."""
        for i in range(self._released, min(index + 1, self._n)):
            self._images[i] = None
            for held in (self._depth, self._labels):
                if held is not None:
                    held[i] = None
        self._released = max(self._released, min(index + 1, self._n))

    def _frame(self, i: int) -> Frame:
        """Frame ``i`` of those appended so far (``seq[i]``: IndexError outside them).

        Raises:
            DataError: a frame already released.
        """
        if self._images[i] is None:
            raise DataError(f"sequence {self.name!r} frame {i} was processed and released; its arrays are gone")
        return Frame(
            index=i,
            timestamp_s=float(self._time_rows[i]),
            intrinsics=self.intrinsics,
            image_rgb=self._images[i],
            depth_m=None if self._depth is None else self._depth[i],
            label_ids=None if self._labels is None else self._labels[i],
            T_world_cam=None if self._gt_rows is None else self._gt_rows[i].copy(),
            source_index=i,
            T_odom_cam=None if self._odom_rows is None else self._odom_rows[i].copy(),
        )


def _as_array(given: object, what: str, where: str) -> np.ndarray:
    """``given`` (an array, an object with ``__array__``, nested lists) as a numpy array, a view where it can be;
    DataError at ``where`` when it cannot be one (ragged lists)."""
    try:
        return np.asarray(given)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{where}: {what} ({type(given).__name__}) cannot be read as an array ({exc}); give a numpy "
                        "array of the image's height x width") from None  # fmt: skip


def _checked_label_space(labels: np.ndarray, where: str) -> np.ndarray:
    """(H, W) uint8 ``labels``, refused (DataError at ``where``) when more than ``MAX_FOREIGN_LABEL_SHARE`` of its
    pixels are neither a train id nor ignore."""
    foreign = (labels >= NUM_CLASSES) & (labels != IGNORE_ID)
    share = float(foreign.mean()) if labels.size else 0.0
    if share > MAX_FOREIGN_LABEL_SHARE:
        values = np.unique(labels[foreign])
        shown = ", ".join(map(str, values[:8])) + (", ..." if values.size > 8 else "")
        raise DataError(f"{where}: {100 * share:.0f} % of label_ids are {shown}, no Cityscapes train id (0-18, "
                        "255 = ignore); give train ids (Cityscapes label ids 0-33? map them id -> trainId, "
                        "cityscapesscripts' labels.py; another dataset's classes: map them to these)")  # fmt: skip
    return labels


def _checked_pose(T: np.ndarray, what: str, to: str, where: str) -> np.ndarray:
    """One frame's (4, 4) camera -> ``to`` pose ``T`` as float64, refused (DataError at ``where``) unless it is a
    finite rigid transform."""
    given = np.asarray(T)
    if given.shape != (4, 4) or not np.issubdtype(given.dtype, np.number):
        raise DataError(f"{where}: {what} is {given.dtype} {given.shape}; give a (4, 4) camera -> {to} pose")
    try:
        return checked_poses(given[None], 1, where, what)[0]
    except DataError:
        raise DataError(f"{where}: {what} is not finite or not a rigid transform (a rotation and a translation over "
                        "the row 0 0 0 1)") from None  # fmt: skip
