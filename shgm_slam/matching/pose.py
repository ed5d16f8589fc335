"""Pose estimation from correspondences: the weighted least squares of Eq. 2 and inlier re-selection.

Eq. 2 minimises ``sum_k W_k |q_k - R p_k - t|^2`` with p_k in B's frame and q_k in A's frame, so the
result is ``T_a_b``. Its closed form is the weighted Kabsch/Umeyama solution
(``geometry.se3.kabsch``), or the 4-DoF yaw-only version for gravity-aligned ground robots.

Weights (Eq. 2 "related to the objects' size"): ``W_k = sqrt(size_a * size_b)`` (geometric mean of the
two observations of the object), divided by the median and clipped to [0.1, 10] so that one huge
object (a building seen in 10^5 pixels, whose centroid is also the least precise) cannot dominate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.arrays import first_indices
from shgm_slam.geometry.se3 import kabsch, kabsch_yaw

WEIGHT_CLIP = (0.1, 10.0)
"""Range of the median-normalised Eq. 2 weights."""

DEFAULT_UP = np.array([0.0, -1.0, 0.0])
"""Vertical axis of a world frame that is a KITTI camera frame (y points down)."""


@dataclass(frozen=True)
class Alignment:
    """A rigid alignment of B onto A with the candidates it explains.

    Attributes:
        T_a_b: (4, 4) float64 maps points of B's frame into A's frame.
        inliers: (K,) bool mask over the candidates: one-to-one correspondences within the threshold.
        rmse_m: root mean square residual of the inliers, metres (inf when there are none).
        support: evidence of the outlier-rejection stage for this hypothesis (RANSAC inlier count or
            clique size); 0 when not set.
        rival_support: the same evidence for the best hypothesis among the candidates this one does
            not explain (an ambiguity / chance level); 0 when not computed.
        inlier_support: refined one-to-one inlier count of this hypothesis among all candidates (RANSAC:
            equal to ``support``); 0 when not computed.
        rival_inlier_support: refined inlier count of the rival hypothesis among the candidates this one
            does not explain; 0 when not computed.
    """

    T_a_b: np.ndarray
    inliers: np.ndarray
    rmse_m: float
    support: int = 0
    rival_support: int = 0
    inlier_support: int = 0
    rival_inlier_support: int = 0

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


def correspondence_weights(sizes_a: np.ndarray, sizes_b: np.ndarray) -> np.ndarray:
    """(K,) Eq. 2 weights from the (K,) sizes of the matched objects in A and B (see module docstring)."""
    w = np.sqrt(np.maximum(sizes_a, 0.0) * np.maximum(sizes_b, 0.0))
    if w.size == 0:
        return w
    median = _median(w)
    if not median > 0:
        return np.ones_like(w)
    return np.clip(w / median, *WEIGHT_CLIP)


def padded_correspondence_weights(sizes_a: np.ndarray, sizes_b: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(B, M) ``correspondence_weights`` of B padded rows at once: row i of the (B, M) sizes holds its
    correspondences in its first ``lengths[i]`` entries; their weights are those of
    ``correspondence_weights`` on them (the same arithmetic, so the same bits), the padding gets 0."""
    valid = np.arange(sizes_a.shape[1])[None, :] < lengths[:, None]
    w = np.sqrt(np.maximum(sizes_a, 0.0) * np.maximum(sizes_b, 0.0))
    s = np.sort(np.where(valid, w, np.inf), axis=1)  # the padding sorts last
    rows, half = np.arange(s.shape[0]), np.minimum(lengths // 2, max(s.shape[1] - 1, 0))
    upper, lower = s[rows, half], s[rows, np.maximum(half - 1, 0)]
    median = np.where(lengths % 2 == 1, upper, (lower + upper) / 2.0)
    ok = (median > 0)[:, None]
    scaled = np.divide(w, median[:, None], out=np.ones_like(w), where=ok)  # no median: uniform
    return np.where(valid, np.clip(scaled, *WEIGHT_CLIP), 0.0)


def _median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array of finite values (the same arithmetic: the middle value, or
    the mean of the two middle values), without its overhead."""
    s = np.sort(values)
    half = s.shape[0] // 2
    return float(s[half]) if s.shape[0] % 2 else float((s[half - 1] + s[half]) / 2.0)


def fit_pose(
    points_b: np.ndarray,
    points_a: np.ndarray,
    weights: np.ndarray | None = None,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
) -> np.ndarray:
    """Eq. 2 closed form: (4, 4) ``T_a_b`` from (K, 3) or batched (B, K, 3) correspondences.

    ``gravity_aligned`` restricts the rotation to a yaw about ``up`` (3,), shared by both frames
    (default ``DEFAULT_UP`` = -y of the KITTI camera frame).
    """
    if gravity_aligned:
        return kabsch_yaw(points_b, points_a, weights, DEFAULT_UP if up is None else up)
    return kabsch(points_b, points_a, weights)


def residuals_m(T_a_b: np.ndarray, points_b: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """(K,) distances |q_k - (R p_k + t)| in metres of (K, 3) correspondences under one ``T_a_b``."""
    mapped = points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    return np.linalg.norm(points_a - mapped, axis=1)


def one_to_one(rows_a: np.ndarray, rows_b: np.ndarray, residuals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Keep, among ``mask``, only the lowest-residual candidate of every node of A and of B.

    Returns:
        (K,) bool mask in which each row of A and each row of B appears at most once.
    """
    idx = np.flatnonzero(mask)
    idx = idx[np.argsort(residuals[idx], kind="stable")]
    idx = idx[first_indices(rows_a[idx])]
    idx = idx[np.argsort(residuals[idx], kind="stable")]
    idx = idx[first_indices(rows_b[idx])]
    out = np.zeros(mask.shape[0], dtype=bool)
    out[idx] = True
    return out


def refine_alignment(
    T_a_b: np.ndarray,
    points_b: np.ndarray,
    points_a: np.ndarray,
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    weights: np.ndarray | None,
    threshold_m: float,
    iterations: int,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
) -> Alignment:
    """Alternate inlier selection (residual < threshold, one-to-one) and the Eq. 2 fit.

    Args:
        T_a_b: (4, 4) initial transform (RANSAC hypothesis or clique fit).
        points_b, points_a: (K, 3) candidate correspondences (B frame, A frame).
        rows_a, rows_b: (K,) node rows of the candidates (for the one-to-one constraint).
        weights: (K,) Eq. 2 weights or None (uniform).
        threshold_m: inlier distance.
        iterations: maximum number of refits (stops early when the inlier set is stable).
    """
    w = np.ones(points_b.shape[0]) if weights is None else weights
    T = np.asarray(T_a_b, dtype=np.float64)
    res = residuals_m(T, points_b, points_a)
    inliers = one_to_one(rows_a, rows_b, res, res < threshold_m)
    for _ in range(iterations):
        if inliers.sum() < 3:
            break
        T = fit_pose(points_b[inliers], points_a[inliers], w[inliers], gravity_aligned, up)
        res = residuals_m(T, points_b, points_a)
        updated = one_to_one(rows_a, rows_b, res, res < threshold_m)
        if np.array_equal(updated, inliers):
            break
        inliers = updated
    rmse = float(np.sqrt(np.mean(res[inliers] ** 2))) if inliers.any() else float("inf")
    return Alignment(T, inliers, rmse)


def spread_m(points: np.ndarray, gravity_aligned: bool = False, up: np.ndarray | None = None) -> float:
    """How well (K, 3) points constrain a rigid fit, metres.

    6-DoF: the extent of the points along their second principal axis (collinear points leave the
    rotation about their line free). 4-DoF: the extent of their horizontal projection along its first
    principal axis (points stacked on one vertical line leave the yaw free).
    """
    if points.shape[0] < 2:
        return 0.0
    centered = points - points.mean(axis=0)
    axis = 1
    if gravity_aligned:
        u = DEFAULT_UP if up is None else np.asarray(up, dtype=np.float64)
        u = u / np.linalg.norm(u)
        centered = centered - np.outer(centered @ u, u)
        axis = 0
    _, _, Vt = np.linalg.svd(centered, full_matrices=False)
    if Vt.shape[0] <= axis:
        return 0.0
    proj = centered @ Vt[axis]
    return float(proj.max() - proj.min())
