"""A ground vehicle's turn between two images from its tracked corners, under planar circular motion.

A car turns about the vertical and drives where it points: between two frames its camera rotates by θ
about its y axis (a level camera, x right, y down, z forward) and moves along the chord of a circular
arc, the direction ``(sin θ/2, 0, cos θ/2)`` (the non-holonomic model of Scaramuzza et al., "Real-time
monocular visual odometry for on-road vehicles with 1-point RANSAC", ICRA 2009). The epipolar constraint
then depends on θ alone, and on no depth: every tracked corner votes for θ through its Sampson distance
to the epipolar line, and the θ that the most corners agree with (a truncated cost, so corners on moving
cars do not pull) is the turn.

Why: depth-assisted PnP trades a turn for a sideways shift when the depth is wrong (a narrow field of
view cannot tell them apart), so on a monocular network's depth the visual odometry's heading drifts
30-50 degrees over a 950 m synthia-like drive; the images' global shift (``image_rotation``) is biased
too, by the expansion of near objects on one side of the street. With the motion model the sideways
shift is no longer free: on the same drives (rendered images, 320x96) the summed turn is off by
0.2-1.6 degrees, and one frame in 950 is off by 9 degrees (the cost's minimum is then shallow: ``support``
tells).

Pure: pixel arrays in, an angle out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.types import Intrinsics

MAX_TURN_DEG = 25.0
"""Largest turn between two consecutive frames searched (a car at 10 fps turns less than 11 deg)."""

COARSE_STEP_DEG = 0.25
FINE_STEP_DEG = 0.005
"""The search grid: coarse over +-``MAX_TURN_DEG``, then fine around the coarse minimum."""

TRUNCATE_PX = 1.0
TRUNCATE_DEG = 0.3
"""A corner's Sampson distance counts up to the larger of ``TRUNCATE_PX`` pixels and ``TRUNCATE_DEG`` of
viewing angle (outliers cost the same, however far); a corner within it agrees with the turn. The angle
is what a real car's motion departs from the model by (suspension pitch, a camera ahead of the rear
axle): at 320x96 (fx 184 px) the pixel floor rules, at KITTI's 1226x370 (fx 707 px) the angle, 3.7 px,
where 1 px left half of the frames of sequence 07 below 80 % support."""

MIN_CORNERS = 20
"""Fewer tracked corners give no estimate."""


@dataclass(frozen=True)
class PlanarTurn:
    """The turn that best explains a frame pair's tracks.

    Attributes:
        yaw_rad: θ with ``R_prev_cur = R_y(θ)`` (``image_rotation.rot_y``), radians.
        support: fraction of the corners that agree with it (within the truncation, ``TRUNCATE_DEG``).
        corners: corners used.
    """

    yaw_rad: float
    support: float
    corners: int


def planar_turn(uv_prev: np.ndarray, uv_cur: np.ndarray, intrinsics: Intrinsics) -> PlanarTurn | None:
    """The planar circular-motion turn from corners tracked between two consecutive images.

    Args:
        uv_prev, uv_cur: (N, 2) pixels (u right, v down) of the same corners in the previous and the
            current image.
        intrinsics: pinhole intrinsics of both images.

    Returns:
        ``PlanarTurn`` or None with fewer than ``MIN_CORNERS`` corners.
    """
    uv_prev = np.asarray(uv_prev, dtype=np.float64).reshape(-1, 2)
    uv_cur = np.asarray(uv_cur, dtype=np.float64).reshape(-1, 2)
    if len(uv_prev) < MIN_CORNERS or uv_cur.shape != uv_prev.shape:
        return None
    x1, x2 = _rays(uv_prev, intrinsics), _rays(uv_cur, intrinsics)
    fx = float(intrinsics.fx)
    truncate_px = _truncate_px(fx)
    coarse = np.radians(np.arange(-MAX_TURN_DEG, MAX_TURN_DEG + 1e-9, COARSE_STEP_DEG))
    cost = _cost(coarse, x1, x2, fx, truncate_px)
    centre = coarse[int(np.argmin(cost))]
    fine = centre + np.radians(np.arange(-COARSE_STEP_DEG, COARSE_STEP_DEG + 1e-9, FINE_STEP_DEG))
    cost = _cost(fine, x1, x2, fx, truncate_px)
    k = int(np.argmin(cost))
    yaw = float(fine[k])
    if 0 < k < len(fine) - 1:  # parabola through the minimum and its neighbours
        c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
        curvature = c0 - 2.0 * c1 + c2
        if curvature > 0:
            yaw += 0.5 * (c0 - c2) / curvature * np.radians(FINE_STEP_DEG)
    d2 = _sampson_px2(np.array([yaw]), x1, x2, fx)[0]
    return PlanarTurn(yaw, float(np.mean(d2 < truncate_px**2)), len(x1))


def epipolar_support(
    T_prev_cur: np.ndarray, uv_prev: np.ndarray, uv_cur: np.ndarray, intrinsics: Intrinsics
) -> float | None:
    """Share of corners that a motion explains as well as ``planar_turn`` counts its own support: their Sampson
    distance to the epipolar lines of ``T_prev_cur`` within the same truncation (``TRUNCATE_PX``,
    ``TRUNCATE_DEG``).

    Args:
        T_prev_cur: (4, 4) the current camera in the previous one (any motion; its translation's length does not
            matter, its direction does).
        uv_prev, uv_cur: (N, 2) pixels of the same corners in the previous and the current image.
        intrinsics: pinhole intrinsics of both images.

    Returns:
        The share in [0, 1], or None with fewer than ``MIN_CORNERS`` corners or a motion without translation
        (no epipolar geometry).
    """
    uv_prev = np.asarray(uv_prev, dtype=np.float64).reshape(-1, 2)
    uv_cur = np.asarray(uv_cur, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(T_prev_cur, dtype=np.float64)[:3, 3]
    norm = float(np.linalg.norm(t))
    if len(uv_prev) < MIN_CORNERS or uv_cur.shape != uv_prev.shape or not norm > 1e-9:
        return None
    c = t / norm
    skew = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    E = np.asarray(T_prev_cur, dtype=np.float64)[:3, :3].T @ skew  # x_cur^T E x_prev = 0
    x1, x2 = _rays(uv_prev, intrinsics), _rays(uv_cur, intrinsics)
    Ex1, Etx2 = x1 @ E.T, x2 @ E
    num = np.einsum("ni,ni->n", x2, Ex1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    fx = float(intrinsics.fx)
    d2 = num**2 / np.maximum(den, 1e-18) * fx**2
    return float(np.mean(d2 < _truncate_px(fx) ** 2))


def _truncate_px(fx: float) -> float:
    """A corner's Sampson distance counts up to this many pixels (``TRUNCATE_PX``, ``TRUNCATE_DEG``)."""
    return max(TRUNCATE_PX, fx * np.tan(np.radians(TRUNCATE_DEG)))


