"""GTSAM building blocks of the pose graph: numpy poses as ``gtsam.Pose3``, sigma and information checks,
the noise models of closures, odometry steps, the prior and the attitude factors (robust kernels included),
and iSAM2's parameters (relinearization thresholds). Pure functions of their arguments.
"""

from __future__ import annotations

import gtsam
import numpy as np

from shgm_slam.backend.keys import ROBOT_LETTERS
from shgm_slam.backend.records import Factorization
from shgm_slam.config import RobustKernel
from shgm_slam.errors import BackendError

PRIOR_SIGMA = 1e-3
"""Sigma (rad and m) of the prior fixing robot 0's first keyframe: the gauge of the shared frame."""

RELINEARIZE_ROT_RAD = 1e-3
"""iSAM2 relinearizes a keyframe whose pending rotation update exceeds this, radians. The attitude
factors' measured sigmas are 1-2e-3 rad (``attitude``): a rotation left up to gtsam's default of 0.1 rad
off its linearization point misplaces the keyframes it holds by that angle times their distance, and
iSAM2's estimate oscillated: in KITTI 00's last kilometre, translations of hundreds of keyframes flipped
by 0.2-0.5 m between successive updates, and updates relinearized up to 1400 of 1570 keyframes (with
this threshold a tenth of the updates there relinearize more than 65 keyframes; before, more than 458). Chosen
on kitti-paths 05 + 06 (world seed 1; docs/benchmarks.md, "sixth" session of 2026-12-02): the live
estimate's largest gap to the converged solution 0.06 m instead of 0.22 m, at the same cost."""

RELINEARIZE_TRANS_M = 0.1
"""iSAM2 relinearizes a keyframe whose pending translation update exceeds this, metres (gtsam's default).
On the same tuning run 0.2 and 0.5 left the live estimate up to 0.18 and 0.56 m off the converged one
(0.5 was a third faster in the last 200 keyframes)."""

KERNEL_WIDTH = {RobustKernel.HUBER: 1.345, RobustKernel.CAUCHY: 1.0, RobustKernel.TUKEY: 4.685}
"""Default width of each robust kernel, in sigmas."""

_KERNELS = {
    RobustKernel.HUBER: lambda k: gtsam.noiseModel.mEstimator.Huber.Create(k),
    RobustKernel.CAUCHY: lambda k: gtsam.noiseModel.mEstimator.Cauchy.Create(k),
    RobustKernel.TUKEY: lambda k: gtsam.noiseModel.mEstimator.Tukey.Create(k),
}


def relinearize_thresholds(rot_rad: float, trans_m: float) -> gtsam.ISAM2ThresholdMap:
    """iSAM2's per-variable-kind relinearization thresholds: every robot letter's Pose3 (tangent order:
    rotation, then translation) gets ``rot_rad`` on its rotation axes and ``trans_m`` on its translation."""
    thresholds = gtsam.ISAM2ThresholdMap()
    per_axis = np.array([rot_rad] * 3 + [trans_m] * 3)
    for letter in ROBOT_LETTERS:
        thresholds.insert((letter, per_axis))
    return thresholds


def pose3(T: np.ndarray) -> gtsam.Pose3:
    """numpy (4, 4) -> gtsam.Pose3 with the rotation projected onto SO(3) (REFERENCE.md §3)."""
    return gtsam.Pose3(gtsam.Rot3.ClosestTo(T[:3, :3]), T[:3, 3])


