"""A car's step length from the road's image motion: the plane-induced homography, searched along one axis.

Where a car's tracked corners lie on edges that run along the street (a bus's side stripes, a kerb, a
building's base line), forward motion slides them along themselves: KLT cannot see motion along an edge,
so such tracks barely move and PnP (and the triangulated scale, which needs parallax) reads a step
30-70 % short, for seconds at a time, with true depth as with a network's. The road is a plane at a known
height under the camera, so its image moves by a homography that depends on the step alone, whatever its
depth: with the rotation ``R`` and the direction ``d`` of the step known, a road point seen at ray ``r``
in the previous frame appears at ``K (R r - s d (n . r) / h)`` in this one (``n`` the road's normal towards
the camera, ``h`` the camera's height above it, ``s`` the step's length). So ``s`` is found by trying
lengths and comparing the previous image's textured road pixels (asphalt grain, lane marks) with this
image at their predicted places: a one-parameter direct alignment, dense over the road (the ground
plane's constraint on monocular scale: Kitt et al. 2011, Song & Chandraker 2014; here for the step
itself, not the depth's scale).

Pure functions of arrays; the visual odometry decides what to do with the length (``visual.py``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from shgm_slam.geometry.se3 import rot_x
from shgm_slam.perception.ground_scale import ROAD_RANGE_M, RoadPlane

COARSE_STEPS = 48
"""Lengths tried between 0 and the longest step, evenly; then ``FINE_STEPS`` around the best of them."""
FINE_STEPS = 21
PITCH_SEARCH_DEG = 1.0
COARSE_PITCHES = 5
FINE_PITCHES = 9
"""Pitch corrections searched with the lengths: +-``PITCH_SEARCH_DEG`` in ``COARSE_PITCHES``, then
``FINE_PITCHES`` around the best, one coarse step either side."""
MAX_ROAD_PIXELS = 1000
"""Textured road pixels compared at most (a regular subsample of them)."""
MIN_ROAD_PIXELS = 200
"""Fewer textured road pixels in view give no length."""
MIN_ROAD_GRADIENT = 8.0
"""Road pixels whose Sobel gradient magnitude is below this (about one grey level per pixel) carry no texture."""
MAX_ROAD_CONTRAST = 0.7
"""A road step counts when its photometric cost is at most this share of the median cost over the lengths
tried (a distinct minimum). Chosen on the RGB tuning drives (seeds 10-14, 30 car drives, the demo models'
depth and labels): per frame, against the true length, road steps more than 25 % off were 1-2 % of the
frames below 0.7 (the tracking chain's steps 5-8 % on the same frames), 7 % at 0.7-0.8 (9 %), 24 % at
0.8-0.9 (12 %); over whole drives (SE(3)-aligned odometry ATE, mean over the 30) tracks only 4.50 m, road
steps up to 0.7 2.91 m, up to 0.8 3.46 m."""
MIN_VALID_SHARE = 0.5
"""A length whose predicted places leave the image for more than half of the pixels is not scored."""


@dataclass(frozen=True)
class GroundStep:
    """The road's verdict on one step.

    Attributes:
        length_m: the step length whose homography matches the road best, metres (the plane's height units).
        contrast: the photometric cost at that length over the median cost of all lengths tried (0-1; low:
            a distinct minimum, near 1: the road gave no answer).
        pixels: textured road pixels compared.
        cost: the photometric cost at that length, grey levels (mean absolute difference, brightness change
            removed): comparable between searches of the same two images and pixels (another direction).
    """

    length_m: float
    contrast: float
    pixels: int
    cost: float


def textured_road_pixels(
    gray: np.ndarray, depth_m: np.ndarray, road: np.ndarray, min_gradient: float
) -> np.ndarray:
    """(N, 2) float64 pixels (u, v) of the road that carry texture: road in ``ROAD_RANGE_M`` whose Sobel
    gradient magnitude is at least ``min_gradient`` (grey levels per pixel, x8 by Sobel) and above the road's
    median, subsampled to ``MAX_ROAD_PIXELS``.

    Args:
        gray: (H, W) uint8 image. depth_m: (H, W) metres. road: (H, W) bool road mask.
    """
    img = np.asarray(gray, dtype=np.float32)
    grad = np.hypot(cv2.Sobel(img, cv2.CV_32F, 1, 0), cv2.Sobel(img, cv2.CV_32F, 0, 1))
    mask = road & (depth_m > ROAD_RANGE_M[0]) & (depth_m < ROAD_RANGE_M[1])
    if not mask.any():
        return np.zeros((0, 2))
    mask &= grad >= max(min_gradient, float(np.median(grad[mask])))
    v, u = np.nonzero(mask)
    step = max(1, len(u) // MAX_ROAD_PIXELS)
    return np.stack([u[::step], v[::step]], axis=1).astype(np.float64)


def ground_step(
    prev_gray: np.ndarray,
    gray: np.ndarray,
    pixels_uv: np.ndarray,
    K: np.ndarray,
    R_cam_prev: np.ndarray,
    direction_cam: np.ndarray,
    plane: RoadPlane,
    max_length_m: float,
) -> GroundStep | None:
    """Length of the step from the previous frame to this one that best moves the road between the images.

    The step's rotation comes from the tracks, whose pitch is least sure (0.2-0.5 deg on drives that pitch),
    and a pitch error moves the road in the image as a step does (1 px of pitch at 320x96 is a quarter of a
    0.9 m step at 8 m), so lengths and pitch corrections up to ``PITCH_SEARCH_DEG`` are searched together;
    the correction only serves the length.

    Args:
        prev_gray, gray: (H, W) uint8 previous and current images.
        pixels_uv: (N, 2) textured road pixels of the previous image (``textured_road_pixels``).
        K: (3, 3) camera matrix.
        R_cam_prev: (3, 3) rotation of the previous camera into this one (``X_cam = R X_prev + t``).
        direction_cam: (3,) unit direction of ``t`` (this camera's frame).
        plane: the road plane in the previous camera's frame (normal towards the camera, height).
        max_length_m: the longest step tried, metres.

    Returns:
        The best length and its contrast, or None with fewer than ``MIN_ROAD_PIXELS`` pixels or no
        length that keeps enough of them in the image.
    """
    if len(pixels_uv) < MIN_ROAD_PIXELS or plane.height <= 0 or max_length_m <= 0:
        return None
    ref = np.asarray(prev_gray, dtype=np.float32)
    cur = np.asarray(gray, dtype=np.float32)
    rays = np.linalg.solve(K, np.vstack([pixels_uv.T, np.ones(len(pixels_uv))]))  # (3, N)
    a = K @ R_cam_prev @ rays  # (3, N): the pixels' places for a zero step
    b = np.outer(K @ np.asarray(direction_cam, dtype=np.float64), plane.normal_cam @ rays) / plane.height
    values = ref[pixels_uv[:, 1].astype(np.int64), pixels_uv[:, 0].astype(np.int64)]
    h, w = cur.shape

    def costs(lengths: np.ndarray, pitches: np.ndarray) -> np.ndarray:
        """(P, S) mean absolute photometric differences (NaN: too few pixels stay in the image)."""
        tilt = K @ np.stack([rot_x(p) for p in pitches]) @ np.linalg.inv(K)  # (P, 3, 3) pitch corrections
        ta, tb = (tilt @ a).astype(np.float32), (tilt @ b).astype(np.float32)  # (P, 3, N)
        ls = lengths.astype(np.float32)[None, :, None]
        x, y, z = (ta[:, None, c] - ls * tb[:, None, c] for c in range(3))  # (P, S, N) each
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = x / z, y / z
        inside = (z > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        shape = u.shape
        u[~inside], v[~inside] = -1.0, -1.0
        diff = cv2.remap(cur, u.reshape(-1, shape[-1]), v.reshape(-1, shape[-1]), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(shape) - values  # fmt: skip
        diff[~inside] = 0.0
        count = inside.sum(axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            offset = diff.sum(axis=-1) / count  # brightness change between the frames
            out = (np.abs(diff - offset[..., None]) * inside).sum(axis=-1) / count
        out[count < MIN_VALID_SHARE * shape[-1]] = np.nan
        return out

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # lengths that leave the image are NaN on purpose
        lengths = np.linspace(0.0, max_length_m, COARSE_STEPS + 1)
        pitches = np.radians(np.linspace(-PITCH_SEARCH_DEG, PITCH_SEARCH_DEG, COARSE_PITCHES))
        c = costs(lengths, pitches)
        if not np.isfinite(c).any():
            return None
        median = float(np.nanmedian(np.nanmin(c, axis=0)))  # each length at its best pitch
        i, k = np.unravel_index(int(np.nanargmin(c)), c.shape)
        best = (float(c[i, k]), float(lengths[k]))
        dl, dp = lengths[1] - lengths[0], pitches[1] - pitches[0]
        fine_l = np.linspace(max(lengths[k] - dl, 0.0), lengths[k] + dl, FINE_STEPS)
        fine_p = np.linspace(pitches[i] - dp, pitches[i] + dp, FINE_PITCHES)
        f = costs(fine_l, fine_p)
        if np.isfinite(f).any():
            j, m = np.unravel_index(int(np.nanargmin(f)), f.shape)
            if f[j, m] < best[0]:
                best = (float(f[j, m]), float(fine_l[m]))
    contrast = best[0] / median if median > 0 else 1.0
    return GroundStep(best[1], float(contrast), len(pixels_uv), best[0])
