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
(``verification``), not on its size.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np

from shgm_slam.arrays import unique_first
from shgm_slam.matching.pose import DEFAULT_UP, fit_pose

HYPOTHESIS_SEEDS = 48
"""``clique_hypotheses``: greedy cliques grown from this many highest-degree candidates."""


_BLOCK_ROWS = 128
"""Rows of the consistency matrix computed at once (keeps the float temporaries in cache)."""


def pairwise_distances(points: np.ndarray) -> np.ndarray:
    """(K, K) float32 distances between (K, 3) points (computed in float64, see ``_node_distances``)."""
    points = np.asarray(points, dtype=np.float64)
    return _node_distances(points - points.mean(axis=0))


def _node_table(points: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The distinct nodes behind (K, 3) candidate points: (U, 3) node points (centred on the mean of
    the K candidates), (K,) index of each candidate's node and whether ``rows`` identify them.

    Candidates share nodes (K = 600 from 150 nodes), so the pairwise distances are computed once per node
    pair and gathered. When candidates with the same row have different points (not the matcher's
    case), every candidate is its own node.
    """
    points = np.asarray(points, dtype=np.float64)
    _, first, index = unique_first(np.asarray(rows))
    by_row = bool(np.array_equal(points[first][index], points))
    if not by_row:
        first, index = np.arange(points.shape[0]), np.arange(points.shape[0])
    return points[first] - points.mean(axis=0), index, by_row


def _node_distances(x: np.ndarray, diagonal: float | None = None) -> np.ndarray:
    """(U, U) float32 distances between (U, 3) centred points; the diagonal set to ``diagonal`` if given.

    The Gram form ``|x|² + |y|² - 2 x·y`` cancels terms of ``extent²``: in float32 it lost up to
    1.4 m at a 5 km map extent (2.5 km after centring) against metre tolerances. It is evaluated in
    float64 and only the result is cast to float32 (relative error 6e-8, below 1 mm at 5 km), which
    keeps the comparisons that follow fast.
    """
    sq = np.einsum("ij,ij->i", x, x)
    d = x @ x.T
    d *= -2.0
    d += sq[:, None]
    d += sq[None, :]
    out = d.astype(np.float32)
    np.maximum(out, 0.0, out=out)
    np.sqrt(out, out=out)
    if diagonal is not None:
        np.fill_diagonal(out, diagonal)
    return out


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

    The float32 distances between candidates are gathered from per-node tables (``_node_table``); with
    ``distinct_nodes`` two candidates of the same node get +inf on A's side and -inf on B's side, whose
    difference is never below the threshold.

    Args:
        points_a, points_b: (K, 3) candidate positions in A's and B's frames, metres.
        rows_a, rows_b: (K,) node rows of the candidates.
        threshold_m: eps, the tolerated difference of the two distances.
        distinct_nodes: also require two consistent candidates to use different nodes on both sides
            (a node cannot match twice).
        gravity_aligned: compare horizontal distances and vertical offsets about ``up`` separately.

    Returns:
        (K, K) bool matrix with a False diagonal (symmetric up to float32 rounding of the distances).
    """
    k = points_a.shape[0]
    dh = None
    if gravity_aligned:
        u = DEFAULT_UP if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        ha, hb = points_a @ u, points_b @ u
        points_a, points_b = points_a - np.outer(ha, u), points_b - np.outer(hb, u)
        # vertical offsets agree <=> (ha_i - hb_i) - (ha_j - hb_j) small: only differences matter, so
        # centre in float64 before casting (a common vertical offset of kilometres cancels exactly)
        dh = ha - hb
        dh = (dh - dh.mean()).astype(np.float32)
    nodes_a, index_a, by_row_a = _node_table(points_a, rows_a)
    nodes_b, index_b, by_row_b = _node_table(points_b, rows_b)
    inf = np.inf if distinct_nodes else None
    # (U, K) tables with their columns gathered once; a block's rows are then plain row copies
    cols_a = np.take(_node_distances(nodes_a, inf), index_a, axis=1)
    cols_b = np.take(_node_distances(nodes_b, None if inf is None else -inf), index_b, axis=1)
    ok = np.empty((k, k), dtype=bool)
    for start in range(0, k, _BLOCK_ROWS):
        stop = min(start + _BLOCK_ROWS, k)
        d_a = np.take(cols_a, index_a[start:stop], axis=0)
        ok[start:stop] = _close(d_a, np.take(cols_b, index_b[start:stop], axis=0), threshold_m)
        if dh is not None:
            d_h = np.subtract.outer(dh[start:stop], dh)
            ok[start:stop] &= np.abs(d_h, out=d_h) < threshold_m
    if distinct_nodes:
        for by_row, rows in ((by_row_a, rows_a), (by_row_b, rows_b)):
            if not by_row:  # every candidate its own node: the tables know only the diagonal
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


def _bit_sets(bits: np.ndarray, where: list[int], out: list[int]) -> list[int]:
    """Rows of an (R, K) bool matrix as Python ints (bit j of a row is its column j), written to ``out`` at
    ``where``; returns ``out``."""
    packed = np.packbits(bits, axis=1, bitorder="little")
    data, width = packed.tobytes(), packed.shape[1]
    for i, start in zip(where, range(0, len(data), width), strict=True):
        out[i] = int.from_bytes(data[start : start + width], "little")
    return out


def _packed_words(bits: np.ndarray) -> np.ndarray:
    """(R, W) uint64 words of the rows of an (R, K) bool matrix: bit j % 64 of word j // 64 is column j."""
    k = bits.shape[1]
    packed = np.zeros((bits.shape[0], -(-k // 64) * 8), dtype=np.uint8)
    packed[:, : -(-k // 8)] = np.packbits(bits, axis=1, bitorder="little")
    return packed.view("<u8")


def _run_starts(sorted_values: np.ndarray) -> np.ndarray:
    """Indices where a run of equal values of a sorted 1-D array begins."""
    return np.flatnonzero(np.diff(sorted_values, prepend=-1))


GrowthState = tuple[list[int], list[int], int]
"""A greedy clique being grown: (the clique so far, the candidates left ascending, the same as bits)."""


def _first_steps(adjacency: np.ndarray, seeds: np.ndarray) -> tuple[list[GrowthState], np.ndarray]:
    """The first step of the greedy clique (``_grow_clique``) from each of (S,) seeds (each of degree >= 1),
    all at once, and the candidates left to any of them (ascending: the rows the growth needs next).

    The seeds' neighbourhoods (the first and largest candidate sets) are listed as (seed, candidate) pairs,
    and every degree among them is the popcount of two packed rows ANDed: one array pass for all seeds
    instead of one Python loop per seed.
    """
    s = seeds.size
    seg, mem = np.nonzero(adjacency[seeds])  # by seed, then candidate ascending
    words = _packed_words(adjacency)
    degree = np.bitwise_count(words[mem] & words[seeds[seg]]).sum(axis=1, dtype=np.int64)
    starts = _run_starts(seg)
    sizes = np.diff(np.append(starts, seg.size))
    universal = degree == np.repeat(sizes - 1, sizes)
    has_universal = np.logical_or.reduceat(universal, starts)
    pick = np.repeat(has_universal, sizes)
    top = np.flatnonzero(~pick & (degree == np.repeat(np.maximum.reduceat(degree, starts), sizes)))
    first = top[_run_starts(seg[top])]  # the first candidate of most degree of each seed without universal
    v_of = np.zeros(s, dtype=np.int64)
    v_of[seg[first]] = mem[first]
    keep = np.where(pick, ~universal, adjacency[v_of[seg], mem])
    added = universal & pick
    added[first] = True
    left = np.zeros((s, adjacency.shape[0]), dtype=bool)
    left[seg[keep], mem[keep]] = True
    masks = _bit_sets(left, list(range(s)), [0] * s)
    members = _split_by(seg[keep], mem[keep], s)
    cliques = _split_by(seg[added], mem[added], s)
    states = [([seed, *c], m, mask) for seed, c, m, mask in zip(seeds.tolist(), cliques, members, masks, strict=True)]
    return states, np.flatnonzero(left.any(axis=0))


def _split_by(groups: np.ndarray, values: np.ndarray, count: int) -> list[list[int]]:
    """``values`` (sorted by ``groups`` in [0, count)) as one list per group."""
    bounds = np.concatenate([[0], np.cumsum(np.bincount(groups, minlength=count))]).tolist()
    flat = values.tolist()
    return [flat[i:j] for i, j in pairwise(bounds)]


def _grow_clique(rows: list[int], state: GrowthState, beat: int) -> list[int]:
    """Grow a clique on: repeatedly add the candidates adjacent to every other candidate left (in any
    maximal clique; ascending), or else the candidate adjacent to most others left (the first of them on
    ties), keeping the candidates adjacent to it (``_first_steps`` took the first step from the seed).

    Gives up (returns an empty list) as soon as the clique cannot exceed ``beat`` vertices.

    Args:
        rows: the (K, K) bool consistency matrix's rows as bit sets (``_bit_sets``; those of the candidates
            left are needed): a degree among the candidates left is one ``&`` and a popcount.
        state: the clique so far, the candidates left and their bits.
        beat: clique size to exceed.
    """
    clique, members, mask = list(state[0]), state[1], state[2]
    while members:
        if len(clique) + len(members) <= beat:
            return []
        degree = [(rows[i] & mask).bit_count() for i in members]
        full = len(members) - 1
        if full in degree:
            clique.extend(i for i, d in zip(members, degree, strict=True) if d == full)
            members = [i for i, d in zip(members, degree, strict=True) if d != full]
            mask = sum(1 << i for i in members)
        else:
            v = members[degree.index(max(degree))]
            clique.append(v)
            mask &= rows[v]
            members = [i for i in members if mask >> i & 1]
    return clique if len(clique) > beat else []


def _seed_cliques(adjacency: np.ndarray, seeds: list[int]) -> list[list[int]]:
    """The greedy cliques from ``seeds`` in order, skipping seeds inside a clique already found (they would
    mostly regrow it); cliques of fewer than 3 candidates and repeats dropped.

    The first steps (``_first_steps``) are taken for the first seed alone, then for every seed not covered
    yet at once: when the first clique covers all other seeds (one large overlap) nothing is wasted.
    """
    rows = [0] * adjacency.shape[0]  # the consistency rows as bit sets, filled as the growth needs them
    states: dict[int, GrowthState] = {}
    seen: set[tuple[int, ...]] = set()
    found: list[list[int]] = []
    covered: set[int] = set()
    for i, seed in enumerate(seeds):
        if seed in covered:
            continue
        if seed not in states:
            batch = [s for s in seeds[i:] if s not in covered][: 1 if i == 0 else None]
            first, left = _first_steps(adjacency, np.asarray(batch))
            states.update(zip(batch, first, strict=True))
            _bit_sets(adjacency[left], left.tolist(), rows)  # after the first step, only the candidates left
        clique = _grow_clique(rows, states[seed], 2)
        key = tuple(sorted(clique))
        if len(clique) >= 3 and key not in seen:
            seen.add(key)
            found.append(clique)
            covered.update(clique)
    return found


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
    several: greedy cliques (``_seed_cliques``) from the ``max_hypotheses`` candidates of highest consistency
    degree, in that order, skipping seeds inside a clique already found; cliques of fewer than 3 candidates
    and repeats dropped.

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
    seeds = seeds[degree[seeds] >= 2]  # by descending degree: the search stops at the first of degree < 2
    if seeds.size == 0:
        return []
    found = _seed_cliques(adjacency, seeds.tolist())
    if not found:
        return []
    cliques = sorted(found, key=lambda c: -len(c))
    # one batched Eq. 2 fit: cliques padded to the largest (with candidate 0) with zero weights
    lengths = np.array([len(c) for c in cliques])
    filled = np.arange(lengths[0])[None, :] < lengths[:, None]  # row-major: the cliques' concatenated order
    index = np.zeros(filled.shape, dtype=np.int64)
    index[filled] = np.concatenate(cliques)
    wc = np.ones(m) if weights is None else weights[:m]
    w = np.where(filled, wc[index], 0.0)
    return list(fit_pose(pb[index], pa[index], w, gravity_aligned, up))
