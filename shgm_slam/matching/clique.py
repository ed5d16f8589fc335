"""Robust outlier rejection beyond the paper: pairwise geometric consistency + maximum clique.

With partial overlap, missed detections and repeated classes (rows of trees, lamps, parked cars)
the best descriptor match of a node is often wrong and RANSAC over a 10-20 % inlier set fails. A
rigid motion preserves distances, so two correct correspondences (a_i, b_i), (a_j, b_j) satisfy
``| |a_i - a_j| - |b_i - b_j| | < eps`` whatever the transform; the correct correspondences form a
clique of this consistency graph while outliers are consistent only by chance. We take several
candidates per node (TOP_K), find a maximum clique, fit Eq. 2 on it and re-select inliers.

Gravity-aligned robots share the vertical axis, so their consistency test also compares vertical
offsets and horizontal distances separately (a much stronger test), and the fit is 4-DoF.

Chance cliques of 5-8 correspondences exist among hundreds of candidates even between places that
do not overlap, and on sparse, noisy maps the largest clique is often not the true one; so the matcher
takes several cliques (``clique_hypotheses``) and judges each on the whole overlap of both graphs
(``verification``), not on its size. ``clique_alignment`` (one maximum clique, its fit and the best
clique among the candidates it does not explain) remains for RANSAC comparisons and diagnostics.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from shgm_slam.matching.pose import DEFAULT_UP, Alignment, fit_pose, refine_alignment, residuals_m

MAX_SEEDS = 48
"""Maximum number of greedy clique constructions (seeds in decreasing degree order)."""

PATIENCE = 12
"""Stop after this many consecutive seeds that did not improve the best clique."""

HYPOTHESIS_SEEDS = 48
"""``clique_hypotheses``: greedy cliques grown from this many highest-degree candidates."""


_BLOCK_ROWS = 128
"""Rows of the consistency matrix computed at once (keeps the float temporaries in cache)."""


class _Centred:
    """(K, 3) points centred in float32 with their squared norms, for blocks of pairwise distances."""

    def __init__(self, points: np.ndarray) -> None:
        self.x = (points - points.mean(axis=0)).astype(np.float32)
        self.sq = np.einsum("ij,ij->i", self.x, self.x)

    def distances(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, K) float32 distances from points ``start:stop`` to all points (Gram form)."""
        d = self.x[start:stop] @ self.x.T
        d *= -2.0
        d += self.sq[start:stop, None]
        d += self.sq[None, :]
        np.maximum(d, 0.0, out=d)
        return np.sqrt(d, out=d)


def pairwise_distances(points: np.ndarray) -> np.ndarray:
    """(K, K) float32 distances between (K, 3) points."""
    return _Centred(points).distances(0, points.shape[0])


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
    """Pairwise consistency of K candidate correspondences, vectorised by broadcasting (in row blocks).

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
    k = points_a.shape[0]
    dh = None
    if gravity_aligned:
        u = DEFAULT_UP if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        ha, hb = points_a @ u, points_b @ u
        points_a, points_b = points_a - np.outer(ha, u), points_b - np.outer(hb, u)
        dh = (ha - hb).astype(np.float32)  # vertical offsets agree <=> (ha_i - hb_i) - (ha_j - hb_j) small
    ca, cb = _Centred(points_a), _Centred(points_b)
    ok = np.empty((k, k), dtype=bool)
    for start in range(0, k, _BLOCK_ROWS):
        stop = min(start + _BLOCK_ROWS, k)
        ok[start:stop] = _close(ca.distances(start, stop), cb.distances(start, stop), threshold_m)
        if dh is not None:
            ok[start:stop] &= _close(dh[start:stop, None] - dh[None, :], 0.0, threshold_m)
    if distinct_nodes:
        for rows in (rows_a, rows_b):
            ok[_same_node_pairs(rows)] = False
    np.fill_diagonal(ok, False)
    return ok


def _close(d_a: np.ndarray, d_b: np.ndarray | float, threshold_m: float) -> np.ndarray:
    """|d_a - d_b| < threshold elementwise, overwriting ``d_a`` (no K^2 temporaries)."""
    d_a -= d_b
    np.abs(d_a, out=d_a)
    return d_a < threshold_m


def _same_node_pairs(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with ``rows[i] == rows[j]`` as index arrays: O(sum of group sizes^2), not O(K^2)."""
    order = np.argsort(rows, kind="stable")
    r = rows[order]
    starts = np.searchsorted(r, r, side="left")
    sizes = np.searchsorted(r, r, side="right") - starts
    i = np.repeat(np.arange(r.size), sizes)
    offsets = np.arange(i.size) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    j = np.repeat(starts, sizes) + offsets
    return order[i], order[j]


