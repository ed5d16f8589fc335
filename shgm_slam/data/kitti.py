"""KITTI odometry sequences: ``image_2/`` (RGB) or ``image_0/`` (gray), ``calib.txt``, ``times.txt``, poses.

Ground truth is ``<seq>/poses.txt`` or, for ``<root>/sequences/<seq>``, ``<root>/poses/<seq>.txt``
(KITTI rows of ``T_world_cam0``). Poses are moved onto the camera that is read using the calib ``P``
line (``T_world_cam = T_world_cam0 @ T_cam0_cam``, about 6 cm for KITTI's image_2; nothing for P = [K|0]).

Frame counts: the images define the frames and must be named ``000000.png``, ``000001.png``, … without
gaps. ``times.txt`` (and poses when present) must have at least one row per image. KITTI downloads
are often partial (the shared sequence 07 holds the first 160 images but 1101 times and poses), so
extra trailing rows are accepted with a logged warning and ignored; fewer rows are a ``DataError``.
Frames load lazily when indexed; only the small index arrays are kept.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from shgm_slam.data.indexed import IndexedFrames
from shgm_slam.errors import DataError
from shgm_slam.io.trajectories import read_kitti_poses
from shgm_slam.types import Frame, Intrinsics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageSource:
    """An image folder and the calib line holding its projection matrix."""

    folder: str
    calib_key: str
    grayscale: bool


IMAGE_SOURCES = (ImageSource("image_2", "P2", False), ImageSource("image_0", "P0", True))
"""Preferred first: the left colour camera, then the left grayscale camera."""


def frame_file(folder: Path, index: int) -> Path:
    """Path of frame ``index`` in ``folder`` (``%06d.png``)."""
    return folder / f"{index:06d}.png"


def count_frame_files(folder: Path) -> int:
    """Number of frames in ``folder``; DataError when empty or when ``%06d.png`` names have gaps."""
    names = sorted(p.name for p in folder.iterdir() if p.suffix.lower() == ".png")
    if not names:
        raise DataError(f"image folder {folder} has no .png frames; expected 000000.png, 000001.png, ...")
    strays = [n for n in names if not (len(n) == 10 and n[:6].isdigit())]
    if strays:
        more = f" and {len(strays) - 1} more" if len(strays) > 1 else ""
        raise DataError(
            f"{folder / strays[0]}{more} is not a frame: frames are named 000000.png, 000001.png, ...; remove or "
            "rename the strays"
        )
    expected = [f"{i:06d}.png" for i in range(len(names))]
    if names != expected:
        first = next(e for n, e in zip(names, expected, strict=True) if n != e)
        raise DataError(
            f"frames in {folder} must be numbered 000000.png ... without gaps; {folder / first} is missing "
            "(rename the files)"
        )
    return len(names)


def _not_there(path: Path) -> str:
    """Why a file that must be there cannot be read: missing, or a folder of that name."""
    return "is a directory, not a file" if path.is_dir() else "is missing"


def read_png(path: Path, flags: int) -> np.ndarray:
    """``cv2.imread`` that raises a DataError naming the file when it is missing or corrupt."""
    image = cv2.imread(str(path), flags)
    if image is None:
        # removing the file would leave a gap in the numbering, which no sequence accepts: a range leaves it out
        leave_out = "use a frame range that leaves it out"
        if path.stem.isdigit():
            i = int(path.stem)
            leave_out += f" (SEQ:0-{i} or SEQ:{i + 1}-)" if i > 0 else " (SEQ:1-)"
        raise DataError(f"cannot read image {path} (missing or corrupt PNG); re-export that file, or {leave_out}")
    return image


def read_projection(calib_path: Path, key: str) -> np.ndarray:
    """(3, 4) projection matrix of the ``key:`` line (``P0`` … ``P3``) of a KITTI calib.txt."""
    if not calib_path.is_file():
        raise DataError(f"{calib_path} {_not_there(calib_path)}; a sequence needs a KITTI calib.txt with a {key} line")
    try:
        text = calib_path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DataError(f"{calib_path} is not UTF-8 text; write a KITTI calib.txt with a {key} line") from None
    except OSError as exc:
        raise DataError(f"cannot read {calib_path}: {exc.strerror or exc}; check its permissions") from None
    for line in text.splitlines():
        head, _, rest = line.partition(":")
        if head.strip() == key:
            try:
                values = np.array(rest.split(), dtype=np.float64)
            except ValueError:
                values = np.zeros(0)
            if values.size == 12 and np.isfinite(values).all():
                return values.reshape(3, 4)
            break
    raise DataError(
        f"{calib_path} has no {key} line of 12 finite numbers; add '{key}: fx 0 cx 0 0 fy cy 0 0 0 1 0'"
    )


MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0
"""A pinhole image's field of view along either axis outside this range is a wrong calibration (a focal length
in other units, or of another resolution), not a camera: rectified images of real lenses lie well inside."""
MAX_PIXEL_ASPECT = 2.0
"""Most ``fx / fy`` (or ``fy / fx``) of a real camera: pixels are square, anamorphic lenses stretch up to 2x."""


def pinhole_problem(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> str | None:
    """Why pinhole intrinsics (pixels) cannot be a ``width`` x ``height`` camera's, or None when they can: a focal
    length that is not positive (zero, or negative: a mirrored map) or not finite, a field of view outside
    ``MIN_FOV_DEG``-``MAX_FOV_DEG``, pixels stretched beyond ``MAX_PIXEL_ASPECT``, or a principal point outside
    the image. Shared by calib files (``check_projection``) and intrinsics given in memory."""
    if not (fx > 0 and fy > 0 and np.isfinite([fx, fy]).all()):
        return f"focal lengths must be positive (a negative one mirrors the map), got fx={fx:g}, fy={fy:g}"
    fov_deg = np.degrees(2.0 * np.arctan2([width / 2.0, height / 2.0], [fx, fy]))
    if not (MIN_FOV_DEG <= fov_deg.min() and fov_deg.max() <= MAX_FOV_DEG):
        return (f"focal lengths fx={fx:g}, fy={fy:g} px give a {fov_deg[0]:.3g} x {fov_deg[1]:.3g} degree field of "
                f"view on a {width}x{height} image (a camera has {MIN_FOV_DEG:g}-{MAX_FOV_DEG:g}): wrong units, or a "
                "calib for another resolution?")  # fmt: skip
    if max(fx, fy) > MAX_PIXEL_ASPECT * min(fx, fy):
        return (f"focal lengths fx={fx:g}, fy={fy:g} px differ {max(fx, fy) / min(fx, fy):.3g}-fold (a camera's "
                f"pixels are square, at most {MAX_PIXEL_ASPECT:g}x stretched): a mistyped calib?")  # fmt: skip
    if not (0 <= cx < width and 0 <= cy < height):
        return (f"principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image; is the calib for another "
                "camera or resolution?")  # fmt: skip
    return None


def check_projection(P: np.ndarray, width: int, height: int, calib_path: Path, key: str) -> None:
    """Sanity of a (3, 4) projection for a ``width`` x ``height`` image.

    Raises:
        DataError: what ``pinhole_problem`` finds in its focal lengths and principal point, or a skewed or
            non-pinhole matrix.
    """
    fx, fy, cx, cy = P[0, 0], P[1, 1], P[0, 2], P[1, 2]
    where = f"{calib_path} {key}"
    skewed = abs(P[0, 1]) > 1e-6 * abs(fx) or abs(P[1, 0]) > 1e-6 * abs(fx)
    if skewed or abs(P[2, 0]) > 1e-9 or abs(P[2, 1]) > 1e-9 or abs(P[2, 2] - 1.0) > 1e-6:
        rows = "; ".join(" ".join(f"{v:g}" for v in row) for row in P[:, :3])
        raise DataError(f"{where}: expected a pinhole projection 'fx 0 cx tx 0 fy cy ty 0 0 1 tz', got [{rows}]")
    problem = pinhole_problem(fx, fy, cx, cy, width, height)
    if problem is not None:
        raise DataError(f"{where}: {problem}")


MIN_FRAME_INTERVAL_S = 1e-3
"""Shortest median frame interval ``times.txt`` may give, seconds (1000 frames per second): shorter means the
times are not in seconds, and every frame's motion reads as an impossible speed (the odometry breaks at each)."""

