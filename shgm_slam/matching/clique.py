"""Robust outlier rejection beyond the paper: pairwise geometric consistency + maximum clique.

With partial overlap, missed detections and repeated classes (rows of trees, lamps, parked cars)
the best descriptor match of a node is often wrong and RANSAC over a 10-20 % inlier set fails. A
rigid motion preserves distances, so two correct correspondences (a_i, b_i), (a_j, b_j) satisfy
``| |a_i - a_j| - |b_i - b_j| | < eps`` whatever the transform; the correct correspondences form a
clique of this consistency graph while outliers are consistent only by chance. We take several
candidates per node (TOP_K), find a maximum clique, fit Eq. 2 on it and re-select inliers.

Gravity-aligned robots share the vertical axis, so their consistency test also compares vertical
offsets and horizontal distances separately (a much stronger test), and the fit is 4-DoF.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from shgm_slam.matching.pose import DEFAULT_UP, Alignment, fit_pose, refine_alignment

MAX_SEEDS = 48
"""Maximum number of greedy clique constructions (seeds in decreasing degree order)."""


def _pairwise(points: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(K, K) distances between candidates, computed once per distinct node then gathered."""
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    d = cdist(points[first], points[first]).astype(np.float32)
    return d[inverse][:, inverse]


def consistency_matrix(
    points_a: np.ndarray,
    points_b: np.ndarray,
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    threshold_m: float,
    distinct_nodes: bool = True,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
) -> np.ndarray:
    """Pairwise consistency of K candidate correspondences, vectorised by broadcasting.

    Args:
        points_a, points_b: (K, 3) candidate positions in A's and B's frames, metres.
        rows_a, rows_b: (K,) node rows of the candidates.
        threshold_m: eps, the tolerated difference of the two distances.
        distinct_nodes: also require two consistent candidates to use different nodes on both sides
            (a node cannot match twice).
        gravity_aligned: compare horizontal distances and vertical offsets about ``up`` separately.

    Returns:
        (K, K) symmetric bool matrix with a False diagonal.
    """
    if gravity_aligned:
        u = DEFAULT_UP if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        ha, hb = points_a @ u, points_b @ u
        flat_a, flat_b = points_a - np.outer(ha, u), points_b - np.outer(hb, u)
        ok = np.abs(_pairwise(flat_a, rows_a) - _pairwise(flat_b, rows_b)) < threshold_m
        ok &= np.abs((ha[:, None] - ha[None, :]) - (hb[:, None] - hb[None, :])) < threshold_m
    else:
        ok = np.abs(_pairwise(points_a, rows_a) - _pairwise(points_b, rows_b)) < threshold_m
    if distinct_nodes:
        ok &= rows_a[:, None] != rows_a[None, :]
        ok &= rows_b[:, None] != rows_b[None, :]
    np.fill_diagonal(ok, False)
    return ok


def _prune(adjacency: np.ndarray, alive: np.ndarray, size: int) -> np.ndarray:
    """Drop vertices that cannot be in a clique larger than ``size`` (degree among alive < size)."""
    alive = alive.copy()
    while True:
        idx = np.flatnonzero(alive)
        degree = adjacency[np.ix_(idx, idx)].sum(axis=1)
        drop = degree < size
        if not drop.any():
            return alive
        alive[idx[drop]] = False


def _greedy_clique(adjacency: np.ndarray, seed: int, alive: np.ndarray, beat: int) -> np.ndarray:
    """Grow a clique from ``seed``: repeatedly add the candidate adjacent to most other candidates.

    Gives up (returns an empty array) as soon as the clique cannot exceed ``beat`` vertices.
    """
    clique = [seed]
    cand = np.flatnonzero(adjacency[seed] & alive)
    sub = adjacency[np.ix_(cand, cand)]
    while cand.size:
        if len(clique) + cand.size <= beat:
            return np.zeros(0, dtype=np.int64)
        v = int(np.argmax(sub.sum(axis=1)))
        clique.append(int(cand[v]))
        keep = sub[v]
        cand, sub = cand[keep], sub[np.ix_(keep, keep)]
    return np.asarray(clique, dtype=np.int64) if len(clique) > beat else np.zeros(0, dtype=np.int64)


def max_clique(adjacency: np.ndarray, max_seeds: int = MAX_SEEDS) -> np.ndarray:
    """A maximum clique of a (K, K) symmetric bool adjacency (heuristic, usually exact here).

    Greedy max-degree construction from up to ``max_seeds`` seeds in decreasing degree order; after
    every improvement, vertices whose degree cannot support a larger clique are pruned (k-core), and
    seeds whose degree cannot beat the best clique end the search.

    Returns:
        (M,) int64 sorted vertex indices of the clique (empty for an empty graph).
    """
    k = adjacency.shape[0]
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    degree = adjacency.sum(axis=1)
    best = np.array([int(np.argmax(degree))], dtype=np.int64)
    alive = np.ones(k, dtype=bool)
    tried = 0
    for seed in np.argsort(-degree, kind="stable"):
        if tried >= max_seeds or degree[seed] < best.size:
            break
        if not alive[seed]:
            continue
        tried += 1
        clique = _greedy_clique(adjacency, int(seed), alive, best.size)
        if clique.size > best.size:
            best = clique
            alive = _prune(adjacency, alive, best.size)
    return np.sort(best)


def clique_alignment(
    points_b: np.ndarray,
    points_a: np.ndarray,
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    consistency_threshold_m: float = 2.0,
    refine_iterations: int = 3,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
) -> Alignment | None:
    """Maximum-clique outlier rejection over K candidates, then the Eq. 2 fit and inlier re-selection.

    The final inliers are the one-to-one candidates whose residual under the clique's fit is below
    ``2 * consistency_threshold_m`` (re-selected ``refine_iterations`` times).

    Args:
        points_b, points_a: (K, 3) candidate positions in B's and A's frames.
        rows_a, rows_b: (K,) node rows of the candidates.
        weights: (K,) Eq. 2 weights or None.

    Returns:
        The alignment, or None when no clique of at least 3 correspondences exists.
    """
    adjacency = consistency_matrix(
        points_a, points_b, rows_a, rows_b, consistency_threshold_m, True, gravity_aligned, up
    )
    clique = max_clique(adjacency)
    if clique.size < 3:
        return None
    w = None if weights is None else weights[clique]
    T = fit_pose(points_b[clique], points_a[clique], w, gravity_aligned, up)
    return refine_alignment(
        T, points_b, points_a, rows_a, rows_b, weights,
        2.0 * consistency_threshold_m, refine_iterations, gravity_aligned, up,
    )  # fmt: skip