def _count(adjacency: np.ndarray, axis: int) -> np.ndarray:
    """Number of True entries along ``axis`` of a bool matrix, as int64 (fast uint8 view reduction)."""
    acc = np.uint16 if adjacency.shape[axis] < 2**16 else np.int64
    return adjacency.view(np.uint8).sum(axis=axis, dtype=acc).astype(np.int64)


def _prune(adjacency: np.ndarray, alive: np.ndarray, degree: np.ndarray, size: int) -> None:
    """Drop (in place) vertices that cannot be in a clique larger than ``size``: degree among alive < size.

    ``degree`` holds each vertex's degree among the alive vertices and is kept up to date.
    """
    drop = alive & (degree < size)
    while drop.any():
        alive &= ~drop
        degree -= _count(adjacency[drop], axis=0)
        drop = alive & (degree < size)


def _greedy_clique(adjacency: np.ndarray, seed: int, alive: np.ndarray, beat: int) -> np.ndarray:
    """Grow a clique from ``seed``: repeatedly add the candidate adjacent to most other candidates.

    Gives up (returns an empty array) as soon as the clique cannot exceed ``beat`` vertices.
    """
    clique = [seed]
    cand = np.flatnonzero(adjacency[seed] & alive)
    sub = adjacency[cand][:, cand]
    while cand.size:
        if len(clique) + cand.size <= beat:
            return np.zeros(0, dtype=np.int64)
        degree = _count(sub, axis=1)
        universal = degree == cand.size - 1  # adjacent to every other candidate: in any maximal clique
        if universal.any():
            clique.extend(cand[universal].tolist())
            keep = ~universal
        else:
            v = int(np.argmax(degree))
            clique.append(int(cand[v]))
            keep = sub[v]
        cand, sub = cand[keep], sub[keep][:, keep]
    return np.asarray(clique, dtype=np.int64) if len(clique) > beat else np.zeros(0, dtype=np.int64)


def max_clique(
    adjacency: np.ndarray,
    within: np.ndarray | None = None,
    max_seeds: int = MAX_SEEDS,
    patience: int = PATIENCE,
) -> np.ndarray:
    """A maximum clique of a (K, K) symmetric bool adjacency (heuristic, usually exact here).

    Greedy max-degree construction from up to ``max_seeds`` seeds in decreasing degree order (stopping
    after ``patience`` seeds without improvement); after every improvement, vertices whose degree
    cannot support a larger clique are pruned (k-core), and seeds whose degree cannot beat the best
    clique end the search.

    Args:
        adjacency: (K, K) bool, symmetric, False diagonal.
        within: optional (K,) bool mask: search only the subgraph induced by these vertices.

    Returns:
        (M,) int64 sorted vertex indices of the clique (empty when no vertex is available).
    """
    k = adjacency.shape[0]
    alive = np.ones(k, dtype=bool) if within is None else within.copy()
    if not alive.any():
        return np.zeros(0, dtype=np.int64)
    degree = _count(adjacency, axis=1)
    if within is not None and not within.all():
        degree -= _count(adjacency[~within], axis=0)
    initial = degree.copy()
    order = np.flatnonzero(alive)[np.argsort(-initial[alive], kind="stable")]
    best = order[:1]
    tried = since_improvement = 0
    for seed in order:
        if tried >= max_seeds or since_improvement >= patience or initial[seed] < best.size:
            break  # seeds come in decreasing initial degree: none of the rest can beat the best
        if not alive[seed] or degree[seed] < best.size:
            continue
        tried += 1
        since_improvement += 1
        clique = _greedy_clique(adjacency, int(seed), alive, best.size)
        if clique.size > best.size:
            best, since_improvement = clique, 0
            _prune(adjacency, alive, degree, best.size)
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
    max_candidates: int | None = None,
) -> Alignment | None:
    """Maximum-clique outlier rejection over K candidates, then the Eq. 2 fit and inlier re-selection.

    The clique is searched among the first ``max_candidates`` candidates (pass them in decreasing
    score order; the consistency matrix costs O(max_candidates^2)); the final inliers are selected
    among *all* K candidates: the one-to-one candidates whose residual under the clique's fit is below
    ``recheck_threshold_m(consistency_threshold_m)`` (re-selected ``refine_iterations`` times).
    ``support`` is the clique size; ``rival_support`` the size of the largest clique among the
    searched candidates that the fit does not explain (residual above twice the re-check threshold).
    ``inlier_support`` is the refined inlier count of the result; ``rival_inlier_support`` that of the
    rival clique's fit, refined among the candidates the result does not explain (0 without a rival).

    Args:
        points_b, points_a: (K, 3) candidate positions in B's and A's frames.
        rows_a, rows_b: (K,) node rows of the candidates.
        weights: (K,) Eq. 2 weights or None.

    Returns:
        The alignment, or None when no clique of at least 3 correspondences exists.
    """
    m = points_b.shape[0] if max_candidates is None else min(max_candidates, points_b.shape[0])
    pb, pa = points_b[:m], points_a[:m]
    adjacency = consistency_matrix(
        pa, pb, rows_a[:m], rows_b[:m], consistency_threshold_m, True, gravity_aligned, up
    )
    clique = max_clique(adjacency)
    if clique.size < 3:
        return None
    w = None if weights is None else weights[clique]
    T = fit_pose(pb[clique], pa[clique], w, gravity_aligned, up)
    threshold = recheck_threshold_m(consistency_threshold_m)
    unexplained = residuals_m(T, pb, pa) >= 2.0 * threshold
    rival = max_clique(adjacency, within=unexplained)
    aligned = refine_alignment(
        T, points_b, points_a, rows_a, rows_b, weights, threshold, refine_iterations, gravity_aligned, up
    )
    rival_inliers = 0
    if rival.size >= 3:
        w_rival = None if weights is None else weights[:m][rival]
        T_rival = fit_pose(pb[rival], pa[rival], w_rival, gravity_aligned, up)
        rest = residuals_m(aligned.T_a_b, points_b, points_a) >= 2.0 * threshold
        rival_inliers = refine_alignment(
            T_rival, points_b[rest], points_a[rest], rows_a[rest], rows_b[rest],
            None if weights is None else weights[rest], threshold, refine_iterations, gravity_aligned, up,
        ).num_inliers  # fmt: skip
    return replace(
        aligned, support=int(clique.size), rival_support=int(rival.size),
        inlier_support=aligned.num_inliers, rival_inlier_support=int(rival_inliers),
    )  # fmt: skip


