"""Alignment hypotheses by pair voting, for gravity-aligned graphs: no descriptors involved.

On sparse, noisy maps (many objects missed, centroids metres off) the descriptors of the true partners
often differ, and the candidate list the cliques grow from holds only 4-9 true pairs among hundreds: no
clique forms near the truth even where the whole overlap, scored at the true alignment, is far beyond
chance (``bench sparse``: 18 of the 400 tuning pairs). A rigid motion about the vertical axis is fixed
by two point pairs, so every same-label *pair of pairs* whose horizontal lengths and vertical offsets
agree votes for one (yaw, position of B's centroid in A): its segment in B turned onto its segment in A.
True correspondences all vote for one cell; chance votes scatter. The most-voted cells become
hypotheses for the matcher's usual refinement and whole-overlap verification (which judges them; the
vote itself decides nothing).

Segments shorter than ``MIN_SEGMENT_M`` fix the heading too loosely under metre-level centroid noise;
the B centroid (not B's origin) is what a cell locates, so a small heading error moves it little.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import unique_first

MIN_SEGMENT_M = 10.0
"""Shortest segment (horizontal node-to-node distance) that votes, metres: with 2 m of centroid noise a
10 m segment fixes the heading to about 15 degrees."""

MAX_SEGMENT_M = 40.0
"""Longest segment that votes, metres (the overlap of two drives is a few street blocks)."""

YAW_CELL_RAD = np.radians(10.0)
"""Heading width of a vote cell."""

POSITION_CELL_M = 6.0
"""Horizontal width of a vote cell (where B's centroid lands in A), metres."""

MAX_VOTES = 200_000
"""Most votes cast per match (segments of B thinned evenly beyond it): keeps city-sized graphs cheap."""


def pair_vote_hypotheses(
    points_b: np.ndarray,
    labels_b: np.ndarray,
    points_a: np.ndarray,
    labels_a: np.ndarray,
    up: np.ndarray,
    *,
    tolerance_m: float,
    count: int,
) -> list[np.ndarray]:
    """The ``count`` most-voted gravity-aligned alignments of B's nodes onto A's (module docstring).

    Args:
        points_b, points_a: (N_b, 3) and (N_a, 3) node positions, each graph in its own frame, metres.
        labels_b, labels_a: (N_b,) and (N_a,) train ids.
        up: (3,) the vertical axis both frames share (any length > 0).
        tolerance_m: a segment of B votes with a same-label segment of A whose horizontal length and whose
            two ends' vertical offsets agree within this, metres (the clique's consistency tolerance).
        count: hypotheses returned (fewer when fewer cells hold votes).

    Returns:
        (4, 4) ``T_a_b`` (a yaw about ``up`` and a translation), most votes first; ties by cell order.
    """
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    e1 = np.cross(u, [1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    frame = np.column_stack([e1, np.cross(u, e1), u])  # columns: two horizontal axes, up
    local_b = np.asarray(points_b, dtype=np.float64) @ frame
    local_a = np.asarray(points_a, dtype=np.float64) @ frame
    labels_b, labels_a = np.asarray(labels_b, dtype=np.int64), np.asarray(labels_a, dtype=np.int64)
    seg_b = _segments(local_b[:, :2], ordered=False)
    seg_a = _segments(local_a[:, :2], ordered=True)  # both directions: B's (i, j) may map onto A's (l, k)
    if not (len(seg_b) and len(seg_a)) or count < 1:
        return []
    votes_b, votes_a = _agreeing(seg_b, seg_a, labels_b, labels_a, local_b, local_a, tolerance_m)
    if votes_b.size == 0:
        return []
    vec_b = local_b[seg_b[votes_b, 1], :2] - local_b[seg_b[votes_b, 0], :2]
    vec_a = local_a[seg_a[votes_a, 1], :2] - local_a[seg_a[votes_a, 0], :2]
    yaw = np.arctan2(vec_a[:, 1], vec_a[:, 0]) - np.arctan2(vec_b[:, 1], vec_b[:, 0])
    cos, sin = np.cos(yaw), np.sin(yaw)
    centre_b = local_b[:, :2].mean(axis=0)
    mid_b = 0.5 * (local_b[seg_b[votes_b, 0], :2] + local_b[seg_b[votes_b, 1], :2])
    mid_a = 0.5 * (local_a[seg_a[votes_a, 0], :2] + local_a[seg_a[votes_a, 1], :2])
    rel = centre_b - mid_b  # B's centroid seen from the segment's midpoint, turned by the vote's yaw
    landing = mid_a + np.column_stack([cos * rel[:, 0] - sin * rel[:, 1], sin * rel[:, 0] + cos * rel[:, 1]])
    rise = 0.5 * (
        local_a[seg_a[votes_a, 0], 2] - local_b[seg_b[votes_b, 0], 2]
        + local_a[seg_a[votes_a, 1], 2] - local_b[seg_b[votes_b, 1], 2]
    )  # fmt: skip
    cells = np.column_stack([
        np.floor(np.mod(yaw, 2.0 * np.pi) / YAW_CELL_RAD), np.floor(landing / POSITION_CELL_M),
    ]).astype(np.int64)  # fmt: skip
    _, _, cell_of = unique_first(_cell_keys(cells))
    votes = np.bincount(cell_of)
    best = np.argsort(-votes, kind="stable")[:count]
    hypotheses = []
    for cell in best:
        member = cell_of == cell
        heading = float(np.angle(np.exp(1j * yaw[member]).mean()))
        c, s = np.cos(heading), np.sin(heading)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        shift = np.append(np.median(landing[member], axis=0) - turn[:2, :2] @ centre_b, np.median(rise[member]))
        T = np.eye(4)
        T[:3, :3] = frame @ turn @ frame.T
        T[:3, 3] = frame @ shift
        hypotheses.append(T)
    return hypotheses


def _segments(xy: np.ndarray, *, ordered: bool) -> np.ndarray:
    """(P, 2) int64 node pairs whose horizontal distance lies in [``MIN_SEGMENT_M``, ``MAX_SEGMENT_M``]:
    i < j, and with ``ordered`` each pair also reversed."""
    pairs = cKDTree(xy).query_pairs(MAX_SEGMENT_M, output_type="ndarray").astype(np.int64).reshape(-1, 2)
    pairs = pairs[np.linalg.norm(xy[pairs[:, 1]] - xy[pairs[:, 0]], axis=1) >= MIN_SEGMENT_M]
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]  # query_pairs' order is the tree's: fix it
    return np.vstack([pairs, pairs[:, ::-1]]) if ordered else pairs


def _agreeing(
    seg_b: np.ndarray, seg_a: np.ndarray, labels_b: np.ndarray, labels_a: np.ndarray,
    local_b: np.ndarray, local_a: np.ndarray, tolerance_m: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(V,) rows into ``seg_b`` and (V,) rows into ``seg_a`` of the segment pairs that vote: same labels at
    both ends, horizontal lengths within ``tolerance_m``, both ends' vertical offsets within it. At most
    ``MAX_VOTES`` (B's segments thinned evenly)."""
    num_labels = int(max(labels_b.max(), labels_a.max())) + 1
    len_b = np.linalg.norm(local_b[seg_b[:, 1], :2] - local_b[seg_b[:, 0], :2], axis=1)
    len_a = np.linalg.norm(local_a[seg_a[:, 1], :2] - local_a[seg_a[:, 0], :2], axis=1)
    # A's segments sorted by (label pair, length): each B segment's partners are one contiguous range
    span = 2.0 * (MAX_SEGMENT_M + tolerance_m)
    key_a = (labels_a[seg_a[:, 0]] * num_labels + labels_a[seg_a[:, 1]]) * span + len_a
    key_b = (labels_b[seg_b[:, 0]] * num_labels + labels_b[seg_b[:, 1]]) * span + len_b
    order = np.argsort(key_a, kind="stable")
    lo = np.searchsorted(key_a[order], key_b - tolerance_m)
    hi = np.searchsorted(key_a[order], key_b + tolerance_m, side="right")
    per_b = hi - lo
    total = int(per_b.sum())
    if total > MAX_VOTES:
        keep = np.zeros(len(seg_b), dtype=bool)
        keep[np.unique(np.linspace(0, len(seg_b) - 1, max(1, len(seg_b) * MAX_VOTES // total)).astype(np.int64))] = True
        per_b = np.where(keep, per_b, 0)
        total = int(per_b.sum())
    rows_b = np.repeat(np.arange(len(seg_b)), per_b)
    starts = np.repeat(lo - (np.cumsum(per_b) - per_b), per_b)
    rows_a = order[starts + np.arange(total)]
    rise_first = local_a[seg_a[rows_a, 0], 2] - local_b[seg_b[rows_b, 0], 2]
    rise_second = local_a[seg_a[rows_a, 1], 2] - local_b[seg_b[rows_b, 1], 2]
    level = np.abs(rise_first - rise_second) < tolerance_m
    return rows_b[level], rows_a[level]


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """(V,) one int64 key per (V, 3) integer vote cell (heading, x, y): equal cells, equal keys."""
    shifted = cells - cells.min(axis=0)
    extent = shifted.max(axis=0) + 1
    return (shifted[:, 0] * extent[1] + shifted[:, 1]) * extent[2] + shifted[:, 2]
