"""The paper's ICP-RANSAC outlier rejection (Alg. 2), with all hypotheses evaluated in batches.

All iterations' minimal samples (4 correspondences) are drawn at once, fitted with the batched
closed-form Eq. 2 (Kabsch), and scored against every candidate at once: a candidate is an inlier of
a hypothesis when its residual is below the threshold (authors: 10 m). The hypothesis with the most
inliers wins (ties: lower truncated residual sum, as MSAC). Its inliers are then refitted with the
weighted Eq. 2 and re-selected ``refine_iterations`` times (``pose.refine_alignment``).

``support`` is the refined winner's one-to-one inlier count; ``rival_support`` the same for the best
hypothesis among the candidates the winner does not explain (residual above twice the threshold),
refined the same way: the chance level, or a competing alignment in an ambiguous scene.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from shgm_slam.matching.pose import Alignment, fit_pose, refine_alignment, residuals_m

SAMPLE_SIZE = 4
"""Correspondences per RANSAC hypothesis (Alg. 2)."""

_BATCH = 256
"""Hypotheses scored per chunk (bounds the (batch, K) squared-residual temporary)."""


def _valid_samples(samples: np.ndarray, rows_a: np.ndarray, rows_b: np.ndarray) -> np.ndarray:
    """(H,) True for samples whose correspondences use distinct nodes on both sides."""
    ok = np.ones(samples.shape[0], dtype=bool)
    for rows in (rows_a, rows_b):
        r = np.sort(rows[samples], axis=1)
        ok &= np.all(r[:, 1:] != r[:, :-1], axis=1)
    return ok


def squared_residuals(T_a_b: np.ndarray, points_b: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """(H, K) squared residuals |q_k - R_h p_k - t_h|^2 of (H, 4, 4) hypotheses over (K, 3) pairs, m^2.

    Expanded as one (H, 17) x (17, K) matrix product (no (H, K, 3) temporary); the points are centred
    first so that the expansion does not lose precision.
    """
    ca, cb = points_a.mean(axis=0), points_b.mean(axis=0)
    q, p = points_a - ca, points_b - cb
    R = T_a_b[:, :3, :3]
    t = T_a_b[:, :3, 3] + np.einsum("hij,j->hi", R, cb) - ca  # translation between the centred frames
    h = T_a_b.shape[0]
    Rt_t = np.einsum("hji,hj->hi", R, t)
    hyp = np.concatenate([R.reshape(h, 9), t, Rt_t, (t * t).sum(1, keepdims=True), np.ones((h, 1))], axis=1)
    pair = np.concatenate(
        [
            -2.0 * (q[:, :, None] * p[:, None, :]).reshape(-1, 9),
            -2.0 * q,
            2.0 * p,
            np.ones((q.shape[0], 1)),
            ((q * q).sum(1) + (p * p).sum(1))[:, None],
        ],
        axis=1,
    )
    d2 = hyp @ pair.T
    return np.maximum(d2, 0.0, out=d2)


def score_hypotheses(
    T_a_b: np.ndarray, points_b: np.ndarray, points_a: np.ndarray, threshold_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 2 scores of (H, 4, 4) hypotheses over (K, 3) correspondences.

    Returns:
        (H, K) bool inlier matrix (residual < threshold) and (H,) truncated squared-residual sums.
    """
    inliers = np.empty((T_a_b.shape[0], points_b.shape[0]), dtype=bool)
    costs = np.empty(T_a_b.shape[0])
    t2 = threshold_m**2
    for start in range(0, T_a_b.shape[0], _BATCH):
        d2 = squared_residuals(T_a_b[start : start + _BATCH], points_b, points_a)
        inliers[start : start + _BATCH] = d2 < t2
        costs[start : start + _BATCH] = np.minimum(d2, t2).sum(axis=1)
    return inliers, costs


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
    inliers, costs = score_hypotheses(hypotheses, points_b, points_a, inlier_threshold_m)
    counts = inliers.sum(axis=1)
    best = int(np.lexsort((costs, -counts))[0])
    aligned = refine_alignment(
        hypotheses[best], points_b, points_a, rows_a, rows_b, weights,
        inlier_threshold_m, refine_iterations, gravity_aligned, up,
    )  # fmt: skip
    support = aligned.num_inliers
    unexplained = residuals_m(aligned.T_a_b, points_b, points_a) >= 2.0 * inlier_threshold_m
    rival = 0
    if unexplained.sum() >= 3:
        other = int(np.argmax(inliers[:, unexplained].sum(axis=1)))
        rival = refine_alignment(
            hypotheses[other], points_b[unexplained], points_a[unexplained], rows_a[unexplained],
            rows_b[unexplained], None if weights is None else weights[unexplained],
            inlier_threshold_m, refine_iterations, gravity_aligned, up,
        ).num_inliers  # fmt: skip
    return replace(
        aligned, support=support, rival_support=rival, inlier_support=support, rival_inlier_support=rival
    )
