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

Labels are folded into a fourth coordinate so that one KD-tree query finds same-label neighbours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from itertools import pairwise

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import first_indices, unique_first

MAX_PARTNER_PROBABILITY = 0.95
"""Cap of the H1 partner rate estimated from the overlap (generalized likelihood ratio)."""

CHANCE_PRIOR_OBSERVATIONS = 4.0
"""Weight of the density model in a label's shifted chance rate, in pseudo-observations: the second-best of
many shifts (48 with a 3 m radius) is lucky on a label of few nodes, so few nodes are judged mostly by
their density, while a row of many repeats outweighs it (chosen on the tuning seeds: 1, 2, 4, 8 compared
in docs/benchmarks.md)."""

MAX_SHIFT_HEADINGS = 64
"""Most shift headings ``shift_headings`` gives (a 3 m radius needs 16)."""

MAX_ROW_STEP_M = 40.0
"""Longest row repeat ``row_steps`` measures, metres (street lamps stand 25-40 m apart); a farther step is a
gap between objects, not a row's spacing."""

MIN_ROW_NODES = 4
"""Nodes of one label that must step by the same vector (either way, within the verification radius) for
the step to be a row's repeat. Every node steps onto its own nearest neighbour, so a step few nodes share
would only re-find those nodes (scattered signs and lights); with 2 or 3 the sparse benchmark's tuning seeds
lost 1-6 of 100 true pairs, with 4 none (a row of four or more is what a street repeats)."""

_LABEL_GAP_M = 1e6
"""Distance between label layers in the (x, y, z, label) embedding: same-label queries never cross."""


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


class LabelledTree:
    """Nodes of one graph indexed for same-label and any-label radius queries.

    Args:
        positions_xyz: (N, 3) node positions, metres.
        label_ids: (N,) train ids.
    """

    def __init__(self, positions_xyz: np.ndarray, label_ids: np.ndarray) -> None:
        self.positions_xyz = np.asarray(positions_xyz, dtype=np.float64)
        self.label_ids = np.asarray(label_ids, dtype=np.int64)

    @cached_property
    def any(self) -> cKDTree:
        """Tree of the (N, 3) positions (built on first use)."""
        return cKDTree(self.positions_xyz)

    @cached_property
    def same(self) -> cKDTree:
        """Tree of the (N, 4) ``embed`` points: same-label queries (built on first use)."""
        return cKDTree(embed(self.positions_xyz, self.label_ids))

    def __len__(self) -> int:
        return int(self.label_ids.shape[0])


def embed(positions_xyz: np.ndarray, label_ids: np.ndarray) -> np.ndarray:
    """(N, 4) points (x, y, z, label * gap): Euclidean distance is infinite-like across labels."""
    return np.column_stack([positions_xyz, np.asarray(label_ids, dtype=np.float64) * _LABEL_GAP_M])


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points mapped by a (4, 4) transform."""
    return points @ T[:3, :3].T + T[:3, 3]


def nearest_same_label(
    tree: LabelledTree, points_xyz: np.ndarray, label_ids: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest same-label node of ``tree`` within ``radius_m`` of each of (N, 3) points.

    Returns:
        (N,) distances (inf when none) and (N,) row indices (``len(tree)`` when none).
    """
    return tree.same.query(embed(points_xyz, label_ids), k=1, distance_upper_bound=radius_m)


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


def shift_headings(radius_m: float, distances_m: tuple[float, ...]) -> int:
    """Headings the shifts need so that a shift along a street of *any* heading is among them.

    A row of objects repeats along its street, whatever way the street runs. With ``n`` headings
    ``2 pi / n`` apart, at most ``pi / n`` lies between the street and the nearest heading; at distance
    ``d`` that heading's shift lands ``d sin(pi / n)`` beside the along-street shift, and it measures the
    row's chance only when that is within ``radius_m``. So ``n >= pi / arcsin(radius_m / d)`` at the
    farthest distance, rounded up to an even count (a shift and its opposite): 16 for 3 m and 14 m.
    Fixed 8 headings (45 degrees apart) missed streets running between them by up to 5.4 m at 14 m, and
    repeated streets at such headings were accepted as aliases.

    Args:
        radius_m: the verification radius (a partner is within this), metres; > 0 (below ~0.7 m the count
            is capped at ``MAX_SHIFT_HEADINGS``: the cost grows with it, and such a radius is finer than
            any object's centroid).
        distances_m: shift distances, metres; > 0.
    """
    d = max(distances_m)
    if radius_m >= d:
        return 4
    n = math.ceil(math.pi / math.asin(radius_m / d) - 1e-9)
    return min(MAX_SHIFT_HEADINGS, max(4, n + n % 2))