def recheck_threshold_m(consistency_threshold_m: float) -> float:
    """Residual under the clique's fit below which a candidate is an inlier: 2 eps.

    (Residuals below eps / 2 guarantee pairwise consistency; 2 eps tolerates the fit's own error.)
    """
    return 2.0 * consistency_threshold_m


def clique_hypotheses(
    points_b: np.ndarray,
    points_a: np.ndarray,
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    consistency_threshold_m: float = 2.0,
    gravity_aligned: bool = False,
    up: np.ndarray | None = None,
    max_candidates: int | None = None,
    max_hypotheses: int = HYPOTHESIS_SEEDS,
) -> list[np.ndarray]:
    """Several alignment hypotheses: the Eq. 2 fits of greedy cliques grown from different seeds.

    The maximum clique is often not the true alignment on sparse, noisy graphs (a chance clique of
    repeated classes can be as large as the true one, whose size noise caps), so the matcher verifies
    several: greedy cliques (``_greedy_clique``) from the ``max_hypotheses`` candidates of highest
    consistency degree, in that order, skipping seeds inside a clique already found; cliques of fewer
    than 3 candidates and repeats dropped.

    Args:
        points_b, points_a: (K, 3) candidate positions in B's and A's frames (decreasing score order).
        rows_a, rows_b: (K,) node rows of the candidates.
        weights: (K,) Eq. 2 weights or None.

    Returns:
        (4, 4) ``T_a_b`` fits, largest clique first.
    """
    m = points_b.shape[0] if max_candidates is None else min(max_candidates, points_b.shape[0])
    pb, pa = points_b[:m], points_a[:m]
    adjacency = consistency_matrix(pa, pb, rows_a[:m], rows_b[:m], consistency_threshold_m, True, gravity_aligned, up)
    degree = _count(adjacency, axis=1)
    seeds = np.argsort(-degree, kind="stable")[:max_hypotheses]
    alive = np.ones(m, dtype=bool)
    seen: set[bytes] = set()
    cliques: list[np.ndarray] = []
    covered = np.zeros(m, dtype=bool)
    for seed in seeds:
        if degree[seed] < 2:
            break
        if covered[seed]:  # it would mostly regrow a clique already found
            continue
        clique = _greedy_clique(adjacency, int(seed), alive, 2)
        key = np.sort(clique).tobytes()
        if clique.size >= 3 and key not in seen:
            seen.add(key)
            cliques.append(clique)
            covered[clique] = True
    if not cliques:
        return []
    cliques.sort(key=lambda c: -c.size)
    # one batched Eq. 2 fit: cliques padded to the largest with zero weights
    size = cliques[0].size
    index = np.zeros((len(cliques), size), dtype=np.int64)
    w = np.zeros((len(cliques), size))
    wc = np.ones(m) if weights is None else weights[:m]
    for i, c in enumerate(cliques):
        index[i, : c.size] = c
        w[i, : c.size] = wc[c]
    return list(fit_pose(pb[index], pa[index], w, gravity_aligned, up))