def _rays(uv: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(N, 3) normalized image rays (x, y, 1) of (N, 2) pixels."""
    return np.column_stack([
        (uv[:, 0] - intrinsics.cx) / intrinsics.fx, (uv[:, 1] - intrinsics.cy) / intrinsics.fy, np.ones(len(uv))
    ])  # fmt: skip


def _sampson_px2(yaw_rad: np.ndarray, x1: np.ndarray, x2: np.ndarray, fx: float) -> np.ndarray:
    """(G, N) squared Sampson distances, pixels², of the corners under each turn.

    The essential matrix (``x_cur^T E x_prev = 0``) of a turn θ under circular motion (the current camera
    rotated by ``R_y(θ)`` in the previous one, its centre along ``(sin θ/2, 0, cos θ/2)``) is
    ``[[0, c, 0], [-c, 0, s], [0, s, 0]]`` with ``c, s = cos, sin(θ/2)``, so the epipolar residual of rays
    (a1, b1, 1) and (a2, b2, 1) is ``c (a2 b1 - a1 b2) + s (b1 + b2)``: written out, the (G, N) grid costs
    a few products instead of 3x3 matrix products per pair (the tests check it against the matrices).
    """
    half = 0.5 * np.asarray(yaw_rad, dtype=np.float64).reshape(-1, 1)
    c, s = np.cos(half), np.sin(half)
    a1, b1, a2, b2 = x1[:, 0], x1[:, 1], x2[:, 0], x2[:, 1]
    num = c * (a2 * b1 - a1 * b2) + s * (b1 + b2)
    den = c**2 * (b1**2 + b2**2) + (s - c * a1) ** 2 + (s + c * a2) ** 2
    return num**2 / np.maximum(den, 1e-18) * fx**2


def _cost(yaw_rad: np.ndarray, x1: np.ndarray, x2: np.ndarray, fx: float, truncate_px: float) -> np.ndarray:
    """(G,) truncated Sampson cost of each turn."""
    return np.minimum(_sampson_px2(yaw_rad, x1, x2, fx), truncate_px**2).sum(axis=1)
