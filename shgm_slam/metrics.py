"""Trajectory metrics: absolute (ATE) and relative (RPE) pose errors through evo, trajectory length.

Both error functions take pose stacks ``(N, 4, 4)`` of ``T_world_cam`` (ground truth and estimate,
associated one-to-one by index) and return an ``ErrorStats`` that reads like evo's stats dict
(``stats["rmse"]``) and like an object (``stats.rmse``). Trajectories too short to evaluate give NaN
statistics with a ``reason`` instead of an exception; malformed input (shapes, counts) raises
``DataError``.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from enum import Enum
from itertools import pairwise

import numpy as np

from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import kabsch

MIN_POSES = 3
"""Fewer poses than this cannot be aligned or evaluated meaningfully: statistics are NaN."""


class AlignMode(str, Enum):
    """How the estimate is aligned to the ground truth before the absolute error is taken."""

    NONE = "none"  # compare in the given frames
    SE3 = "se3"  # rigid Umeyama alignment (evo -a)
    SIM3 = "sim3"  # rigid + scale (evo -as), for scale-ambiguous estimates


class RelationKind(str, Enum):
    """Which part of the relative pose error RPE measures."""

    TRANSLATION_M = "translation_m"
    ROTATION_DEG = "rotation_deg"


@dataclass(frozen=True)
class ErrorStats:
    """Error statistics of one trajectory comparison (metres, or degrees for rotation RPE).

    ``reason`` is empty when the statistics are valid and explains the NaN values otherwise.
    """

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    num_poses: int
    reason: str = ""

    @property
    def valid(self) -> bool:
        return not self.reason

    def __getitem__(self, name: str) -> float | int | str:
        return getattr(self, name)

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)

    @staticmethod
    def invalid(num_poses: int, reason: str) -> ErrorStats:
        nan = float("nan")
        return ErrorStats(nan, nan, nan, nan, nan, num_poses, reason)


def _enum(kind: type[Enum], value: Enum | str):  # -> the enum member
    """Accept an enum member or its string value (``"se3"``); DataError naming the choices otherwise."""
    try:
        return kind(value)
    except ValueError:
        choices = ", ".join(m.value for m in kind)
        raise DataError(f"metrics: unknown {kind.__name__} {value!r}; choose one of {choices}") from None


def _check_pair(poses_gt: np.ndarray, poses_est: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Validate shapes; returns float64 copies and a reason string when they cannot be evaluated."""
    gt = np.asarray(poses_gt, dtype=np.float64)
    est = np.asarray(poses_est, dtype=np.float64)
    for name, P in (("poses_gt", gt), ("poses_est", est)):
        if P.ndim != 3 or P.shape[1:] != (4, 4):
            raise DataError(f"metrics: {name} must be an (N, 4, 4) pose stack, got shape {P.shape}")
    if gt.shape[0] != est.shape[0]:
        raise DataError(
            f"metrics: {gt.shape[0]} ground-truth poses but {est.shape[0]} estimated poses; "
            "associate the trajectories (same frames, same order) before evaluating"
        )
    reason = ""
    if gt.shape[0] < MIN_POSES:
        reason = f"only {gt.shape[0]} poses (need at least {MIN_POSES})"
    elif not (np.isfinite(gt).all() and np.isfinite(est).all()):
        reason = "poses contain NaN or inf"
    return gt, est, reason


def _path(poses: np.ndarray):  # -> evo PosePath3D
    from evo.core.trajectory import PosePath3D

    return PosePath3D(poses_se3=list(poses))


def _stats(errors: np.ndarray, num_poses: int) -> ErrorStats:
    e = np.asarray(errors, dtype=np.float64)
    return ErrorStats(
        rmse=float(np.sqrt(np.mean(e**2))),
        mean=float(np.mean(e)),
        median=float(np.median(e)),
        std=float(np.std(e)),
        max=float(np.max(e)),
        num_poses=num_poses,
    )


