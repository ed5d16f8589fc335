"""Attitude from the ground: how far a keyframe's measured "up" can be trusted, and the shared frame's up.

A front end fits a plane to the road under each keyframe (``geometry.ground``; to the road, sidewalk and
terrain when little road is in view); its normal, rotated by the keyframe's orientation, is that
keyframe's measurement of where "up" is. On level ground every keyframe should see the same up, so a
unary factor per keyframe (gtsam's ``AttitudeFactorPose3``: the camera-frame normal, rotated by the
keyframe's estimated orientation, should point along the shared frame's up) stops roll and pitch from
drifting with the odometry, and with them the height error that pitch drift integrates over kilometres.

The factor's sigma is measured per agent, not assumed: the angle between two successive measured
keyframes' normals (both in the odometry frame) is the difference of their two errors plus the
odometry's rotation error between them. With isotropic Gaussian tilt errors of sigma per axis that angle
is Rayleigh-distributed with scale ``sigma·√2`` and median ``sigma·√2·√(2 ln 2)``, so the median angle
gives a robust sigma (``normal_sigma_rad``). It is an upper bound: where the normals are better than the
odometry's step (the road of rendered depth: ~1e-5 rad off the truth) it measures the odometry instead
(KISS-ICP at 320x96: 1.5-2e-3 rad); on predicted depth, whose normals err by ~4e-3 rad with errors that
persist over several keyframes, it measures ~2e-3.
What the scatter of successive keyframes cannot see is a slope shared by both: the factor assumes level
ground, and the robust (Huber) kernel only bounds the pull of a keyframe on a ramp.
"""

from __future__ import annotations

import numpy as np

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
"""Median of a Rayleigh distribution of unit scale."""

MIN_SIGMA_RAD = 1e-5
"""Floor of a measured sigma (a numerical guard only; see the module docstring for what is measured)."""


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


def up_at_start(up_shared: np.ndarray, walk_var_rad2: np.ndarray, sigma_rad: float) -> np.ndarray:
    """(3,) unit "up" at keyframe 0 from a robot's first measured normals, rotated into the shared frame
    by its (drifting) odometry.

    Each normal is the up at keyframe 0 plus two errors: the odometry's rotation error accumulated since
    keyframe 0 (a random walk: ``walk_var_rad2`` per axis, growing with the distance driven) and the
    plane fit's own error (``sigma_rad`` per axis, independent between keyframes). Their generalized least
    squares mean (covariance ``sigma² I + min(V_i, V_j)``) weighs each normal by what both errors leave of
    it: exact normals (rendered depth) give keyframe 0's own, noisy ones (predicted depth) are averaged over
    the keyframes before the odometry's drift outweighs their noise. (A line through the normals over the
    keyframe index, before: a drift that is not linear in the index, such as KISS-ICP's first metres,
    tilted it by ~0.1 degrees, which a 400 m drive turns into 0.7 m of height.)

    Args:
        up_shared: (K, 3) unit normals in the shared frame, K >= 1.
        walk_var_rad2: (K,) the odometry's accumulated rotation variance (rad² per axis) at each normal's
            keyframe since keyframe 0, >= 0.
        sigma_rad: per-axis sigma of one normal (``normal_sigma_rad``), > 0.

    Raises:
        ValueError: no normals, mismatched shapes, negative variances, or an estimate of (near) zero
            length.
    """
    up = np.asarray(up_shared, dtype=np.float64).reshape(-1, 3)
    walk = np.asarray(walk_var_rad2, dtype=np.float64).reshape(-1)
    if up.shape[0] < 1 or walk.shape != (up.shape[0],) or not np.isfinite(walk).all() or (walk < 0).any():
        raise ValueError("the up at keyframe 0 needs normals with one non-negative drift variance each")
    if not sigma_rad > 0:
        raise ValueError(f"the normals' sigma must be positive, got {sigma_rad}")
    cov = np.minimum.outer(walk, walk) + sigma_rad**2 * np.eye(len(walk))
    weights = np.linalg.solve(cov, np.ones(len(walk)))
    mean = weights @ up
    norm = float(np.linalg.norm(mean))
    if not norm > 1e-9:
        raise ValueError("the normals give no up direction")
    return mean / norm