def shift_vectors(up: np.ndarray, radius_m: float, distances_m: tuple[float, ...] = (6.0, 10.0, 14.0)) -> np.ndarray:
    """(S, 3) horizontal shifts (perpendicular to ``up``): ``shift_headings(radius_m, distances_m)``
    headings, 0 first, times ``distances_m``, metres (read-only; cached, every match of a run uses the
    same)."""
    directions = shift_headings(radius_m, tuple(distances_m))
    return _shift_vectors(tuple(np.asarray(up, dtype=np.float64).tolist()), tuple(distances_m), directions)


@lru_cache(maxsize=16)
def _shift_vectors(up: tuple[float, float, float], distances_m: tuple[float, ...], directions: int) -> np.ndarray:
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    e1 = np.cross(u, [1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    ang = np.arange(directions) * (2.0 * np.pi / directions)
    heads = np.outer(np.cos(ang), e1) + np.outer(np.sin(ang), e2)
    shifts = (np.asarray(distances_m)[:, None, None] * heads[None]).reshape(-1, 3)
    shifts.flags.writeable = False
    return shifts


def row_steps(
    tree: LabelledTree, up: np.ndarray, *, radius_m: float, longer_than_m: float, max_m: float = MAX_ROW_STEP_M
) -> tuple[np.ndarray, np.ndarray]:
    """The repeats of a graph's own rows that the fixed shifts do not reach: (K, 3) horizontal step vectors
    (metres, in the graph's frame) and (K,) int64 the label each belongs to.

    A node's step is the horizontal offset (perpendicular to ``up``) to its nearest node of the same label.
    A step (either sign) shared within ``radius_m`` by at least ``MIN_ROW_NODES`` nodes of the label is a
    row's repeat: a row aligns again when shifted by it, wherever its street repeats. Only steps longer
    than ``longer_than_m`` (what the fixed ``shift_vectors`` reach: their longest plus the radius) and at
    most ``max_m`` are kept; steps within a third of the radius of each other count once.

    Args:
        tree: the graph's nodes (its cached same-label tree finds each node's nearest).
        up: (3,) vertical axis of the frame (any length > 0).
        radius_m: the verification radius, metres.
        longer_than_m: keep steps longer than this, metres.
        max_m: keep steps of at most this, metres.
    """
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    positions_xyz, label_ids = tree.positions_xyz, tree.label_ids
    empty = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    if len(tree) < MIN_ROW_NODES:
        return empty
    # every node's nearest same-label node in one query (labels far apart in the embedding; a lone node's
    # nearest is another label's, a step beyond any cap)
    nearest = tree.same.query(tree.same.data, k=2)[1][:, 1]
    step = positions_xyz[nearest] - positions_xyz
    step -= np.outer(step @ u, u)
    length = np.linalg.norm(step, axis=1)
    keep = (length > longer_than_m) & (length <= max_m) & (label_ids[nearest] == label_ids)
    if not keep.any():
        return empty
    both = np.vstack([step[keep], -step[keep]])  # a node stepping by -v shares the row of one stepping by v
    labels = np.concatenate([label_ids[keep], label_ids[keep]])
    shared = cKDTree(embed(both, labels)).query_ball_point(embed(both, labels), radius_m, return_length=True)
    both, labels = both[shared >= MIN_ROW_NODES], labels[shared >= MIN_ROW_NODES]
    # one integer key per (label, cell): cells lie within MAX_ROW_STEP_M / (radius / 3) of 0 on each axis
    cells = np.round(both / (radius_m / 3.0)).astype(np.int64)
    side = 2 * int(np.ceil(max_m / (radius_m / 3.0))) + 3
    keys = ((labels * side + cells[:, 0] + side // 2) * side + cells[:, 1] + side // 2) * side + cells[:, 2] + side // 2
    first = np.sort(first_indices(keys))
    return both[first], labels[first]


def shifted_hits(
    tree: LabelledTree, points_xyz: np.ndarray, label_ids: np.ndarray, shifts_m: np.ndarray, radius_m: float
) -> np.ndarray:
    """(S, N) bool: point n finds a same-label node of ``tree`` within ``radius_m`` once shifted by shift s.

    One sparse distance query collects every same-label node within reach of any shift; the shifts are then
    tested on the offsets of those pairs (vectorised over pairs x shifts).
    """
    n, num_shifts = points_xyz.shape[0], shifts_m.shape[0]
    reach = float(np.linalg.norm(shifts_m, axis=1).max()) + radius_m
    near = cKDTree(embed(points_xyz, label_ids)).sparse_distance_matrix(tree.same, reach, output_type="ndarray")
    hits = np.zeros((num_shifts, n), dtype=bool)
    if near.size == 0:
        return hits
    offsets = tree.positions_xyz[near["j"]] - points_xyz[near["i"]]  # (P, 3)
    d2 = ((offsets[None, :, :] - shifts_m[:, None, :]) ** 2).sum(axis=2)  # (S, P)
    s_idx, p_idx = np.nonzero(d2 < radius_m**2)
    hits[s_idx, near["i"][p_idx]] = True
    return hits


def label_chance(hits: np.ndarray, label_ids: np.ndarray, inside: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(N,) chance of a partner per node from the best shifted alignment of its label (module docstring).

    For every label, the shifts under which most of the label's overlap nodes find partners give the
    label's chance rate: rows of trees or lamps and repeated templates align again under a shift by
    their spacing, irregular objects do not. A periodic row aligns under both s and -s, so the
    second-best shift counts (the best alone is biased upwards by luck over many shifts). Shrunk
    towards ``prior`` (the density model, (N,)) by ``CHANCE_PRIOR_OBSERVATIONS`` pseudo-observations,
    so a label of few nodes is not judged on its luckiest shifts.
    """
    out = prior.copy()
    rows = np.flatnonzero(inside)
    if rows.size == 0:
        return out
    labels, _, group = unique_first(label_ids[rows])
    s_idx, r_idx = np.nonzero(hits[:, rows])
    num_shifts, num_labels = hits.shape[0], labels.size
    per_shift = np.bincount(s_idx * num_labels + group[r_idx], minlength=num_shifts * num_labels)
    best = np.sort(per_shift.reshape(num_shifts, num_labels), axis=0)[-2]  # hits of each label under each shift
    size = np.bincount(group, minlength=labels.size)
    p = prior[rows]
    m = CHANCE_PRIOR_OBSERVATIONS
    out[rows] = np.maximum(p, (best[group] + m * p) / (size[group] + m))
    return out


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
    inside_b = _within(tree_a.any, pb, coverage_m).reshape(h, n_b) & _counts(tree_b.label_ids, free)
    inside_a = _within(tree_b.any, pa_in_b, coverage_m).reshape(h, n_a) & _counts(tree_a.label_ids, free)
    reach = density_radius_m
    if shifts_m is not None and np.size(shifts_m):
        reach = max(reach, float(np.linalg.norm(shifts_m, axis=-1).max()) + radius_m)
    near = [
        cKDTree(embed(p, tree_b.label_ids)).sparse_distance_matrix(tree_a.same, reach, output_type="ndarray")
        for p in pb
    ]
    # the hypotheses' graphs side by side: B's node i of hypothesis k is k * N_b + i (A's likewise), so
    # every step below works on all hypotheses at once and, per hypothesis, as on one
    pair_counts = [x.size for x in near]
    hyp = np.repeat(np.arange(h), pair_counts)
    i_b = np.concatenate([x["i"] for x in near]).astype(np.int64) + hyp * n_b
    j_a = np.concatenate([x["j"] for x in near]).astype(np.int64) + hyp * n_a
    d = np.concatenate([x["v"] for x in near])
    pairs, dist = _partners_from_near(i_b, j_a, d, radius_m)
    res_a = np.full(h * n_a, np.inf)
    res_b = np.full(h * n_b, np.inf)
    res_a[pairs[:, 0]] = res_b[pairs[:, 1]] = dist
    dense = d <= density_radius_m
    near_b = np.bincount(i_b[dense], minlength=h * n_b).reshape(h, n_b)
    near_a = np.bincount(j_a[dense], minlength=h * n_a).reshape(h, n_a)
    hits_b = hits_a = None
    if shifts_m is not None:
        offsets = tree_a.positions_xyz[j_a - hyp * n_a] - np.concatenate(pb)[i_b]  # (P, 3) in A's frame
        per_hypothesis = np.broadcast_to(shifts_m, (h, *np.shape(shifts_m)[-2:]))
        hits_b = np.zeros((per_hypothesis.shape[1], h * n_b), dtype=bool)
        hits_a = np.zeros((per_hypothesis.shape[1], h * n_a), dtype=bool)
        shared = _shares_first(per_hypothesis)  # B's rows seldom turn: most hypotheses share one product
        bounds = np.concatenate([[0], np.cumsum(pair_counts)])
        runs = [(np.flatnonzero(np.repeat(shared, pair_counts)), 0)]
        runs += [(np.arange(bounds[k], bounds[k + 1]), k) for k in np.flatnonzero(~shared).tolist()]
        for rows, k in runs:
            hb, ha = _shifted_hits_both(
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
        usable_a, usable_b = _counts(tree_a.label_ids, free)[0], _counts(tree_b.label_ids, free)[0]
        # A's nodes seen from B: the hypothesis shifted by s in A's frame moves B's nodes by s, i.e. A's node by
        # -s turned into B's frame
        general_in_b = None if general is None else -np.einsum("hsi,hij->hsj", general, T_stack[:, :3, :3])
        within = d <= radius_m  # same-label pairs within the radius (the others are counted from the trees)
        same_b = (np.bincount(i_b[within], minlength=h * n_b).reshape(h, n_b), near_b)
        same_a = (np.bincount(j_a[within], minlength=h * n_a).reshape(h, n_a), near_a)
        radii = {"radius_m": radius_m, "density_radius_m": density_radius_m}
        trace_b = confusion_llrs(inside_b & ~np.isfinite(res_b), pb, tree_b.label_ids, tree_a, usable_a, general,
                                 same_b, **radii)  # fmt: skip
        trace_a = confusion_llrs(inside_a & ~np.isfinite(res_a), pa_in_b, tree_a.label_ids, tree_b, usable_b,
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


def confusion_llrs(
    unpartnered: np.ndarray, points: list[np.ndarray], label_ids: np.ndarray, other: LabelledTree,
    usable: np.ndarray, shifts_m: np.ndarray | None, same_near: tuple[np.ndarray, np.ndarray], *,
    radius_m: float, density_radius_m: float,
) -> np.ndarray:  # fmt: skip
    """(H,) log Bayes factor, >= 0, of the *traces of confused labels* among one side's nodes under H hypotheses.

    A node inside the other's area without a same-label partner is either an object the other robot did not map,
    or one it mapped under another label (a pole taken for a sign, a tree for a building): then another label's
    node lies within ``radius_m``. Under a wrong alignment that happens at the chance of another label's node
    nearby: the density of other labels within ``density_radius_m`` (as ``p0``), raised, as the same label's
    chance is (``label_chance``), to what the hypothesis shifted by ``shifts_m`` finds (rows of other objects
    line up under a shifted street too). The rate under the right alignment is unknown (the maps' confusion rate);
    the Bayes factor integrates it over a uniform prior, a proper likelihood ratio (no parameter fitted to the
    data it judges), floored at 1: the traces can rescue the support a confused label lost, never count against
    an alignment. Without it, each confused object of the overlap is a lost partner on both sides (10 % of labels
    confused per robot cost a fifth of the sparse benchmark's localizations).

    Args:
        unpartnered: (H, N) bool, the side's nodes inside the other's area, giving evidence, without a partner.
        points: H arrays (N, 3): the side's nodes placed in the other graph's frame by each hypothesis.
        label_ids: (N,) the side's labels.
        other: the other graph's nodes.
        usable: (M,) bool, the other graph's nodes whose labels give evidence.
        shifts_m: (H, S, 3) shifts of the nodes in the other's frame (the chance model's) or None.
        same_near: (H, N) counts of the other graph's nodes of each node's own label within ``radius_m`` and (H, N)
            within ``density_radius_m`` (the verification has them).
        radius_m, density_radius_m: the verification's radii, metres.
    """
    h, n = unpartnered.shape
    flat = np.flatnonzero(unpartnered.reshape(-1))  # (hypothesis, node) keys k * N + row
    if flat.size == 0 or not usable.any():
        return np.zeros(h)
    hyp, rows = flat // n, flat % n
    placed = np.stack(points).reshape(-1, 3)[flat]
    counted = other.any if usable.all() else cKDTree(other.positions_xyz[usable])

    def other_labels_within(r: float, same: np.ndarray) -> np.ndarray:
        # every usable node within r less those of the node's own label (a usable label: the node gives evidence)
        return counted.query_ball_point(placed, r, return_length=True) - same.reshape(-1)[flat]

    same_r, same_density = same_near
    trace = other_labels_within(radius_m, same_r) > 0
    if not trace.any():  # no trace anywhere: every factor is below 1
        return np.zeros(h)
    q0 = 1.0 - np.exp(-other_labels_within(density_radius_m, same_density) * (radius_m / density_radius_m) ** 2)
    bound = _confusion_factors(np.clip(q0, 1e-3, 1.0 - 1e-3), trace, hyp, h)
    live = (bound > 0.0)[hyp]  # the shifted chance only raises q0, and a higher q0 only lowers the factor
    if shifts_m is None or not shifts_m.size or not live.any():
        return bound
    reach = max(density_radius_m, float(np.linalg.norm(shifts_m, axis=-1).max()) + radius_m)
    # the live hypotheses side by side: their copies of the other graph (node j of a copy is copy * M + j) and
    # their nodes lie apart in a fourth coordinate, so no pair of different hypotheses is formed
    m, sel = len(other), np.flatnonzero(live)
    tiles = np.flatnonzero(bound > 0.0)  # a copy of the other graph per live hypothesis
    mine = cKDTree(np.column_stack([placed[sel], hyp[sel] * _LABEL_GAP_M]))
    theirs = cKDTree(np.column_stack([np.tile(other.positions_xyz, (tiles.size, 1)),
                                      np.repeat(tiles, m) * _LABEL_GAP_M]))  # fmt: skip
    near = mine.sparse_distance_matrix(theirs, reach, output_type="ndarray")
    i, j = near["i"].astype(np.int64), near["j"].astype(np.int64) % m
    keep = usable[j] & (other.label_ids[j] != label_ids[rows[sel[i]]])
    i, j = i[keep], j[keep]
    hits = _shifted_hits(other.positions_xyz[j] - placed[sel[i]], i, sel.size, shifts_m, hyp[sel[i]], radius_m)
    groups = hyp[sel] * (n + 1) + _label_index(label_ids)[rows[sel]]
    q0[sel] = label_chance(hits, groups, np.ones(sel.size, bool), q0[sel])
    return _confusion_factors(np.clip(q0, 1e-3, 1.0 - 1e-3), trace, hyp, h)


def _label_index(label_ids: np.ndarray) -> np.ndarray:
    """(N,) index of each node's label among the distinct labels."""
    return unique_first(np.asarray(label_ids))[2]


def _shifted_hits(
    offsets: np.ndarray, rows: np.ndarray, n: int, shifts_m: np.ndarray, hypotheses: np.ndarray, radius_m: float
) -> np.ndarray:
    """(S, n) bool: row r finds a node within ``radius_m`` once shifted by shift s, from the (P, 3) offsets (node -
    row) of its pairs within reach, (H, S, 3) shifts per hypothesis and (P,) each pair's hypothesis. |o - s|^2 =
    |o|^2 - 2 o.s + |s|^2, the products one matrix product per shift set (one for all the hypotheses whose shifts
    equal the first's: those that do not turn with the hypothesis)."""
    hits = np.zeros((shifts_m.shape[1], n), dtype=bool)
    sq_off = np.einsum("pi,pi->p", offsets, offsets)
    set_of = np.where(_shares_first(shifts_m), 0, np.arange(len(shifts_m)))
    of_pair = set_of[hypotheses]
    sets = [(np.flatnonzero(of_pair == k), shifts_m[k]) for k in np.unique(of_pair).tolist()]
    for pairs, shifts in sets:
        sq_s = np.einsum("si,si->s", shifts, shifts)
        cross = np.einsum("pi,si->ps", offsets[pairs], shifts)  # einsum, not BLAS: no threads for a 3-term sum
        close = sq_off[pairs, None] - 2.0 * cross + sq_s[None, :] < radius_m**2  # (P_k, S)
        p_idx, s_idx = np.nonzero(close)
        hits[s_idx, rows[pairs[p_idx]]] = True
    return hits


def _shares_first(shifts_m: np.ndarray) -> np.ndarray:
    """(H,) bool: the hypothesis' (S, 3) shifts of (H, S, 3) equal the first hypothesis' (True for the first)."""
    flat = shifts_m.reshape(len(shifts_m), -1)
    return (flat == flat[0]).all(axis=1)


_CONFUSION_RATES = np.linspace(0.0, 1.0, 129)
"""Grid of the confused share ``c`` over which ``_confusion_factors`` integrates."""

_TRAPEZOID_WEIGHTS = np.r_[0.5, np.ones(_CONFUSION_RATES.size - 2), 0.5] * (_CONFUSION_RATES[1] - _CONFUSION_RATES[0])
"""The trapezoid rule's weights on ``_CONFUSION_RATES`` (they sum to 1)."""


def _confusion_factors(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """(H,) log Bayes factors, floored at 0, of (N,) trace outcomes grouped by (N,) hypothesis: under the alignment
    a node shows a trace with probability ``q0 + (1 - q0) c`` (chance, plus the confused share c of the objects the
    other robot mapped under another label), under chance ``q0``; c uniform in [0, 1] (trapezoid rule). c = 0 is
    chance itself, so a factor exceeds 1 only where there are more traces than chance gives.

    The log-likelihood ratio ``g(c) = sum log(1 + c lift) + n_without log(1 - c)`` is concave with g(0) = 0, so
    where its slope at 0 (``sum lift - n_without``) is not positive, g <= 0 for every c and the factor is 0
    exactly: only the other hypotheses are integrated (most wrong ones are at or below chance)."""
    rising = _rising(q0, trace, hypotheses, h)
    out = np.zeros(h)
    if rising.any():
        keep = rising[hypotheses]
        index = np.cumsum(rising) - 1  # the rising hypotheses renumbered 0..R-1
        out[rising] = _integrated_factors(q0[keep], trace[keep], index[hypotheses[keep]], int(rising.sum()))
    return out


def _integrated_factors(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """``_confusion_factors`` by the trapezoid rule over ``_CONFUSION_RATES``, every hypothesis integrated."""
    c = _CONFUSION_RATES
    without = np.bincount(hypotheses[~trace], minlength=h)
    order = np.argsort(hypotheses[trace], kind="stable")  # each hypothesis' traces summed alone, in node order
    lift = ((1.0 - q0[trace]) / q0[trace])[order]
    owner = hypotheses[trace][order]
    log_f = np.zeros((c.size, h))  # (C, H)
    if lift.size:
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        log_f[:, owner[starts]] = np.add.reduceat(np.log1p(np.outer(c, lift)), starts, axis=1)
    log_f[:-1] += np.outer(np.log1p(-c[:-1]), without)
    log_f[-1, without > 0] = -np.inf  # (1 - c)^n at c = 1 (0^0 = 1 where every node shows a trace)
    top = log_f.max(axis=0)
    return np.maximum(0.0, top + np.log(_TRAPEZOID_WEIGHTS @ np.exp(log_f - top)))


def _rising(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """(H,) bool: the log-likelihood ratio of ``_confusion_factors`` rises from c = 0 (its slope there,
    ``sum (1 - q0) / q0`` over the traces less the nodes without one, is positive); where it does not, the
    concave ratio stays <= 0 for every c and the factor is 0."""
    lift = (1.0 - q0[trace]) / q0[trace]
    return np.bincount(hypotheses[trace], weights=lift, minlength=h) > np.bincount(hypotheses[~trace], minlength=h)


def _counts(label_ids: np.ndarray, evidence_free_labels: tuple[int, ...]) -> np.ndarray:
    """(1, N) bool: the node's label gives evidence (is not one of ``evidence_free_labels``)."""
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


def _shifted_hits_both(
    offsets: np.ndarray, i_b: np.ndarray, j_a: np.ndarray, n_b: int, n_a: int, shifts_m: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(S, N_b) and (S, N_a) bool: a node finds a same-label partner once the hypothesis is shifted by s.

    B's node i mapped and shifted by s lands within ``radius_m`` of A's node j when |offset - s| < r; seen
    from A (A's node mapped into B's frame and shifted by s turned into B's frame) the same pair hits
    when |offset + s| < r. ``offsets`` (P, 3) are A_j - T(B_i) for the pairs within reach.
    """
    hits_b = np.zeros((len(shifts_m), n_b), dtype=bool)
    hits_a = np.zeros((len(shifts_m), n_a), dtype=bool)
    if offsets.size == 0:
        return hits_b, hits_a
    r2 = radius_m**2
    sq_off = np.einsum("pi,pi->p", offsets, offsets)
    cross = np.einsum("si,pi->sp", shifts_m, offsets)  # (S, P); einsum, not BLAS: no threads for a 3-term sum
    sq_s = np.einsum("si,si->s", shifts_m, shifts_m)[:, None]
    s_idx, p_idx = np.nonzero(sq_off[None, :] - 2.0 * cross + sq_s < r2)
    hits_b[s_idx, i_b[p_idx]] = True
    s_idx, p_idx = np.nonzero(sq_off[None, :] + 2.0 * cross + sq_s < r2)
    hits_a[s_idx, j_a[p_idx]] = True
    return hits_b, hits_a