def _align_degenerate(gt: np.ndarray, est: np.ndarray, *, with_scale: bool) -> np.ndarray | None:
    """Umeyama fit of (N, 4, 4) ``est`` onto ``gt`` positions that also works for collinear positions.

    Returns the aligned (N, 4, 4) estimate, or None when the estimated positions have no spread and a
    scale is requested (or are all identical for the rotation part).
    """
    p, q = est[:, :3, 3], gt[:, :3, 3]
    pc, qc = p - p.mean(axis=0), q - q.mean(axis=0)
    var_p = float((pc**2).sum())
    if var_p < 1e-18 and with_scale:
        return None
    T = kabsch(p, q)
    R = T[:3, :3]
    s = float(np.einsum("ij,ij->", qc, pc @ R.T) / var_p) if with_scale else 1.0
    out = est.copy()
    out[:, :3, :3] = R @ est[:, :3, :3]
    out[:, :3, 3] = s * (p @ R.T) + (q.mean(axis=0) - s * R @ p.mean(axis=0))
    return out


def ate(poses_gt: np.ndarray, poses_est: np.ndarray, *, align: AlignMode | str = AlignMode.SE3) -> ErrorStats:
    """Absolute trajectory error of the translation part (evo APE), metres.

    Args:
        poses_gt: (N, 4, 4) ground-truth ``T_world_cam``.
        poses_est: (N, 4, 4) estimated poses of the same frames (any world frame when aligned).
        align: NONE compares in the given frames; SE3/SIM3 first fit the estimate onto the ground
            truth with Umeyama (the estimate is deep-copied, inputs are never modified). The string
            values ("none", "se3", "sim3") are accepted too.

    Returns:
        ``ErrorStats`` of the per-pose position errors; NaN with a reason for < 3 poses, non-finite
        poses, or a degenerate alignment (e.g. all positions identical).
    """
    from evo.core import metrics
    from evo.core.geometry import GeometryException

    align = _enum(AlignMode, align)
    gt, est, reason = _check_pair(poses_gt, poses_est)
    n = gt.shape[0]
    if reason:
        return ErrorStats.invalid(n, reason)
    ref, traj = _path(gt), copy.deepcopy(_path(est))  # evo aligns in place (REFERENCE.md §4)
    if align is not AlignMode.NONE:
        try:
            traj.align(ref, correct_scale=align is AlignMode.SIM3)
        except GeometryException:
            # evo refuses rank-deficient (straight-line) trajectories although the position error is
            # still well defined there: fit with our degenerate-safe weighted Kabsch instead.
            aligned = _align_degenerate(gt, est, with_scale=align is AlignMode.SIM3)
            if aligned is None:
                reason = f"{align.value} alignment impossible: all estimated positions coincide"
                return ErrorStats.invalid(n, reason)
            traj = _path(aligned)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    return _stats(ape.error, n)


def joint_ate(poses_gt: list[np.ndarray], poses_est: list[np.ndarray]) -> tuple[list[ErrorStats], ErrorStats]:
    """ATE of several robots' trajectories under ONE rigid alignment fit to all of them together, metres.

    The fused trajectories of a multi-robot run share one frame whose gauge is the first robot's first pose:
    in that frame every robot also carries the first robot's own drift, and aligning each robot on its own
    hides whether their maps agree. A single SE(3) fit (Umeyama, no scale) of all robots' positions at once
    removes the gauge only: what is left is how consistently the robots were placed relative to each other
    (the fleet's map), as collaborative SLAM evaluations report it.

    Args:
        poses_gt: per robot, (N_i, 4, 4) ground-truth ``T_world_cam`` in one world frame (all robots').
        poses_est: per robot, (N_i, 4, 4) estimated poses of the same frames, all in one frame (the run's
            shared frame).

    Returns:
        Per robot, the ``ErrorStats`` of its position errors after the joint fit, and those of all poses
        together; NaN with a reason when fewer than ``MIN_POSES`` poses in all, non-finite poses or
        positions that all coincide.
    """
    if len(poses_gt) != len(poses_est):
        raise DataError(f"metrics: {len(poses_gt)} ground-truth trajectories but {len(poses_est)} estimated ones")
    pairs = [_check_pair(g, e) for g, e in zip(poses_gt, poses_est, strict=True)]
    sizes = [g.shape[0] for g, _, _ in pairs]
    n = sum(sizes)
    gt = np.concatenate([g for g, _, _ in pairs]) if pairs else np.zeros((0, 4, 4))
    est = np.concatenate([e for _, e, _ in pairs]) if pairs else np.zeros((0, 4, 4))
    reason = "" if np.isfinite(gt).all() and np.isfinite(est).all() else "poses contain NaN or inf"
    if not reason and n < MIN_POSES:
        reason = f"only {n} poses (need at least {MIN_POSES})"
    if not reason and np.ptp(est[:, :3, 3], axis=0).max() == 0.0:
        reason = "joint alignment impossible: all estimated positions coincide"
    if reason:
        return [ErrorStats.invalid(k, reason) for k in sizes], ErrorStats.invalid(n, reason)
    aligned = _align_degenerate(gt, est, with_scale=False)  # one Umeyama fit of every robot's poses at once
    errors = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    bounds = np.cumsum([0, *sizes]).tolist()
    per_robot = [
        _stats(errors[i:j], j - i) if j > i else ErrorStats.invalid(0, "no poses") for i, j in pairwise(bounds)
    ]
    return per_robot, _stats(errors, n)