MAX_FRAME_INTERVAL_S = 30.0
"""Longest median frame interval, seconds: a 10 Hz camera's times in milliseconds read 100 s apart, in
microseconds or nanoseconds days or years."""


def read_times(path: Path) -> np.ndarray:
    """(N,) float64 seconds from a times.txt (one number a line)."""
    if not path.is_file():
        raise DataError(f"{path} {_not_there(path)}; write one timestamp (seconds) per frame")
    try:
        with warnings.catch_warnings():  # an empty file is reported below as a count mismatch
            warnings.simplefilter("ignore", UserWarning)
            times = np.loadtxt(path, dtype=np.float64, ndmin=1, comments="#")
    except ValueError as e:
        raise DataError(f"{path} must hold one number per line: {e}") from e
    if times.ndim != 1:
        raise DataError(f"{path} must hold one number per line (got {times.shape[1]} columns)")
    return check_times(times, str(path), "line")


def check_times(times: np.ndarray, where: str, row: str = "frame") -> np.ndarray:
    """(N,) float64 timestamps in seconds, checked: finite, strictly increasing, frames between
    ``MIN_FRAME_INTERVAL_S`` and ``MAX_FRAME_INTERVAL_S`` apart (median). DataError otherwise, naming ``where``
    and the offending ``row`` ("line" numbers count from 1, "frame" indices from 0)."""
    times = np.asarray(times, dtype=np.float64)
    first = 1 if row == "line" else 0
    if times.ndim != 1:
        raise DataError(f"{where}: timestamps must be one number per frame, not an array of shape {times.shape}")
    if not np.isfinite(times).all():
        k = int(np.flatnonzero(~np.isfinite(times))[0])
        raise DataError(f"{where}: {row} {k + first} holds {times[k]:g}; every {row} needs a finite timestamp in "
                        "seconds")  # fmt: skip
    steps = np.diff(times)
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0])
        raise DataError(
            f"{where}: timestamps must increase, but {row} {k + 1 + first} ({times[k + 1]:g} s) is not after "
            f"{row} {k + first} ({times[k]:g} s); frames out of order or duplicated?"
        )
    if steps.size:
        step = float(np.median(steps))
        if not MIN_FRAME_INTERVAL_S <= step <= MAX_FRAME_INTERVAL_S:
            raise DataError(
                f"{where}: frames are {step:.3g} s apart (median), {1.0 / step:.3g} frames per second; timestamps "
                "must be in seconds (in milliseconds, microseconds or nanoseconds? divide by 1e3, 1e6 or 1e9)"
            )
    return times


