"""Whole-overlap verification of a graph alignment: a likelihood ratio against chance, beyond the paper.

A hypothesis ``T_a_b`` is judged on *all* nodes of both graphs, not only on the descriptor candidates
that produced it. Under the hypothesis, B's nodes that land inside the area A observed (within
``coverage_m`` of some node of A) should find a same-label node of A within ``radius_m``, and A's nodes
inside the area B observed should find one of B. Each such node is one Bernoulli observation:

- H1 (the alignment is right): a node finds a partner with probability p1, the observed share of overlap
  nodes with a partner (a generalized likelihood ratio), but at least ``partner_probability`` (the
  other robot mapped the same object; maps miss 30-60 % of objects): a low share is not explained away;
- H0 (the alignment is wrong): a node finds one by chance with probability
  ``p0 = 1 - exp(-c (radius_m / density_radius_m)^2)``, where ``c`` counts the other graph's
  same-label nodes within ``density_radius_m`` of the node: the local density of its label (rows of
  trees along a street are dense, a lone traffic light is not). A uniform density underrates objects
  in rows and repeated templates (street trees and lamps at regular spacing, an intersection's signals
  laid out alike everywhere): they align again under a shift by their spacing. So, given ``shifts_m``
  (the matcher passes ``shift_vectors``: 6, 10 and 14 m along enough headings that one runs
  within the radius of any street's own direction, 16 for a 3 m radius), each label's chance is also measured
  under the hypothesis shifted by each vector (``label_chance``), and the larger p0 counts. Rows that repeat
  farther apart than those shifts reach (street lamps every 25-40 m) are measured under their own repeat:
  ``row_steps`` finds the steps many nodes of one label share in either graph (B's turned into A's frame
  by the hypothesis), and each such step shifts only its own label (``shift_labels``). Without it, one
  lamp row matched on another street carried a whole alias (6 of 8 poles partnered against a density
  chance of 3 %: +14 nats, every other label at chance).

Classes that two robots do not map alike can be left without evidence either way
(``evidence_free_labels``; the map server passes ``labels.VIEWPOINT_DEPENDENT_LABELS`` between robots that
look from very different heights, ``server/viewpoints.py``). Flat ground: a car sees the strip of sidewalk
or grass beside it, a UAV 50 m up the whole block's, so their centroids lie metres apart under the true
alignment (counted, terrain alone gave -10 to -21 nats against every true car-UAV alignment on the airsim-like
tuning worlds, while the partners of compact objects supported it); buildings likewise (a facade against a
roof); poles, traffic lights and signs are a few pixels seen from above, so the car's find no partner. They
still pair up (``pairs``: closure refits take the height of flat ground).

The log likelihood ratio sums ``log(p1 / p0)`` over supported nodes and ``log((1 - p1) / (1 - p0))``
over contradicting ones (inside the other's area, no partner). A contradicting node may be an object the other
robot mapped under another label (a pole taken for a sign): then another label's node lies within the radius,
its *trace*. Traces beyond their chance (the density of other labels, raised to what the shifted hypotheses find,
as for partners) add the log Bayes factor of ``confusion_llrs``, never less than 0; in a rendered city's dense
graphs some other object lies within 3 m of almost anything and the traces add nothing, in sparse maps they
recover what confused labels cost (``bench sparse --confusion 0.10``, tuning seeds 10-29: 144 -> 152 of 200).
An alias explains the repeated street but contradicts everything around it: buildings, intersections and objects
where the other robot mapped none. The evidence of both directions is required (the smaller LLR counts). The matcher
compares it with ``log(hypotheses / alpha)``: a false-alarm probability ``alpha`` after searching that
many hypotheses (Bonferroni).

Where the parts live: the shifts, row repeats and label chance in ``chance.py``, the confused labels' traces in
``confusion.py``, the same-label KD-tree (labels folded into a fourth coordinate) in ``labelled_tree.py``; this
module pairs the nodes up and sums the evidence.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import first_indices, unique_first
from shgm_slam.matching.chance import label_chance, shares_first, shifted_hits_both
from shgm_slam.matching.confusion import confusion_llrs
from shgm_slam.matching.labelled_tree import LabelledTree, embed, nearest_same_label

MAX_PARTNER_PROBABILITY = 0.95
"""Cap of the H1 partner rate estimated from the overlap (generalized likelihood ratio)."""


@dataclass(frozen=True)
class Verification:
    """Evidence for one alignment.

    Attributes:
        support: one-to-one same-label node pairs within the radius (evidence-free labels included).
        overlap_a, overlap_b: nodes of A (B) inside the area the other robot observed whose labels give
            evidence.
        contradictions: overlap nodes (both sides) without a same-label partner.
        expected_chance: nodes of B expected to find a partner by chance (sum of p0 over B's overlap).
        llr: log likelihood ratio H1 / H0 (the smaller of the two directions), nats.
        pairs: (S, 2) int64 row pairs (row_a, row_b) of the support.
    """

    support: int
    overlap_a: int
    overlap_b: int
    contradictions: int
    expected_chance: float
    llr: float
    pairs: np.ndarray


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points mapped by a (4, 4) transform."""
    return points @ T[:3, :3].T + T[:3, 3]


def support_counts(
    tree_a: LabelledTree, points_b: np.ndarray, labels_b: np.ndarray, T_stack: np.ndarray, radius_m: float
) -> np.ndarray:
    """(H,) nodes of B with a same-label node of A within ``radius_m`` under each of (H, 4, 4) hypotheses
    (not one-to-one: a fast screening score for many hypotheses at once)."""
    mapped = map_stack(T_stack, points_b)
    d, _ = nearest_same_label(tree_a, mapped.reshape(-1, 3), np.tile(labels_b, len(T_stack)), radius_m)
    return np.isfinite(d).reshape(len(T_stack), -1).sum(axis=1)


def map_stack(T_stack: np.ndarray, points_xyz: np.ndarray) -> np.ndarray:
    """(H, N, 3) the (N, 3) points mapped by each of (H, 4, 4) transforms (one einsum).

    The rotations are copied to a contiguous (H, 3, 3) block first: einsum then takes a loop twice as fast as
    on the strided view, with the same products summed in the same order (the same bits).
    """
    rotations = np.ascontiguousarray(T_stack[:, :3, :3])
    return np.einsum("hij,nj->hni", rotations, points_xyz) + T_stack[:, None, :3, 3]


def _one_to_one(rows_a: np.ndarray, rows_b: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Indices of a greedy one-to-one subset of candidate pairs, closest first."""
    order = np.argsort(dist, kind="stable")
    keep = order[first_indices(rows_a[order])]
    keep = keep[np.argsort(dist[keep], kind="stable")]
    return keep[first_indices(rows_b[keep])]


def partner_pairs(
    tree_a: LabelledTree, points_b_in_a: np.ndarray, labels_b: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one same-label partners of B's (N_b, 3) nodes (mapped into A's frame) among A's nodes.

    Returns:
        (S, 2) int64 row pairs (row_a, row_b), closest first per node, and their (S,) distances in metres.
    """
    return partner_pairs_stack(tree_a, points_b_in_a[None], labels_b, radius_m)[0]


def partner_pairs_stack(
    tree_a: LabelledTree, points_b_in_a: np.ndarray, labels_b: np.ndarray, radius_m: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``partner_pairs`` of B's nodes placed by H hypotheses, (H, N_b, 3) in A's frame, with one tree query
    (each point's nearest neighbour does not depend on the other points queried with it)."""
    h, n = points_b_in_a.shape[:2]
    d, j = nearest_same_label(tree_a, points_b_in_a.reshape(-1, 3), np.tile(labels_b, h), radius_m)
    close = np.flatnonzero(np.isfinite(d))  # (h * N_b) flat rows, by hypothesis then row of B
    hyp, row_b, row_a = close // n, close % n, j[close].astype(np.int64)
    # one greedy one-to-one over all hypotheses: keys offset by hypothesis never collide across them, and
    # each hypothesis' entries keep their relative order (the selection and ties are those of one call)
    keep = _one_to_one(hyp * (len(tree_a) + 1) + row_a, close, d[close])
    pairs, dist = np.stack([row_a[keep], row_b[keep]], axis=1), d[close][keep]
    bounds = np.concatenate([[0], np.cumsum(np.bincount(hyp[keep], minlength=h))]).tolist()
    return [(pairs[i:j], dist[i:j]) for i, j in pairwise(bounds)]


def _direction_llrs(
    residual_m: np.ndarray, inside: np.ndarray, same_nearby: np.ndarray,
    radius_m: float, density_radius_m: float, partner_probability: float,
    hits: np.ndarray | None = None, label_ids: np.ndarray | None = None,
) -> list[tuple[float, float]]:  # fmt: skip
    """(LLR, expected chance count) of one direction over its overlap nodes (module docstring), for H
    hypotheses at once.

    Args:
        residual_m: (H, N) each node's distance to its partner (inf without one).
        inside: (H, N) bool, the node lies in the other graph's observed area.
        same_nearby: (H, N) same-label nodes of the other graph within ``density_radius_m``.
        hits: (S, H * N) bool shifted hits (``_shifted_hits_both`` on stacked nodes) or None.
        label_ids: (N,) the nodes' labels (with ``hits``).

    Every value is computed element by element as for one hypothesis; label groups are (hypothesis,
    label) pairs and each hypothesis' sums run over its own contiguous slice, so the results are those
    of one hypothesis at a time.
    """
    h, n = residual_m.shape
    p0 = 1.0 - np.exp(-same_nearby.reshape(-1) * (radius_m / density_radius_m) ** 2)
    inside_flat = inside.reshape(-1)
    if hits is not None and label_ids is not None:
        _, _, label_index = unique_first(np.asarray(label_ids))
        groups = np.arange(h)[:, None] * (n + 1) + label_index[None, :]  # (hypothesis, label) keys
        p0 = label_chance(hits, groups.reshape(-1), inside_flat, p0)
    s = np.isfinite(residual_m.reshape(-1)[inside_flat])  # by hypothesis, then node
    counts = inside.sum(axis=1)
    hyp = np.repeat(np.arange(h), counts)
    p1 = np.full(h, partner_probability)
    seen = counts > 0  # generalized LR: the observed partner share, clipped
    share = np.bincount(hyp, weights=s, minlength=h)[seen] / counts[seen]
    p1[seen] = np.minimum(np.maximum(share, partner_probability), MAX_PARTNER_PROBABILITY)
    p1_of = p1[hyp]
    p0 = np.clip(p0[inside_flat], 1e-3, p1_of)
    llr = np.where(s, np.log(p1_of / p0), np.log((1.0 - p1_of) / (1.0 - p0)))
    bounds = np.concatenate([[0], np.cumsum(counts)])
    return [(float(llr[i:j].sum()), float(p0[i:j].sum())) for i, j in pairwise(bounds)]


def verify_alignment(
    tree_a: LabelledTree,
    tree_b: LabelledTree,
    T_a_b: np.ndarray,
    *,
    radius_m: float,
    coverage_m: float,
    density_radius_m: float,
    partner_probability: float,
    shifts_m: np.ndarray | None = None,
    shift_labels: np.ndarray | None = None,
    evidence_free_labels: tuple[int, ...] = (),
    confusions: bool = True,
) -> Verification:
    """Support, overlap, contradictions, chance expectation and the likelihood ratio of ``T_a_b``.

    One sparse same-label distance query between B's nodes (mapped into A's frame) and A's nodes serves
    both directions: a rigid map keeps distances, so the pairs within reach of each other, their offsets
    and the local densities are the same seen from A or from B (shifts turn with the hypothesis).

    Args:
        tree_a, tree_b: the two graphs' nodes, each in its own frame.
        T_a_b: (4, 4) hypothesis mapping B's frame into A's.
        radius_m: a same-label node this close is a partner.
        coverage_m: a node this close to any node of the other graph lies in the other's observed area.
        density_radius_m: radius of the local same-label density (chance model).
        partner_probability: probability that an object in the other's area was mapped by both (H1).
        shifts_m: (S, 3) shifts in A's frame (``shift_vectors``): when given, each label's chance of a partner
            is also measured under the hypothesis shifted by each (``label_chance``), and the larger counts.
        shift_labels: (S,) int64, the label each shift measures (a ``row_steps`` repeat), -1 for every label;
            None: every shift measures every label.
        evidence_free_labels: train ids whose nodes neither support nor contradict (module docstring): they
            are left out of the overlap counts, the contradictions and the LLR, and still pair up (``support``,
            ``pairs``).
        confusions: also count the traces of confused labels (``confusion_llrs``): a node without a same-label
            partner but with another label's node within ``radius_m``, as far as such traces are beyond chance.
    """
    return verify_alignments(
        tree_a, tree_b, np.asarray(T_a_b)[None], radius_m=radius_m, coverage_m=coverage_m,
        density_radius_m=density_radius_m, partner_probability=partner_probability, shifts_m=shifts_m,
        shift_labels=shift_labels, evidence_free_labels=evidence_free_labels, confusions=confusions,
    )[0]  # fmt: skip


def verify_alignments(
    tree_a: LabelledTree,
    tree_b: LabelledTree,
    T_stack: np.ndarray,
    *,
    radius_m: float,
    coverage_m: float,
    density_radius_m: float,
    partner_probability: float,
    shifts_m: np.ndarray | None = None,
    shift_labels: np.ndarray | None = None,
    evidence_free_labels: tuple[int, ...] = (),
    confusions: bool = True,
) -> list[Verification]:
    """``verify_alignment`` of each of (H, 4, 4) hypotheses; the overlap queries of all hypotheses are
    stacked into one query per tree (a point's nearest neighbour does not depend on the other points).
    ``shifts_m`` may also be (H, S, 3), a shift set per hypothesis (B's own rows turn with it)."""
    h, n_a, n_b = len(T_stack), len(tree_a), len(tree_b)
    pb = [transform(T, tree_b.positions_xyz) for T in T_stack]
    pa_in_b = [(tree_a.positions_xyz - T[:3, 3]) @ T[:3, :3] for T in T_stack]  # B's trees are reused
    free = evidence_free_labels
    usable_a, usable_b = _counts(tree_a.label_ids, free), _counts(tree_b.label_ids, free)
    inside_b = _within(tree_a.any, pb, coverage_m).reshape(h, n_b) & usable_b
    inside_a = _within(tree_b.any, pa_in_b, coverage_m).reshape(h, n_a) & usable_a
    reach = density_radius_m
    if shifts_m is not None and np.size(shifts_m):
        reach = max(reach, float(np.linalg.norm(shifts_m, axis=-1).max()) + radius_m)
    # the hypotheses' graphs side by side: B's node i of hypothesis k is k * N_b + i (A's likewise), so
    # every step below works on all hypotheses at once and, per hypothesis, as on one; one query of B's nodes
    # placed by every hypothesis (same-label layers of A's tree; each pair's distance as alone)
    placed_b = np.concatenate(pb)
    near = cKDTree(embed(placed_b, np.tile(tree_b.label_ids, h))).sparse_distance_matrix(
        tree_a.same, reach, output_type="ndarray"
    )
    i_b = near["i"].astype(np.int64)
    hyp = i_b // max(n_b, 1)
    j_a = near["j"].astype(np.int64) + hyp * n_a
    d = near["v"]
    pairs, dist = _partners_from_near(i_b, j_a, d, radius_m)
    res_a = np.full(h * n_a, np.inf)
    res_b = np.full(h * n_b, np.inf)
    res_a[pairs[:, 0]] = res_b[pairs[:, 1]] = dist
    dense = d <= density_radius_m
    near_b = np.bincount(i_b[dense], minlength=h * n_b).reshape(h, n_b)
    near_a = np.bincount(j_a[dense], minlength=h * n_a).reshape(h, n_a)
    hits_b = hits_a = None
    if shifts_m is not None:
        offsets = tree_a.positions_xyz[j_a - hyp * n_a] - placed_b[i_b]  # (P, 3) in A's frame
        per_hypothesis = np.broadcast_to(shifts_m, (h, *np.shape(shifts_m)[-2:]))
        hits_b = np.zeros((per_hypothesis.shape[1], h * n_b), dtype=bool)
        hits_a = np.zeros((per_hypothesis.shape[1], h * n_a), dtype=bool)
        shared = shares_first(per_hypothesis)  # B's rows seldom turn: most hypotheses share one product
        runs = [(np.flatnonzero(shared[hyp]), 0)]
        runs += [(np.flatnonzero(hyp == k), k) for k in np.flatnonzero(~shared).tolist()]
        for rows, k in runs:
            hb, ha = shifted_hits_both(
                offsets[rows], i_b[rows], j_a[rows], h * n_b, h * n_a, per_hypothesis[k], radius_m
            )
            hits_b |= hb
            hits_a |= ha
        if shift_labels is not None:  # a row's repeat measures its own label only
            hits_b &= np.tile(_measures(shift_labels, tree_b.label_ids), (1, h))
            hits_a &= np.tile(_measures(shift_labels, tree_a.label_ids), (1, h))
    res_a, res_b = res_a.reshape(h, n_a), res_b.reshape(h, n_b)
    args = (radius_m, density_radius_m, partner_probability)
    llr_b = _direction_llrs(res_b, inside_b, near_b, *args, hits_b, tree_b.label_ids)
    llr_a = _direction_llrs(res_a, inside_a, near_a, *args, hits_a, tree_a.label_ids)
    trace_b = trace_a = np.zeros(h)
    if confusions:
        general = None
        if shifts_m is not None and np.size(shifts_m):
            every = np.ones(np.shape(shifts_m)[-2], bool) if shift_labels is None else np.asarray(shift_labels) == -1
            general = np.broadcast_to(shifts_m, (h, *np.shape(shifts_m)[-2:]))[:, every]
        # A's nodes seen from B: the hypothesis shifted by s in A's frame moves B's nodes by s, i.e. A's node by
        # -s turned into B's frame
        general_in_b = None if general is None else -np.einsum("hsi,hij->hsj", general, T_stack[:, :3, :3])
        within = d <= radius_m  # same-label pairs within the radius (the others are counted from the trees)
        same_b = (np.bincount(i_b[within], minlength=h * n_b).reshape(h, n_b), near_b)
        same_a = (np.bincount(j_a[within], minlength=h * n_a).reshape(h, n_a), near_a)
        radii = {"radius_m": radius_m, "density_radius_m": density_radius_m}
        trace_b = confusion_llrs(inside_b & ~np.isfinite(res_b), pb, tree_b.label_ids, tree_a, usable_a[0], general,
                                 same_b, **radii)  # fmt: skip
        trace_a = confusion_llrs(inside_a & ~np.isfinite(res_a), pa_in_b, tree_a.label_ids, tree_b, usable_b[0],
                                 general_in_b, same_a, **radii)  # fmt: skip
    contradictions = (inside_b & ~np.isfinite(res_b)).sum(axis=1) + (inside_a & ~np.isfinite(res_a)).sum(axis=1)
    of = pairs[:, 1] // max(n_b, 1)  # pairs come by hypothesis, then B's row
    local = pairs - of[:, None] * np.array([n_a, n_b])
    bounds = np.concatenate([[0], np.cumsum(np.bincount(of, minlength=h))]).tolist()
    overlap_a, overlap_b = inside_a.sum(axis=1).tolist(), inside_b.sum(axis=1).tolist()
    return [
        Verification(
            support=j - i, overlap_a=overlap_a[k], overlap_b=overlap_b[k], contradictions=int(contradictions[k]),
            expected_chance=llr_b[k][1], llr=min(llr_a[k][0] + trace_a[k], llr_b[k][0] + trace_b[k]),
            pairs=local[i:j],
        )
        for k, (i, j) in enumerate(pairwise(bounds))
    ]  # fmt: skip


def _counts(label_ids: np.ndarray, evidence_free_labels: tuple[int, ...]) -> np.ndarray:
    """(1, N) bool: the node's label gives evidence (is not one of ``evidence_free_labels``)."""
    if not evidence_free_labels:  # every label (np.isin costs tens of microseconds even on an empty set)
        return np.ones((1, np.shape(label_ids)[0]), dtype=bool)
    return ~np.isin(np.asarray(label_ids), np.asarray(evidence_free_labels, dtype=np.int64))[None, :]


def _measures(shift_labels: np.ndarray, label_ids: np.ndarray) -> np.ndarray:
    """(S, N) bool: shift s measures node n's label (its label, or -1: every label)."""
    own = np.asarray(shift_labels)[:, None]
    return (own == -1) | (own == np.asarray(label_ids)[None, :])


def _within(tree: cKDTree, points: list[np.ndarray], radius_m: float) -> np.ndarray:
    """(sum of N,) bool: each of the stacked (N, 3) point sets' points has a tree point within ``radius_m``."""
    return np.isfinite(tree.query(np.concatenate(points), k=1, distance_upper_bound=radius_m)[0])


def _partners_from_near(
    i_b: np.ndarray, j_a: np.ndarray, d: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``partner_pairs`` from a precomputed same-label pair list (i in B, j in A, distance d): each B node's
    nearest A node within ``radius_m``, then the greedy one-to-one subset, closest first."""
    close = d <= radius_m
    i_b, j_a, d = i_b[close], j_a[close], d[close]
    order = np.lexsort((j_a, d, i_b))  # by B node, then distance (ties: lower A row, as a KD-tree query)
    first = order[first_indices(i_b[order])]
    keep = _one_to_one(j_a[first], i_b[first], d[first])
    rows = np.stack([j_a[first][keep], i_b[first][keep]], axis=1).astype(np.int64).reshape(-1, 2)
    return rows, d[first][keep]
