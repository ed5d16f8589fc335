"""Attitude from the ground: how far a keyframe's measured "up" can be trusted, and the shared frame's up.

A front end fits a plane to the road, sidewalk and terrain under each keyframe (``geometry.ground``); its
normal, rotated by the keyframe's orientation, is that keyframe's measurement of where "up" is. On level
ground every keyframe should see the same up, so a unary factor per keyframe (gtsam's
``AttitudeFactorPose3``: the camera-frame normal, rotated by the keyframe's estimated orientation, should
point along the shared frame's up) stops roll and pitch from drifting with the odometry, and with them the
height error that pitch drift integrates over kilometres.

The factor's sigma is measured per agent, not assumed: between two successive measured keyframes the
odometry's rotation is accurate to far better than the plane fit, so the angle between their normals
(both in the odometry frame) is the difference of two independent measurement errors. With isotropic
Gaussian tilt errors of sigma per axis that angle is Rayleigh-distributed with scale ``sigma·√2`` and
median ``sigma·√2·√(2 ln 2)``, so the median angle gives a robust sigma (``normal_sigma_rad``).
What the scatter of successive keyframes cannot see is a slope shared by both: the factor assumes level
ground, and the robust (Huber) kernel only bounds the pull of a keyframe on a ramp.
"""

from __future__ import annotations

import numpy as np

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
"""Median of a Rayleigh distribution of unit scale."""

MIN_SIGMA_RAD = 1e-5
"""Floor of a measured sigma (a numerical guard only: exact renders measure ~2e-4 rad)."""


def normal_sigma_rad(up_odom: np.ndarray) -> float | None:
    """Per-axis sigma (rad) of one agent's ground-normal measurements, from successive keyframes.

    Args:
        up_odom: (K, 3) each keyframe's unit ground normal in the agent's odometry frame, in keyframe
            order; NaN rows for keyframes without a ground fit (pairs skip over them).

    Returns:
        ``median(angle between successive normals) / (√2 · √(2 ln 2))`` radians (at least
        ``MIN_SIGMA_RAD``), or None with fewer than two measured keyframes.
    """
    up = np.asarray(up_odom, dtype=np.float64).reshape(-1, 3)
    up = up[np.isfinite(up).all(axis=1)]
    if up.shape[0] < 2:
        return None
    cos = np.clip(np.sum(up[1:] * up[:-1], axis=1), -1.0, 1.0)
    angles = np.arccos(cos)
    return max(float(np.median(angles)) / (np.sqrt(2.0) * RAYLEIGH_MEDIAN), MIN_SIGMA_RAD)


def up_at_start(up_shared: np.ndarray, kf_index: np.ndarray) -> np.ndarray:
    """(3,) unit "up" at keyframe 0 from a robot's first measured normals, rotated into the shared frame
    by its (drifting) odometry: the intercept of a least-squares line through them over the keyframe
    index, so the odometry's drift (growing with the index) does not tilt it, unlike their mean.

    Args:
        up_shared: (K, 3) unit normals in the shared frame, K >= 2.
        kf_index: (K,) their keyframe indices (distinct).

    Raises:
        ValueError: fewer than two normals, or an intercept of (near) zero length.
    """
    up = np.asarray(up_shared, dtype=np.float64).reshape(-1, 3)
    k = np.asarray(kf_index, dtype=np.float64).reshape(-1)
    if up.shape[0] < 2 or k.shape != (up.shape[0],) or np.ptp(k) == 0:
        raise ValueError("the up at keyframe 0 needs at least two normals at distinct keyframes")
    A = np.stack([np.ones_like(k), k], axis=1)
    coef, *_ = np.linalg.lstsq(A, up, rcond=None)
    norm = float(np.linalg.norm(coef[0]))
    if not norm > 1e-9:
        raise ValueError("the normals give no up direction")
    return coef[0] / norm
