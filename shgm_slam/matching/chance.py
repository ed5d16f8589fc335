"""The chance model's repeated structure: where a wrong alignment finds partners by chance because the city
repeats itself (rows of trees and lamps along a street, an intersection laid out alike everywhere).

A wrong alignment shifted along a street lines rows up again, so each label's chance of a partner is measured
under the hypothesis shifted by ``shift_vectors`` (along every heading) and by the graphs' own row repeats
(``row_steps``); ``label_chance`` turns those hits into each node's chance rate. The verification
(``verification.py``) and the confused-label traces (``confusion.py``) use it; the module docstring of
``verification.py`` tells the whole model.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import first_indices, unique_first
from shgm_slam.matching.labelled_tree import LabelledTree, embed

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


def shifted_hits_both(
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


def shares_first(shifts_m: np.ndarray) -> np.ndarray:
    """(H,) bool: the hypothesis' (S, 3) shifts of (H, S, 3) equal the first hypothesis' (True for the first)."""
    flat = shifts_m.reshape(len(shifts_m), -1)
    return (flat == flat[0]).all(axis=1)
