"""Metric scale of predicted depth from the road under a car's camera (known mounting height).

A monocular depth network's metric scale drifts with the scene: the demo models predict depth
2-14 % long on cities they were not trained on (more on some kinds of city than others), and every
metre the odometry and the semantic graph measure inherits that factor. The road under a car is the
one surface whose distance from the camera is known in advance: the camera's mounting height (KITTI:
1.65 m). So each frame's road pixels are back-projected with the predicted depth, a plane is fitted
to them, and the depth is scaled by ``camera_height_m / (the camera's distance from that plane)``,
smoothed by a running median over recent frames (the scale of monocular visual odometry fixed from
the ground plane: Kitt et al. 2011, Song & Chandraker 2014).

Only a level camera's road counts: the plane's normal must be within ``MAX_TILT_DEG`` of the camera's
vertical (image down) axis, the road within ``ROAD_RANGE_M``, and the measured factor within
[``MIN_FACTOR``, ``MAX_FACTOR``]; a UAV's oblique view (normal 40-50 deg off, ground 30-60 m away) fails
these and leaves the depth as predicted, which the caller reports. A running factor outside
``USUAL_FACTOR`` is used but reported (``usual_factor``): a network far off scale, or a wrong mounting
height.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

from shgm_slam.geometry.camera import backproject
from shgm_slam.labels import Label
from shgm_slam.types import Intrinsics

MAX_TILT_DEG = 25.0
"""The road plane's normal is at most this far from the camera's vertical axis (a level car camera)."""
MIN_FACTOR, MAX_FACTOR = 0.2, 5.0
"""A per-frame factor outside this range is not a car camera at the configured height: not used. Wide, since
a network can be off by several times on images unlike its training set (the demo models, trained on our
synthetic cities, read KITTI 07's road 2-10 m below the camera where it lies 1.65 m: between 0.67 and 1.5
only the first ten frames' factors were used, and the odometry ran 2-4 times too far with too few corners
within its depth range); a UAV's ground lies beyond ``ROAD_RANGE_M`` or tilted past ``MAX_TILT_DEG``."""
USUAL_FACTOR = (0.67, 1.5)
"""A running factor outside this range is reported (``usual_factor``): the network's scale is far off, or the
camera is not at the configured height, which the road alone cannot tell apart."""
ROAD_RANGE_M = (2.0, 25.0)
"""Road pixels whose predicted depth is in this range are fitted (near road is predicted best)."""
MIN_ROAD_POINTS = 100
MAX_FIT_POINTS = 1000
RANSAC_HYPOTHESES = 64
INLIER_FRACTION = 0.05  # a point is on the plane within this fraction of the camera's height above it
WINDOW_FRAMES = 30
WARN_AFTER_REJECTED = 20
"""A road plane refused this many times with none accepted is logged once (a UAV, a wrong mounting height)."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RoadPlane:
    """The road plane of one frame, in the camera frame (x right, y down, z forward).

    Attributes:
        normal_cam: (3,) unit normal pointing from the road up towards the camera.
        height: the camera's distance from the plane, in the depth's units (metres if metric).
        inliers: road points on the plane (of at most ``MAX_FIT_POINTS`` fitted).
    """

    normal_cam: np.ndarray
    height: float
    inliers: int


def road_plane(depth_m: np.ndarray, label_ids: np.ndarray, intrinsics: Intrinsics) -> RoadPlane | None:
    """Plane fitted to the road pixels of one depth image (RANSAC on 3 points, then least squares).

    Unlike ``scene_scale.fit_ground_plane`` (any ground: road, sidewalk, terrain or the lowest image rows,
    any tilt, at any range; for the scene's scale, a UAV's included), only the road near a level camera
    counts: the kerb's 15 cm and a far road's depth error would bias the height this scale is read from.

    Args:
        depth_m: (H, W) z-depth, metres (0 or non-finite: unknown).
        label_ids: (H, W) Cityscapes train ids; pixels labelled road are fitted.
        intrinsics: pinhole intrinsics of the image.

    Returns:
        The plane, or None with fewer than ``MIN_ROAD_POINTS`` road points in ``ROAD_RANGE_M``, or when
        no plane within ``MAX_TILT_DEG`` of level holds enough of them. Deterministic.
    """
    road_depth = np.where(np.asarray(label_ids) == Label.ROAD, np.asarray(depth_m, dtype=np.float64), 0.0)
    points, _ = backproject(road_depth, intrinsics, min_depth_m=ROAD_RANGE_M[0], max_depth_m=ROAD_RANGE_M[1])
    if len(points) < MIN_ROAD_POINTS:
        return None
    points = points[:: max(1, len(points) // MAX_FIT_POINTS)]
    rng = np.random.default_rng(0)
    triples = points[rng.integers(0, len(points), size=(RANSAC_HYPOTHESES, 3))]  # (K, 3, 3)
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    spread = norms > 1e-9  # a triple with a repeated or collinear point spans no plane
    normals, anchors = normals[spread] / norms[spread, None], triples[spread, 0]
    level = np.abs(normals[:, 1]) >= np.cos(np.radians(MAX_TILT_DEG))
    normals, anchors = normals[level], anchors[level]
    if len(normals) == 0:
        return None
    offsets = -np.sum(normals * anchors, axis=1)  # plane n.x + d = 0; |d| = the camera's height above it
    residual = np.abs(points @ normals.T + offsets)  # (N, K)
    on_plane = residual < INLIER_FRACTION * np.abs(offsets)
    best = int(np.argmax(on_plane.sum(axis=0)))
    inliers = points[on_plane[:, best]]
    if len(inliers) < MIN_ROAD_POINTS // 2:
        return None
    centre = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
    if abs(normal[1]) < np.cos(np.radians(MAX_TILT_DEG)):
        return None
    normal = normal if normal @ centre < 0 else -normal  # towards the camera (the origin)
    return RoadPlane(normal, float(abs(normal @ centre)), len(inliers))


class GroundScale:
    """Running depth scale from the road plane: ``camera_height_m / measured height``, median of a window.

    Args:
        camera_height_m: the camera's height above the road, metres (KITTI 1.65).
        window: frames whose factors the median is taken over.

    ``update`` returns the factor to multiply this frame's depth by, or None while no frame has given a
    usable one (then the depth stays as predicted). ``frames``/``planes``/``rejected`` count the frames
    seen, those with a usable factor, and those whose road plane gave a factor out of range.
    """

    def __init__(self, camera_height_m: float, window: int = WINDOW_FRAMES) -> None:
        self.camera_height_m = float(camera_height_m)
        self._factors: deque[float] = deque(maxlen=window)
        self.frames = 0
        self.planes = 0
        self.rejected = 0
        self.rejected_height: float | None = None  # the last out-of-range height measured, depth units

    def reset(self) -> None:
        """Forget every frame seen (the window and the counts): a run starts from its own first frame."""
        self._factors.clear()
        self.frames = self.planes = self.rejected = 0
        self.rejected_height = None

    def update(self, depth_m: np.ndarray, label_ids: np.ndarray, intrinsics: Intrinsics) -> float | None:
        """Measure this frame's road plane (if any) and return the current factor (or None)."""
        self.frames += 1
        plane = road_plane(depth_m, label_ids, intrinsics)
        if plane is not None and plane.height > 0:
            factor = self.camera_height_m / plane.height
            if MIN_FACTOR <= factor <= MAX_FACTOR:
                self._factors.append(factor)
                self.planes += 1
            else:
                self.rejected += 1
                self.rejected_height = plane.height
                if self.rejected == WARN_AFTER_REJECTED and not self.planes:
                    log.warning(
                        "the road lies %.1f m below the camera by the predicted depth, not perception.camera_height_m"
                        " = %.2f m: depth left as predicted (for a car, set camera_height_m to its mounting height)",
                        plane.height, self.camera_height_m,
                    )  # fmt: skip
        return float(np.median(self._factors)) if self._factors else None


def usual_factor(factor: float) -> bool:
    """Whether a running depth factor lies within ``USUAL_FACTOR`` (a network's usual scale error)."""
    return USUAL_FACTOR[0] <= factor <= USUAL_FACTOR[1]