MAX_POSE_SPEED_MPS = 200.0
"""A robot's own odometry (``T_odom_cam``) or ground truth (``T_world_cam``, a poses file) whose median speed
between frames is above this (720 km/h) is refused: its translations are not in metres (millimetres give 1000x the
speed; every odometry step would be cut as a failure, the ground truth's ATE would be kilometres)."""


def check_pose_units(T_x_cam: np.ndarray, timestamps_s: np.ndarray, where: str, what: str = "T_odom_cam") -> None:
    """Refuse (DataError at ``where``) poses (N, 4, 4) ``T_x_cam`` (a robot's own odometry ``T_odom_cam``, ground
    truth ``T_world_cam``, a poses file; called ``what`` in messages) at (N,) ``timestamps_s``, whose median speed
    between frames is above ``MAX_POSE_SPEED_MPS``: translations not in metres (ground truth in millimetres gave
    an ATE of 16 km without a word)."""
    if len(T_x_cam) < 2:
        return
    steps_m = np.linalg.norm(np.diff(T_x_cam[:, :3, 3], axis=0), axis=1)
    speed_mps = float(np.median(steps_m / np.diff(timestamps_s)))
    if speed_mps > MAX_POSE_SPEED_MPS:
        raise DataError(f"{where}: {what} moves at {speed_mps:.3g} m/s between frames (median), faster than any "
                        f"robot ({MAX_POSE_SPEED_MPS:g} m/s); give its translations in metres (in millimetres or "
                        "centimetres? divide them by 1000 or 100)")  # fmt: skip


def sequence_folder_problem(root: Path) -> str | None:
    """Why ``root`` is no sequence folder (what ``open_sequence``, ``KittiSequence`` and ``evaluate``'s sequences
    say), or None when it is a folder: a file given where its folder is meant (a sequence's ``poses.txt``, said
    to be "a folder that does not exist" before), nothing there, or a path that cannot be looked at (a name too
    long, a parent folder without permission: an OSError traceback before)."""
    try:
        if root.is_dir():
            return None
        if root.exists():
            return (f"{root} is a file; give the robot's sequence folder (its images, times.txt and poses.txt), "
                    "not a file in it")  # fmt: skip
    except OSError as exc:
        return f"sequence folder {root} cannot be looked at ({exc.strerror or exc}); check the path"
    return f"sequence folder {root} does not exist; check the path"


