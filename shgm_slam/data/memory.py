"""A sequence held in memory: your own frames (a camera driver, a ROS bag you decoded, a dataset with
another layout) run through the same pipeline as a sequence folder.

``ArraySequence`` takes the images and, optionally, depth, labels, ground-truth poses and the robot's own odometry
(``T_odom_cam``, run instead of the system's odometry) as arrays of N frames, or as any indexable of N arrays (a
list, or an object with ``__len__`` and ``__getitem__`` that loads frame ``i`` when asked: nothing is read before
the pipeline asks for it). It checks what it can at once (counts, timestamps, intrinsics, poses) and each frame when
it is read (shape, dtype, image size), with errors that name the frame. Depth that is not finite or not positive
becomes 0 (invalid), as in depth files. ``depth_origin`` says whether a sensor measured the depth (KISS-ICP
odometry, never rescaled) or a network predicted it (as for a ``perceive`` folder: visual odometry, scaled to the
camera height).
"""

from __future__ import annotations

import numbers
from typing import Protocol

import numpy as np

from shgm_slam.data.indexed import IndexedFrames
from shgm_slam.data.kitti import check_pose_units, check_times, pinhole_problem
from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import project_to_so3
from shgm_slam.types import DepthOrigin, Frame, Intrinsics

POSE_TOLERANCE = 1e-2
"""Largest max |RᵀR - I| of a ground-truth pose's rotation (and |last row - [0, 0, 0, 1]|)."""
POSE_REPAIR_ABOVE = 1e-6
"""Poses whose rotation is farther than this from orthonormal (within ``POSE_TOLERANCE``) are re-orthonormalized
(``project_to_so3``), as a poses file's rows are (``io.trajectories``): the pipeline's messages carry rotations
orthonormal within 1e-5 (``wire``), and a pose 1e-3 off ended the run there."""


