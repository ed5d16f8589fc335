"""A robot's odometry rotation drift, measured from its own loop closures.

The pose graph weighs every odometry step with a rotation sigma that grows with the step's length
(``floor + rate · length``, per axis, rad). The rate is a prior for the kind of depth a robot's odometry
runs on (``config.MEASURED_DEPTH_DRIFT``): tight where KISS-ICP on measured depth turns little (a tight
rate keeps closures from bending a well-measured trajectory), but a robot whose odometry drifts more than
that in heading — a systematic yaw drift of a few degrees per 100 m — would keep its bent loop: a tight
odometry outweighs the closure that should straighten it.

A loop closure measures that drift. Closing keyframe ``j`` to an older keyframe ``i`` of the same robot,
the rotation the closure measures and the one the odometry integrated between the two differ by
``δ = Log(R_odomᵀ · R_closure)`` (3,). Under the random-walk model each of its three components has the
variance ``Σ_k (floor + rate · L_k)²`` over the steps ``k = i+1 .. j`` of lengths ``L_k``, so one closure's
maximum-likelihood rate solves ``|δ|² / 3 = Σ_k (floor + rate · L_k)²`` (a quadratic; 0 when the floor
alone explains ``δ``). The closure's own rotation error is left out: the pose graph's closure sigma
(0.1 rad) is set for robustness, not measured, and subtracting it would leave a loop ~10 deg off
unmeasured; closures of the files tuning worlds err by 0.5-1.3 deg (std per robot pair, synthia-like's
opposite-facing views 1.3-7). A poor closure on a short loop can raise a rate on its own (7 deg over 50 m
measures 0.0066 rad/m); the median over the robot's loop closures bounds that, and a loop closure has
passed the odometry check and the loops' consistency vote (``consistency.py``) before it counts.
A robot's measured rate is the median over its accepted loop closures (closures of one revisit share
most of their loop and would outvote a lone one in a mean).

The pose graph uses ``max(prior, measured)``, rounded up to the prior times a power of ``LEVEL_STEP``
(``drift_level``): the graph is rebuilt with new odometry sigmas only when the measured rate crosses a
level, and a graph restored from a snapshot reaches the same level from the same closures. The prior's
rate is never lowered (a loop tells too little to tighten it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

LEVEL_STEP = math.sqrt(2.0)
"""Ratio between successive drift levels (a rebuild per doubling of the variance at most)."""

UNIT_RATE_RAD_PER_M = 1e-4
"""Level unit where the prior rate is 0 (every step alike): levels are this times a power of
``LEVEL_STEP``."""


def loop_rotation_error_rad(T_odom_i: np.ndarray, T_odom_j: np.ndarray, T_i_j: np.ndarray) -> np.ndarray:
    """(3,) rotation vector between the odometry's and a loop closure's relative rotation, radians.

    Args:
        T_odom_i, T_odom_j: (4, 4) the two keyframes' poses in the robot's odometry frame.
        T_i_j: (4, 4) the closure: keyframe j's camera pose in keyframe i's camera frame.
    """
    R_odom = T_odom_i[:3, :3].T @ T_odom_j[:3, :3]
    return Rotation.from_matrix(R_odom.T @ T_i_j[:3, :3]).as_rotvec()


def closure_rate(rot_error_rad: np.ndarray, step_lengths_m: np.ndarray, floor_rad: float) -> float:
    """Maximum-likelihood rotation drift rate (rad per metre, >= 0) of one loop closure (module docstring).

    Args:
        rot_error_rad: (3,) ``loop_rotation_error_rad`` of the closure.
        step_lengths_m: (K,) lengths of the odometry steps inside the loop, metres.
        floor_rad: the step sigma at zero length, rad.
    """
    lengths = np.asarray(step_lengths_m, dtype=np.float64)
    target = float(np.dot(rot_error_rad, rot_error_rad)) / 3.0
    a, b = float(np.dot(lengths, lengths)), 2.0 * floor_rad * float(lengths.sum())
    c = lengths.size * floor_rad**2 - target
    if c >= 0.0 or a <= 0.0:  # the floor already explains the error
        return 0.0
    return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def measured_rate(rates: Sequence[float]) -> float:
    """A robot's measured rate from its closures' rates (the median; 0 without closures)."""
    return float(np.median(rates)) if len(rates) else 0.0


def drift_level(measured_rad_per_m: float, prior_rad_per_m: float) -> float:
    """The rate the pose graph uses: the prior, or the measured rate rounded up to the prior (or
    ``UNIT_RATE_RAD_PER_M`` when the prior is 0) times a power of ``LEVEL_STEP``, whichever is larger."""
    if measured_rad_per_m <= prior_rad_per_m:
        return prior_rad_per_m
    unit = prior_rad_per_m if prior_rad_per_m > 0 else UNIT_RATE_RAD_PER_M
    power = math.ceil(math.log(measured_rad_per_m / unit) / math.log(LEVEL_STEP) - 1e-9)
    return unit * LEVEL_STEP ** max(power, 0)