def check_pose(T: np.ndarray, what: str) -> np.ndarray:
    """``T`` as a float64 (4, 4) array; ``BackendError`` naming ``what`` when it is not a finite (4, 4) pose."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise BackendError(f"{what} must be a finite (4, 4) pose, got shape {T.shape}")
    return T


def sigmas6(rot_trans: tuple[float, float]) -> np.ndarray:
    """(6,) Pose3 tangent-order sigmas from (rotation rad, translation m); ``BackendError`` unless both > 0."""
    rot, trans = (float(v) for v in rot_trans)
    if rot <= 0 or trans <= 0:
        raise BackendError(f"noise sigmas must be positive, got rotation {rot} rad, translation {trans} m")
    return np.r_[[rot] * 3, [trans] * 3]  # Pose3 tangent order: [rx ry rz tx ty tz]


def isam2_params(factorization: Factorization, relinearize_threshold: tuple[float, float]) -> gtsam.ISAM2Params:
    """iSAM2's parameters: ``factorization``, relinearization thresholds (rotation rad, translation m;
    ``relinearize_thresholds``) checked at every update, on the touched cliques only (a flat cost per update)."""
    p = gtsam.ISAM2Params()
    p.setFactorization(factorization.value)
    p.setRelinearizeThreshold(relinearize_thresholds(*relinearize_threshold))
    p.relinearizeSkip = 1
    p.enablePartialRelinearizationCheck = True  # check the touched cliques only: flat cost per update
    return p


def prior_noise() -> gtsam.noiseModel.Base:
    """Noise of the prior fixing robot 0's first keyframe (``PRIOR_SIGMA`` on every axis)."""
    return gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)


def odometry_noise(sigmas: np.ndarray) -> gtsam.noiseModel.Base:
    """Noise of one odometry step with (6,) [rot rad x3, trans m x3] ``sigmas``."""
    return gtsam.noiseModel.Diagonal.Sigmas(sigmas)


def attitude_noise(sigma_rad: float) -> gtsam.noiseModel.Base:
    """Noise of an attitude factor: the robot's measured normal sigma (rad, on the 2-D error of a unit
    vector) under a Huber kernel of its default width."""
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(KERNEL_WIDTH[RobustKernel.HUBER]),
        gtsam.noiseModel.Isotropic.Sigma(2, sigma_rad),
    )


def closure_noise_model(
    information: np.ndarray | None,
    closure_sigmas: np.ndarray,
    robust_kernel: RobustKernel,
    kernel_width: float | None,
) -> tuple[gtsam.noiseModel.Base, np.ndarray]:
    """A closure's noise model and its (6, 6) information matrix (gtsam order [rot, trans]).

    Args:
        information: the closure's (6, 6) information, or None for the configured sigmas.
        closure_sigmas: (6,) [rot rad x3, trans m x3] configured closure sigmas (``sigmas6``).
        robust_kernel: M-estimator wrapped around the Gaussian (``RobustKernel.NONE``: none).
        kernel_width: the kernel's width in sigmas; None (or 0) for its default (``KERNEL_WIDTH``).

    Raises:
        BackendError: ``information`` is not a finite, positive definite (6, 6) matrix.
    """
    if information is None:
        base = gtsam.noiseModel.Diagonal.Sigmas(closure_sigmas)
        info = np.diag(1.0 / closure_sigmas**2)
    else:
        info = np.asarray(information, dtype=np.float64)
        if info.shape != (6, 6) or not np.isfinite(info).all() or np.linalg.eigvalsh(info).min() <= 0:
            raise BackendError("closure information must be a finite, positive definite (6, 6) matrix")
        base = gtsam.noiseModel.Gaussian.Information(info)
    if robust_kernel is RobustKernel.NONE:
        return base, info
    width = kernel_width or KERNEL_WIDTH[robust_kernel]
    return gtsam.noiseModel.Robust.Create(_KERNELS[robust_kernel](width), base), info


def inverse_information(information: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Information of the flipped measurement ``T_b_a`` given that of ``T_a_b = T_b_a⁻¹``.

    With right perturbations, ``T_a_b·Exp(ξ)`` inverts to ``T_b_a·Exp(-Ad(T_a_b)·ξ)``, so the
    information becomes ``Ad(T_b_a)ᵀ · I · Ad(T_b_a)`` (gtsam [rot, trans] order).
    """
    Ad = pose3(T_b_a).AdjointMap()
    return Ad.T @ np.asarray(information, dtype=np.float64) @ Ad