class FrameArrays(Protocol):
    """N arrays, one per frame: a stacked (N, ...) array, a list, or a lazy loader."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> np.ndarray: ...


class ArraySequence(IndexedFrames):
    """A ``types.Sequence`` over frames held in memory (module docstring).

    Args:
        images_rgb: N images, each (H, W, 3) uint8 RGB or (H, W) uint8 grey (replicated to 3 channels).
        intrinsics: the camera's pinhole intrinsics; ``width`` x ``height`` is every image's size.
        timestamps_s: (N,) seconds, strictly increasing (frames 1 ms to 30 s apart, median).
        depth_m: N (H, W) float depth maps in metres (0 or non-finite: invalid), or None.
        label_ids: N (H, W) integer maps of Cityscapes train ids (0-18, 255 = ignore), or None.
        T_world_cam: (N, 4, 4) ground-truth poses (camera -> world, KITTI camera axes), or None.
        T_odom_cam: (N, 4, 4) the robot's own odometry (camera -> its odometry frame), run as the odometry
            (``OdometryKind.GIVEN``, which ``auto`` chooses when it is given), or None.
        depth_origin: whether ``depth_m`` was measured or predicted by a network.
        name: the sequence's name in logs and messages.

    Raises:
        DataError: counts that differ, bad timestamps, intrinsics or poses.
    """

    def __init__(
        self,
        images_rgb: FrameArrays,
        intrinsics: Intrinsics,
        timestamps_s: np.ndarray,
        *,
        depth_m: FrameArrays | None = None,
        label_ids: FrameArrays | None = None,
        T_world_cam: np.ndarray | None = None,
        T_odom_cam: np.ndarray | None = None,
        depth_origin: DepthOrigin = DepthOrigin.MEASURED,
        name: str = "in memory",
    ) -> None:
        self.name = name
        self.intrinsics = checked_intrinsics(intrinsics, name)
        self.depth_origin = checked_depth_origin(depth_origin, name)
        for what, arrays in (("images_rgb", images_rgb), ("depth_m", depth_m), ("label_ids", label_ids)):
            check_indexable(arrays, what, name)
        n = len(images_rgb)
        if n == 0:
            raise DataError(f"sequence {name!r} has no images; give at least one frame")
        for what, arrays in (("depth_m", depth_m), ("label_ids", label_ids)):
            if arrays is not None and len(arrays) != n:
                raise DataError(f"sequence {name!r}: {len(arrays)} {what} maps for {n} images; give one per image")
        times = checked_numbers(timestamps_s, "timestamps_s", name)
        if times.shape != (n,):
            raise DataError(f"sequence {name!r}: timestamps_s has shape {times.shape} for {n} images; give (N,) "
                            "seconds")  # fmt: skip
        self._times = check_times(times, f"sequence {name!r}").copy()
        self._times.flags.writeable = False
        self._gt = None if T_world_cam is None else checked_poses(T_world_cam, n, name)
        if self._gt is not None:
            check_pose_units(self._gt, self._times, f"sequence {name!r}", "T_world_cam")
        self._odom = None if T_odom_cam is None else checked_poses(T_odom_cam, n, name, "T_odom_cam")
        if self._odom is not None:
            check_pose_units(self._odom, self._times, f"sequence {name!r}")
        self._images, self._depth, self._labels = images_rgb, depth_m, label_ids

    def __setstate__(self, state: dict) -> None:
        """Unpickled (a worker process of ``run --jobs``): the timestamps and poses read-only again."""
        self.__dict__.update(state)
        for array in (self._times, self._gt, self._odom):
            if array is not None:
                array.flags.writeable = False

    def _frame(self, i: int) -> Frame:
        """Frame ``i`` (0..N-1), checked."""
        where = f"sequence {self.name!r} frame {i}"
        return Frame(
            index=i,
            timestamp_s=float(self._times[i]),
            intrinsics=self.intrinsics,
            image_rgb=self._image(i, where),
            depth_m=None if self._depth is None else self._depth_map(i, where),
            label_ids=None if self._labels is None else self._label_map(i, where),
            T_world_cam=None if self._gt is None else self._gt[i].copy(),
            source_index=i,
            T_odom_cam=None if self._odom is None else self._odom[i].copy(),
        )

    @property
    def has_depth(self) -> bool:
        return self._depth is not None

    @property
    def has_labels(self) -> bool:
        return self._labels is not None

    def _map(self, arrays: FrameArrays, i: int, where: str, what: str) -> np.ndarray:
        """Frame ``i`` of ``arrays`` as an array on the image grid (the first two axes)."""
        array = np.asarray(arrays[i])
        size = (self.intrinsics.height, self.intrinsics.width)
        if array.ndim < 2 or array.shape[:2] != size:
            raise DataError(
                f"{where}: {what} has shape {array.shape}; expected {size[0]} x {size[1]} (the intrinsics' "
                "height x width)"
            )
        return array

    def _image(self, i: int, where: str) -> np.ndarray:
        image = self._map(self._images, i, where, "the image")
        if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
            raise DataError(f"{where}: the image is {image.dtype} {image.shape}; give (H, W, 3) uint8 RGB or (H, W) "
                            "uint8 grey")  # fmt: skip
        return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else np.ascontiguousarray(image)

    def _depth_map(self, i: int, where: str) -> np.ndarray:
        depth = self._map(self._depth, i, where, "depth_m")
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            hint = ""
            if depth.ndim == 2 and np.issubdtype(depth.dtype, np.integer):  # a depth sensor's or PNG's integers
                hint = (" (millimetres, as depth cameras give them? depth / 1000.0; KITTI-style metres x 256 PNGs? "
                        "depth / 256.0)")  # fmt: skip
            raise DataError(f"{where}: depth_m is {depth.dtype} {depth.shape}; give (H, W) float metres{hint}")
        depth = depth.astype(np.float32, copy=True)
        depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
        return depth

    def _label_map(self, i: int, where: str) -> np.ndarray:
        labels = self._map(self._labels, i, where, "label_ids")
        if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
            raise DataError(f"{where}: label_ids is {labels.dtype} {labels.shape}; give (H, W) integer train ids")
        if labels.size and (labels.min() < 0 or labels.max() > 255):
            raise DataError(f"{where}: label_ids hold values outside 0-255; give Cityscapes train ids (0-18, "
                            "255 = ignore)")  # fmt: skip
        return labels.astype(np.uint8)


def checked_intrinsics(intrinsics: Intrinsics, name: str) -> Intrinsics:
    """``intrinsics`` with plain Python numbers (float pixels, int width and height; numpy scalars and whole-number
    floats such as 640.0 are converted), refused (DataError naming sequence ``name``) unless an ``Intrinsics`` of
    numbers with positive finite focal lengths and image size that a camera can have (``kitti.pinhole_problem``, as
    for a calib file: a field of view of 1-170 degrees, pixels at most 2x stretched, the principal point inside the
    image)."""
    if not isinstance(intrinsics, Intrinsics):
        raise DataError(f"sequence {name!r}: intrinsics must be an Intrinsics, not {type(intrinsics).__name__}")
    intrinsics = plain_intrinsics(intrinsics, name)
    focal = np.array([intrinsics.fx, intrinsics.fy], dtype=np.float64)
    if not (np.isfinite(focal).all() and (focal > 0).all() and intrinsics.width > 0 and intrinsics.height > 0):
        raise DataError(f"sequence {name!r}: intrinsics {intrinsics} need positive focal lengths and image size")
    k = intrinsics
    if not np.isfinite([k.cx, k.cy]).all():
        raise DataError(f"sequence {name!r}: intrinsics {intrinsics} need a finite principal point (cx, cy)")
    problem = pinhole_problem(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    if problem is not None:
        raise DataError(f"sequence {name!r}: intrinsics {intrinsics}: {problem}")
    return intrinsics


def plain_intrinsics(intrinsics: Intrinsics, name: str) -> Intrinsics:
    """``intrinsics`` with Python floats (fx, fy, cx, cy) and ints (width, height), or a DataError naming sequence
    ``name`` for a field that is no real number or a size that is no whole number of pixels (a float width reached
    numpy's array constructors deep inside a run, after its results folder was made)."""
    values = {}
    for field in ("fx", "fy", "cx", "cy", "width", "height"):
        value = getattr(intrinsics, field)
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise DataError(f"sequence {name!r}: intrinsics {field} is {type(value).__name__} {value!r}; give a number "
                            "(pixels)")  # fmt: skip
        values[field] = float(value)
    for field in ("width", "height"):
        if not (np.isfinite(values[field]) and values[field].is_integer()):
            raise DataError(f"sequence {name!r}: intrinsics {field} {values[field]:g} is not a whole number of "
                            "pixels; give the image size in pixels")  # fmt: skip
        values[field] = int(values[field])
    return Intrinsics(**values)


def checked_depth_origin(depth_origin: DepthOrigin | str, name: str) -> DepthOrigin:
    """``depth_origin`` as a ``DepthOrigin`` (its value, e.g. "predicted", is taken too); DataError otherwise."""
    try:
        return DepthOrigin(depth_origin)
    except ValueError:
        choices = ", ".join(repr(d.value) for d in DepthOrigin)
        raise DataError(f"sequence {name!r}: depth_origin {depth_origin!r} is none of {choices}; give "
                        "DepthOrigin.MEASURED (a sensor) or DepthOrigin.PREDICTED (a network)") from None  # fmt: skip


def check_indexable(arrays: object, what: str, name: str) -> None:
    """DataError naming sequence ``name`` unless ``arrays`` is None or has ``len`` and ``[i]`` (``FrameArrays``):
    a generator or iterator can be read only once and in order, and gave Python's "has no len()"."""
    if arrays is not None and not (hasattr(arrays, "__len__") and hasattr(arrays, "__getitem__")):
        raise DataError(f"sequence {name!r}: {what} ({type(arrays).__name__}) cannot be read by frame index; "
                        "give an (N, ...) array, a list (list(...) of it), or an object with __len__ and "
                        "__getitem__ that loads frame i")  # fmt: skip


def checked_numbers(values: object, what: str, name: str) -> np.ndarray:
    """``values`` (an array, a list or any iterable, e.g. a generator) as a float64 array; DataError naming sequence
    ``name`` when they are not numbers."""
    if not hasattr(values, "__len__") and hasattr(values, "__iter__"):
        values = list(values)  # type: ignore[call-overload]
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"sequence {name!r}: {what} holds values that are not numbers (got {type(values).__name__}); "
                        "give (N,) seconds") from None  # fmt: skip