def find_gt_file(root: Path) -> Path | None:
    """``root/poses.txt``, else ``<kitti>/poses/<seq>.txt`` when ``root`` is ``<kitti>/sequences/<seq>``.

    Raises:
        DataError: the one found is a folder (the sequence read as having no ground truth before).
    """
    kitti_file = root.parent.parent / "poses" / f"{root.name}.txt"
    for path in (root / "poses.txt", *([kitti_file] if root.parent.name == "sequences" else [])):
        if path.is_dir():
            raise DataError(f"{path} is a folder where the sequence's pose file should be (KITTI rows of "
                            "T_world_cam0, one per image); move that folder away")  # fmt: skip
        if path.is_file():
            return path
    return None


def fit_count(values: np.ndarray, count: int, path: Path, allow_extra: bool) -> np.ndarray:
    """First ``count`` rows of ``values``; DataError when too few (or too many and not ``allow_extra``)."""
    n = values.shape[0]
    if n == count:
        return values
    if n < count or not allow_extra:
        raise DataError(
            f"{path} has {n} rows but there are {count} images; every frame needs exactly one row "
            "(fix the file or remove the extra images)"
        )
    log.warning("%s has %d rows for %d images; using the first %d (partial download?)", path, n, count, count)
    return values[:count]


class KittiSequence(IndexedFrames):
    """A KITTI odometry sequence folder (see the module doc for the layout and the count policy)."""

    allow_extra_rows = True

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root).absolute()
        if (problem := sequence_folder_problem(self.root)) is not None:
            raise DataError(problem)
        source = next((s for s in IMAGE_SOURCES if (self.root / s.folder).is_dir()), None)
        if source is None:
            raise DataError(
                f"{self.root} has neither image_2/ nor image_0/; point at a KITTI-style sequence folder"
            )
        self.name = self.root.name
        self._source = source
        self._image_dir = self.root / source.folder
        count = count_frame_files(self._image_dir)
        P = read_projection(self.root / "calib.txt", source.calib_key)
        first = self._read_image(0, check_size=False)
        check_projection(P, first.shape[1], first.shape[0], self.root / "calib.txt", source.calib_key)
        self.intrinsics = Intrinsics.from_K(P[:, :3], first.shape[1], first.shape[0])
        self._times = fit_count(read_times(self.root / "times.txt"), count, self.root / "times.txt",
                                self.allow_extra_rows)
        self._times.flags.writeable = False
        self._gt: np.ndarray | None = None
        gt_file = find_gt_file(self.root)
        if gt_file is not None:
            T_cam0_cam = np.eye(4)
            T_cam0_cam[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])  # P = K [I | t], t = p_cam of cam0 origin
            T_world_cam0 = fit_count(read_kitti_poses(gt_file), count, gt_file, self.allow_extra_rows)
            check_pose_units(T_world_cam0, self._times, str(gt_file), "the ground truth")
            self._gt = T_world_cam0 @ T_cam0_cam
            self._gt.flags.writeable = False

    @property
    def has_depth(self) -> bool:
        return False

    @property
    def has_labels(self) -> bool:
        return False

    def _check_size(self, image: np.ndarray, path: Path) -> None:
        wh = (image.shape[1], image.shape[0])
        if wh != self.intrinsics.size_wh:
            raise DataError(
                f"{path} is {wh[0]}x{wh[1]} but the sequence's first frame is "
                f"{self.intrinsics.width}x{self.intrinsics.height}; all frames must share one size"
            )

    def _read_image(self, index: int, check_size: bool = True) -> np.ndarray:
        """(H, W, 3) uint8 RGB of file ``index`` (grayscale replicated to 3 channels)."""
        path = frame_file(self._image_dir, index)
        if self._source.grayscale:
            image = cv2.cvtColor(read_png(path, cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2RGB)
        else:
            image = cv2.cvtColor(read_png(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        if check_size:
            self._check_size(image, path)
        return image

    def _frame(self, i: int) -> Frame:
        """Frame ``i`` (0..N-1), loaded from disk now."""
        return Frame(
            index=i,
            timestamp_s=float(self._times[i]),
            intrinsics=self.intrinsics,
            image_rgb=self._read_image(i),
            T_world_cam=None if self._gt is None else self._gt[i].copy(),
            source_index=i,
        )
