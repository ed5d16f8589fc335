"""Our sequence layout (what ``simulate`` writes, what ``run`` reads): KITTI plus optional depth and labels.

```
<sequence>/ image_2/%06d.png (RGB)  depth/%06d.png (uint16, metres x 256, 0 = invalid)
            semantic/%06d.png (uint8 train ids)  calib.txt (P0..P3 = [K|0])  times.txt  poses.txt (optional)
```
Unlike KITTI downloads, counts must agree exactly: every image has one times row, one pose row (when
poses.txt exists), one depth and one label PNG (when those folders exist).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import TracebackType
from typing import TextIO

import cv2
import numpy as np

from shgm_slam.data.kitti import KittiSequence, count_frame_files, frame_file, read_png
from shgm_slam.errors import DataError
from shgm_slam.io.trajectories import format_kitti_pose
from shgm_slam.types import Frame, Intrinsics

DEPTH_SCALE = 256.0
"""Depth PNG units per metre (KITTI depth convention): uint16 value = round(depth_m * 256)."""
DEPTH_DIR, LABEL_DIR, IMAGE_DIR = "depth", "semantic", "image_2"
PERCEIVE_MANIFEST = "perceive.json"
"""What ``shgm-slam perceive`` writes beside the depth and labels it predicted (``complete`` once done)."""
_WRITTEN = (IMAGE_DIR, DEPTH_DIR, LABEL_DIR, "calib.txt", "times.txt", "poses.txt")


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres -> uint16 ``round(m * 256)`` clipped to 65535; 0 for invalid, non-finite or <= 0."""
    d = np.asarray(depth_m, dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0.0), d, 0.0)
    return np.clip(np.rint(d * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def decode_depth(depth_png: np.ndarray) -> np.ndarray:
    """uint16 depth PNG values -> (H, W) float32 metres (0 stays 0 = invalid)."""
    return depth_png.astype(np.float32) / np.float32(DEPTH_SCALE)


def read_perceive_manifest(root: Path) -> dict | None:
    """``root``'s ``perceive.json`` as a dict; None when it is absent, unreadable or not an object."""
    try:
        manifest = json.loads((Path(root) / PERCEIVE_MANIFEST).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _unfinished_perceive(root: Path) -> bool:
    """True when ``root`` holds a ``perceive`` manifest that says the job did not finish."""
    manifest = read_perceive_manifest(root)
    return manifest is not None and manifest.get("complete") is False


class ShgmSequence(KittiSequence):
    """A sequence in our layout: ``KittiSequence`` plus lazily loaded ``depth/`` and ``semantic/``."""

    allow_extra_rows = False

    def __init__(self, root: Path | str) -> None:
        super().__init__(root)
        self._depth_dir = self.root / DEPTH_DIR if (self.root / DEPTH_DIR).is_dir() else None
        self._label_dir = self.root / LABEL_DIR if (self.root / LABEL_DIR).is_dir() else None
        for folder in (self._depth_dir, self._label_dir):
            if folder is not None and (n := count_frame_files(folder)) != len(self):
                if _unfinished_perceive(self.root):
                    raise DataError(
                        f"{self.root} is an unfinished `shgm-slam perceive` output ({n} of {len(self)} frames in "
                        f"{folder.name}/): run the same perceive command again to finish it (it resumes)"
                    )
                raise DataError(
                    f"{folder} has {n} frames but {self._image_dir} has {len(self)}; "
                    "every image needs one file there (or remove the folder)"
                )

    @property
    def has_depth(self) -> bool:
        return self._depth_dir is not None

    @property
    def has_labels(self) -> bool:
        return self._label_dir is not None

    def _read_single_channel(self, folder: Path, index: int, dtype: type, what: str) -> np.ndarray:
        path = frame_file(folder, index)
        image = read_png(path, cv2.IMREAD_UNCHANGED)
        if image.dtype != dtype or image.ndim != 2:
            raise DataError(
                f"{path} is a {image.dtype} PNG with shape {image.shape}; {what} must be single-channel "
                f"{np.dtype(dtype).name} (re-export it)"
            )
        self._check_size(image, path)
        return image

    def _frame(self, i: int) -> Frame:
        frame = super()._frame(i)
        i = frame.source_index
        if self._depth_dir is not None:
            depth = self._read_single_channel(self._depth_dir, i, np.uint16, "depth (metres x 256)")
            frame.depth_m = decode_depth(depth)
        if self._label_dir is not None:
            frame.label_ids = self._read_single_channel(self._label_dir, i, np.uint8, "labels (train ids)")
        return frame


class SequenceWriter:
    """Streams frames into our layout; each ``write`` lands on disk at once (interrupted runs keep it).

    Use as a context manager. ``calib.txt`` is written at construction (P0..P3 = [K|0]). Frames are
    numbered 0, 1, ... in call order; their ``index`` is ignored.
    """

    def __init__(
        self,
        root: Path | str,
        intrinsics: Intrinsics,
        *,
        overwrite: bool = False,
        write_depth: bool = True,
        write_labels: bool = True,
    ) -> None:
        self.root = Path(root)
        self.intrinsics = intrinsics
        self.write_depth, self.write_labels = write_depth, write_labels
        if self.root.exists() and not self.root.is_dir():
            raise DataError(f"cannot write a sequence to {self.root}: it is a file; choose a folder")
        if self.root.is_dir() and any(self.root.iterdir()):
            if not overwrite:
                raise DataError(f"{self.root} is not empty; choose a new folder or pass overwrite=True")
            for name in _WRITTEN:  # only what we write: never wipe a folder we did not create
                p = self.root / name
                shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
        folders = [IMAGE_DIR] + [DEPTH_DIR] * write_depth + [LABEL_DIR] * write_labels
        for name in folders:
            (self.root / name).mkdir(parents=True, exist_ok=True)
        P = np.hstack([intrinsics.K, np.zeros((3, 1))]).ravel()
        line = " ".join(f"{v:.12e}" for v in P)
        (self.root / "calib.txt").write_text("".join(f"P{k}: {line}\n" for k in range(4)))
        self._times: TextIO | None = open(self.root / "times.txt", "w")  # closed in close()
        self._poses: TextIO | None = None
        self._has_poses: bool | None = None
        self.count = 0

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _check(self, array: np.ndarray | None, what: str, fix: str) -> np.ndarray:
        if array is None:
            raise DataError(f"frame {self.count} for {self.root} has no {what}; {fix}")
        h, w = np.shape(array)[:2]
        if (w, h) != self.intrinsics.size_wh:
            raise DataError(
                f"frame {self.count} {what} is {w}x{h} but {self.root} was opened for "
                f"{self.intrinsics.width}x{self.intrinsics.height}"
            )
        return np.asarray(array)

    def _imwrite(self, folder: str, image: np.ndarray) -> None:
        path = frame_file(self.root / folder, self.count)
        if not cv2.imwrite(str(path), image):
            raise DataError(f"cannot write {path}; check free disk space and permissions")

    def write(self, frame: Frame) -> None:
        """Append ``frame``: image_2 (RGB), depth (uint16 m*256), semantic (uint8), times and poses rows."""
        if self._times is None:
            raise DataError(f"the writer for {self.root} is closed; open a new SequenceWriter")
        rgb = self._check(frame.image_rgb, "image_rgb", "every frame needs an image")
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise DataError(f"frame {self.count} image_rgb must be HxWx3 uint8, not {rgb.dtype} {rgb.shape}")
        has_pose = frame.T_world_cam is not None
        if has_pose and (np.shape(frame.T_world_cam) != (4, 4) or not np.isfinite(frame.T_world_cam).all()):
            raise DataError(f"frame {self.count} T_world_cam must be a finite (4, 4) pose")
        if not np.isfinite(frame.timestamp_s):
            raise DataError(f"frame {self.count} has a non-finite timestamp_s ({frame.timestamp_s})")
        if self._has_poses is not None and has_pose != self._has_poses:
            raise DataError(f"frame {self.count} for {self.root}: either every frame has T_world_cam or none")
        depth = labels = None
        if self.write_depth:
            depth = encode_depth(self._check(frame.depth_m, "depth_m", "set it or pass write_depth=False"))
            if depth.ndim != 2:
                raise DataError(f"frame {self.count} depth_m must be (H, W) metres, got shape {depth.shape}")
        if self.write_labels:
            labels = self._check(frame.label_ids, "label_ids", "set it or pass write_labels=False")
            integer = np.issubdtype(labels.dtype, np.integer)
            if labels.ndim != 2 or not integer or labels.min() < 0 or labels.max() > 255:
                raise DataError(f"frame {self.count} label_ids must be (H, W) integer train ids in 0..255")
            labels = labels.astype(np.uint8)
        self._imwrite(IMAGE_DIR, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if depth is not None:
            self._imwrite(DEPTH_DIR, depth)
        if labels is not None:
            self._imwrite(LABEL_DIR, labels)
        self._times.write(f"{float(frame.timestamp_s):.9f}\n")
        self._times.flush()
        if has_pose:
            if self._poses is None:
                self._poses = open(self.root / "poses.txt", "w")  # closed in close()
            self._poses.write(format_kitti_pose(frame.T_world_cam) + "\n")
            self._poses.flush()
        self._has_poses = has_pose
        self.count += 1

    def close(self) -> None:
        """Flush and close the times/poses files (idempotent)."""
        for handle in (self._times, self._poses):
            if handle is not None:
                handle.close()
        self._times = self._poses = None