def rpe(
    poses_gt: np.ndarray,
    poses_est: np.ndarray,
    *,
    delta_frames: int = 1,
    relation: RelationKind | str = RelationKind.TRANSLATION_M,
) -> ErrorStats:
    """Relative pose error between frame pairs ``delta_frames`` apart (evo RPE), metres or degrees.

    RPE is independent of the global frame, so no alignment is done.

    Args:
        poses_gt: (N, 4, 4) ground-truth ``T_world_cam``.
        poses_est: (N, 4, 4) estimated poses of the same frames.
        delta_frames: frame offset of the compared pairs (>= 1).
        relation: translation error (m) or rotation angle error (deg) of the relative motion.

    Returns:
        ``ErrorStats`` over the N - delta_frames pairs; NaN with a reason when there are too few.
    """
    from evo.core import metrics
    from evo.core.units import Unit

    relation = _enum(RelationKind, relation)
    if delta_frames < 1:
        raise DataError(f"metrics: rpe delta_frames must be >= 1, got {delta_frames}")
    gt, est, reason = _check_pair(poses_gt, poses_est)
    n = gt.shape[0]
    if not reason and n - delta_frames < 1:
        reason = f"only {n} poses for delta {delta_frames} frames"
    if reason:
        return ErrorStats.invalid(n, reason)
    kind = (
        metrics.PoseRelation.translation_part
        if relation is RelationKind.TRANSLATION_M
        else metrics.PoseRelation.rotation_angle_deg
    )
    rel = metrics.RPE(kind, delta=delta_frames, delta_unit=Unit.frames, all_pairs=False)
    rel.process_data((_path(gt), _path(est)))
    return _stats(rel.error, n)


def trajectory_length(poses: np.ndarray) -> float:
    """Path length in metres: sum of distances between consecutive positions of (N, 4, 4) poses."""
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise DataError(f"metrics: poses must be an (N, 4, 4) pose stack, got shape {P.shape}")
    if P.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum())


DRIFT_LENGTHS_M = (50.0, 100.0, 150.0, 200.0)
"""Segment lengths of ``drift_percent`` (KITTI uses 100-800 m; our drives are 200-950 m long)."""


def drift_percent(
    poses_gt: np.ndarray, poses_est: np.ndarray, *, lengths_m: tuple[float, ...] = DRIFT_LENGTHS_M, step: int = 5
) -> float:
    """Translational drift in % of the distance driven (KITTI's t_rel): for segments starting every
    ``step`` frames and ``lengths_m`` long (ground-truth path), the translation error of the estimated
    relative motion over the segment divided by its length, averaged over all segments.

    Args:
        poses_gt: (N, 4, 4) ground-truth ``T_world_cam``.
        poses_est: (N, 4, 4) estimated poses of the same frames (any frame: only relative motion counts).

    Returns:
        The mean drift in percent; NaN when the path is shorter than the shortest segment.
    """
    gt, est, reason = _check_pair(poses_gt, poses_est)
    if reason:
        return float("nan")
    dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))]
    errors = []
    for length in lengths_m:
        start = np.arange(0, len(gt), max(1, step))
        end = np.searchsorted(dist, dist[start] + length)
        ok = end < len(gt)
        i, j = start[ok], end[ok]
        if len(i) == 0:
            continue
        rel_gt = np.linalg.inv(gt[i]) @ gt[j]
        rel_est = np.linalg.inv(est[i]) @ est[j]
        err = np.linalg.inv(rel_gt) @ rel_est
        errors.append(np.linalg.norm(err[:, :3, 3], axis=1) / length)
    return 100.0 * float(np.mean(np.concatenate(errors))) if errors else float("nan")
