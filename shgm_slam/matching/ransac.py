"""The paper's ICP-RANSAC outlier rejection (Alg. 2), with all hypotheses evaluated in batches.

All iterations' minimal samples (4 correspondences) are drawn at once, fitted with the batched
closed-form Eq. 2 (Kabsch), and scored against every candidate at once: a candidate is an inlier of
a hypothesis when its residual is below the threshold (authors: 10 m). The hypothesis with the most
inliers wins (ties: lower truncated residual sum, as MSAC). Its inliers are then refitted with the
weighted Eq. 2 and re-selected ``refine_iterations`` times (``pose.refine_alignment``).
"""

from __future__ import annotations

import numpy as np

from shgm_slam.matching.pose import Alignment, fit_pose, refine_alignment

SAMPLE_SIZE = 4
"""Correspondences per RANSAC hypothesis (Alg. 2)."""

_BATCH = 256
"""Hypotheses scored per chunk (bounds the (batch, K, 3) temporary)."""


def _valid_samples(samples: np.ndarray, rows_a: np.ndarray, rows_b: np.ndarray) -> np.ndarray:
    """(H,) True for samples whose correspondences use distinct nodes on both sides."""
    ok = np.ones(samples.shape[0], dtype=bool)
    for rows in (rows_a, rows_b):
        r = np.sort(rows[samples], axis=1)
        ok &= np.all(r[:, 1:] != r[:, :-1], axis=1)
    return ok


def score_hypotheses(
    T_a_b: np.ndarray, points_b: np.ndarray, points_a: np.ndarray, threshold_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Inlier counts (H,) int64 and truncated residual sums (H,) of (H, 4, 4) hypotheses over (K, 3) pairs."""
    counts = np.empty(T_a_b.shape[0], dtype=np.int64)
    costs = np.empty(T_a_b.shape[0])
    for start in range(0, T_a_b.shape[0], _BATCH):
        T = T_a_b[start : start + _BATCH]
        mapped = np.matmul(points_b[None], np.swapaxes(T[:, :3, :3], 1, 2)) + T[:, None, :3, 3]
        d = np.linalg.norm(mapped - points_a[None], axis=2)
        counts[start : start + _BATCH] = (d < threshold_m).sum(axis=1)
        costs[start : start + _BATCH] = np.minimum(d, threshold_m).sum(axis=1)
    return counts, costs


def ransac_alignment(
    points_b: np.ndarray,
    points_a: np.ndarray,
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    iterations: int = 1000,
    inlier_threshold_m: float = 10.0,
    refine_iterations: int = 3,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
    seed: int = 0,
) -> Alignment | None:
    """Alg. 2 over K candidate correspondences; deterministic for a given ``seed``.

    Args:
        points_b: (K, 3) candidate positions in B's frame (p_k).
        points_a: (K, 3) candidate positions in A's frame (q_k).
        rows_a, rows_b: (K,) node rows of the candidates (samples reusing a node are skipped).
        weights: (K,) Eq. 2 weights for the refinement (the minimal fits are unweighted).
        iterations: number of hypotheses N_i.
        inlier_threshold_m: T_R of Alg. 2.
        refine_iterations: weighted refits of the winning inlier set.

    Returns:
        The refined alignment, or None when there are fewer than 3 candidates or no valid sample.
    """
    k = points_b.shape[0]
    if k < 3:
        return None
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, k, size=(iterations, min(SAMPLE_SIZE, k)))
    samples = samples[_valid_samples(samples, rows_a, rows_b)]
    if samples.shape[0] == 0:
        return None
    hypotheses = fit_pose(points_b[samples], points_a[samples], None, gravity_aligned, up)
    counts, costs = score_hypotheses(hypotheses, points_b, points_a, inlier_threshold_m)
    best = np.lexsort((costs, -counts))[0]
    return refine_alignment(
        hypotheses[best], points_b, points_a, rows_a, rows_b, weights,
        inlier_threshold_m, refine_iterations, gravity_aligned, up,
    )  # fmt: skip