def checked_poses(T_world_cam: np.ndarray, n: int, name: str, what: str = "T_world_cam") -> np.ndarray:
    """``T_world_cam`` (or other poses, called ``what`` in messages) as a read-only (n, 4, 4) float64 copy, refused
    (DataError naming sequence ``name`` and the frame) unless every pose is finite and rigid within
    ``POSE_TOLERANCE``."""
    poses = np.asarray(T_world_cam, dtype=np.float64)
    if poses.shape != (n, 4, 4):
        raise DataError(f"sequence {name!r}: {what} has shape {poses.shape}; give ({n}, 4, 4), one per image")
    if not np.isfinite(poses).all():
        k = int(np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))[0])
        raise DataError(f"sequence {name!r}: {what} of frame {k} is not finite")
    R = poses[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    row = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = (err > POSE_TOLERANCE) | (np.linalg.det(R) <= 0.0) | (row > POSE_TOLERANCE)
    if bad.any():
        k = int(np.argmax(bad))
        raise DataError(f"sequence {name!r}: {what} of frame {k} is not a rigid transform (a rotation and a "
                        "translation over the row 0 0 0 1)")  # fmt: skip
    poses = poses.copy()
    repair = err > POSE_REPAIR_ABOVE
    if repair.any():  # (within the tolerance: rounding, a float32 pipeline) the nearest rotation
        poses[repair, :3, :3] = project_to_so3(poses[repair, :3, :3])
    poses[:, 3] = [0.0, 0.0, 0.0, 1.0]
    poses.flags.writeable = False
    return poses


