"""Odometry that did not move while the camera did: a degenerate trajectory reported, never hidden.

All-zero or NaN depth, a wrong depth kind in a model card or a voxel far too small give identity poses:
a robot that "never moves" although its images change from frame to frame. ``ImageChange`` measures the
images with a plain frame difference (grey 32x24 thumbnails, mean absolute difference); ``odometry_motion``
sums the odometry's steps; ``stillness_warning`` compares the two.
"""

from __future__ import annotations

import cv2
import numpy as np

THUMB_WH = (32, 24)
"""Thumbnail size of the frame difference (robust to noise, cheap)."""
CHANGED_GREY = 3.0
"""Mean absolute grey difference (0..255) of consecutive thumbnails above which the view changed."""
STILL_PATH_M = 0.05
STILL_ROTATION_DEG = 1.0
"""Odometry whose whole path is below both of these did not move."""
MIN_CHANGED_PAIRS = 3
MIN_CHANGED_FRACTION = 0.5
"""... and the images moved when at least this many (and this share) of consecutive frames changed."""


class ImageChange:
    """Counts consecutive frames whose images differ (``CHANGED_GREY``); feed frames in order."""

    def __init__(self) -> None:
        self.pairs = 0
        self.changed = 0
        self._prev: np.ndarray | None = None

    def add(self, image_rgb: np.ndarray | None) -> None:
        """Compare (H, W, 3) uint8 ``image_rgb`` with the previous image given (None: ignored)."""
        if image_rgb is None or np.ndim(image_rgb) != 3:
            return
        grey = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
        thumb = cv2.resize(grey, THUMB_WH, interpolation=cv2.INTER_AREA).astype(np.float32)
        if self._prev is not None:
            self.pairs += 1
            self.changed += float(np.abs(thumb - self._prev).mean()) > CHANGED_GREY
        self._prev = thumb


def odometry_motion(T_odom_cam: np.ndarray, frame_segment: np.ndarray) -> tuple[float, float]:
    """(path length m, summed rotation deg) of the odometry's steps within each trajectory segment.

    Args:
        T_odom_cam: (N, 4, 4) per-frame odometry poses; NaN rows (skipped frames) are left out.
        frame_segment: (N,) trajectory segment of each frame (-1: none).
    """
    T = np.asarray(T_odom_cam, dtype=np.float64)
    ok = np.isfinite(T.reshape(len(T), -1)).all(axis=1) & (np.asarray(frame_segment) >= 0)
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return 0.0, 0.0
    a, b = idx[:-1], idx[1:]
    same = np.asarray(frame_segment)[a] == np.asarray(frame_segment)[b]
    a, b = a[same], b[same]
    path = float(np.linalg.norm(T[b, :3, 3] - T[a, :3, 3], axis=1).sum())
    R_rel = np.einsum("nji,njk->nik", T[a, :3, :3], T[b, :3, :3])
    cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return path, float(np.degrees(np.arccos(cos)).sum())


def stillness_warning(
    path_m: float, rotation_deg: float, images: ImageChange, *, given: bool = False
) -> str | None:
    """A warning when the odometry did not move although the images did, else None; ``given``: the odometry was the
    robot's own, given with its frames (the hint then points at those poses, not at the depth)."""
    moved_images = images.changed >= MIN_CHANGED_PAIRS and images.changed >= MIN_CHANGED_FRACTION * images.pairs
    if not moved_images or path_m >= STILL_PATH_M or rotation_deg >= STILL_ROTATION_DEG:
        return None
    check = ("check the T_odom_cam given with the frames: the robot's own odometry, which the run used as given"
             if given else "check the depth: valid pixels, scale, a model card's depth kind; odometry.voxel_size; "
             "or --odometry")  # fmt: skip
    return (
        f"odometry did not move ({path_m:.2f} m, {rotation_deg:.1f} deg in all) while the images changed in "
        f"{images.changed} of {images.pairs} consecutive frames: its trajectory is invalid ({check})"
    )
