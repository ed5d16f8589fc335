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

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import run_starts
from shgm_slam.geometry.se3 import yaw_basis

MIN_SEGMENT_M = 10.0
"""Shortest segment (horizontal node-to-node distance) that votes, metres: with 2 m of centroid noise a
10 m segment fixes the heading to about 15 degrees."""

MAX_SEGMENT_M = 40.0
"""Longest segment that votes, metres (the overlap of two drives is a few street blocks)."""

YAW_CELL_RAD = np.radians(10.0)
"""Heading width of a vote cell."""

POSITION_CELL_M = 6.0
"""Horizontal width of a vote cell (where B's centroid lands in A), metres."""

MAX_VOTES = 10_000
"""Most votes cast per match (segments of B thinned evenly beyond it): the sparse benchmark's tuning pairs
cast 2500 (median; 20 of 800 more than 10 000); a rendered city's graph windows of ~200 nodes many times as
many, and thinned they cost a few milliseconds (tuning pairs localized with a cap of 5000 / 10000 / 20000:
329 / 331 / 331 of 400)."""

MAX_SEGMENTS = 20_000
"""Most segments kept per graph (thinned evenly beyond it): bounds the sort of a kilometre-long graph's."""


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
    frame = yaw_basis(up).T  # columns: two horizontal axes, up
    local_b = np.asarray(points_b, dtype=np.float64) @ frame
    local_a = np.asarray(points_a, dtype=np.float64) @ frame
    seg_b = _Segments.of(local_b, np.asarray(labels_b, dtype=np.int64), ordered=False)
    seg_a = _Segments.of(local_a, np.asarray(labels_a, dtype=np.int64), ordered=True)  # B's (i, j) onto A's (l, k)
    if not (len(seg_b) and len(seg_a)) or count < 1:
        return []
    votes_b, votes_a, rise = _agreeing(seg_b, seg_a, tolerance_m)
    if votes_b.size == 0:
        return []
    yaw = seg_a.heading[votes_a] - seg_b.heading[votes_b]
    cos, sin = np.cos(yaw), np.sin(yaw)
    centre_b = local_b[:, :2].mean(axis=0)
    rel = centre_b - seg_b.mid_xy[votes_b]  # B's centroid seen from the segment's midpoint, turned by the yaw
    turned = np.column_stack([cos * rel[:, 0] - sin * rel[:, 1], sin * rel[:, 0] + cos * rel[:, 1]])
    landing = seg_a.mid_xy[votes_a] + turned
    keys = _cell_keys(
        np.floor(np.mod(yaw, 2.0 * np.pi) / YAW_CELL_RAD).astype(np.int64),
        np.floor(landing[:, 0] / POSITION_CELL_M).astype(np.int64),
        np.floor(landing[:, 1] / POSITION_CELL_M).astype(np.int64),
    )
    by_cell = np.argsort(keys, kind="stable")  # each cell's votes together, in vote order
    starts = np.flatnonzero(run_starts(keys[by_cell]))
    votes = np.diff(starts, append=keys.size)  # per cell, cells by ascending key
    hypotheses = []
    for cell in np.argsort(-votes, kind="stable")[:count].tolist():
        member = by_cell[starts[cell] : starts[cell] + votes[cell]]
        heading = float(np.angle(np.exp(1j * yaw[member]).mean()))
        c, s = np.cos(heading), np.sin(heading)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        middle = _column_medians(np.column_stack([landing[member], rise[member]]))  # (x, y, rise)
        shift = np.append(middle[:2] - turn[:2, :2] @ centre_b, middle[2])
        T = np.eye(4)
        T[:3, :3] = frame @ turn @ frame.T
        T[:3, 3] = frame @ shift
        hypotheses.append(T)
    return hypotheses


@dataclass(frozen=True)
class _Segments:
    """A graph's voting segments: node pairs whose horizontal distance lies in [``MIN_SEGMENT_M``,
    ``MAX_SEGMENT_M``], in the vertical frame (x, y horizontal, z up)."""

    labels: np.ndarray  # (P, 2) int64 labels of the two ends
    length_m: np.ndarray  # (P,) horizontal length
    heading: np.ndarray  # (P,) horizontal direction from the first end to the second, radians
    mid_xy: np.ndarray  # (P, 2) horizontal midpoint
    heights: tuple[np.ndarray, np.ndarray]  # (P,) the first ends' heights, (P,) the second ends'

    @classmethod
    def of(cls, local_xyz: np.ndarray, label_ids: np.ndarray, *, ordered: bool) -> _Segments:
        """Segments of (N, 3) nodes (vertical frame): i < j, and with ``ordered`` each also reversed."""
        xy = local_xyz[:, :2]
        n = xy.shape[0]
        ends = cKDTree(xy).query_pairs(MAX_SEGMENT_M, output_type="ndarray").astype(np.int64).reshape(-1, 2)
        # query_pairs' order is the tree's: fix it, by (i, j) with i < j (one key i * N + j, one sort)
        key = np.sort(ends[:, 0] * n + ends[:, 1])
        ends = np.stack([key // max(n, 1), key % max(n, 1)], axis=1)
        step = xy[ends[:, 1]] - xy[ends[:, 0]]
        length = np.hypot(step[:, 0], step[:, 1])
        keep = np.flatnonzero(length >= MIN_SEGMENT_M)
        if keep.size > MAX_SEGMENTS:
            keep = keep[np.unique(np.linspace(0, keep.size - 1, MAX_SEGMENTS).astype(np.int64))]
        ends, step, length = ends[keep], step[keep], length[keep]
        heading = np.arctan2(step[:, 1], step[:, 0])
        if ordered:
            ends, length = np.vstack([ends, ends[:, ::-1]]), np.concatenate([length, length])
            heading = np.concatenate([heading, heading + np.pi])
        mid = 0.5 * (xy[ends[:, 0]] + xy[ends[:, 1]])
        return cls(label_ids[ends], length, heading, mid, (local_xyz[ends[:, 0], 2], local_xyz[ends[:, 1], 2]))

    def __len__(self) -> int:
        return int(self.length_m.shape[0])


def _agreeing(seg_b: _Segments, seg_a: _Segments, tolerance_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V,) rows of ``seg_b`` and (V,) rows of ``seg_a`` of the segment pairs that vote: same labels at both
    ends, horizontal lengths within ``tolerance_m``, both ends' vertical offsets within it. At most
    ``MAX_VOTES`` (B's segments thinned evenly). Also (V,) each vote's rise: the mean vertical offset of its
    two ends (A's height less B's), metres."""
    num_labels = int(max(seg_b.labels.max(), seg_a.labels.max())) + 1
    # A's segments sorted by (label pair, length): each B segment's partners are one contiguous range
    span = 2.0 * (MAX_SEGMENT_M + tolerance_m)
    key_a = (seg_a.labels[:, 0] * num_labels + seg_a.labels[:, 1]) * span + seg_a.length_m
    key_b = (seg_b.labels[:, 0] * num_labels + seg_b.labels[:, 1]) * span + seg_b.length_m
    order = np.argsort(key_a, kind="stable")
    sorted_a = key_a[order]
    lo = np.searchsorted(sorted_a, key_b - tolerance_m)
    per_b = np.searchsorted(sorted_a, key_b + tolerance_m, side="right") - lo
    total = int(per_b.sum())
    if total > MAX_VOTES:
        keep = np.zeros(len(seg_b), dtype=bool)
        keep[np.unique(np.linspace(0, len(seg_b) - 1, max(1, len(seg_b) * MAX_VOTES // total)).astype(np.int64))] = True
        per_b = np.where(keep, per_b, 0)
        total = int(per_b.sum())
    rows_b = np.repeat(np.arange(len(seg_b)), per_b)
    starts = np.repeat(lo - (np.cumsum(per_b) - per_b), per_b)
    rows_a = order[starts + np.arange(total)]
    rise_first = seg_a.heights[0][rows_a] - seg_b.heights[0][rows_b]
    rise_second = seg_a.heights[1][rows_a] - seg_b.heights[1][rows_b]
    level = np.abs(rise_first - rise_second) < tolerance_m
    return rows_b[level], rows_a[level], 0.5 * (rise_first[level] + rise_second[level])


def _column_medians(values: np.ndarray) -> np.ndarray:
    """(C,) ``np.median(values, axis=0)`` of an (N, C) array with N >= 1 and no NaN, by one sort (the same
    values: the middle one, or the mean of the middle two; ``np.median`` costs ~10x more on a few votes)."""
    s = np.sort(values, axis=0)
    half = s.shape[0] // 2
    return s[half] if s.shape[0] % 2 else 0.5 * (s[half - 1] + s[half])


def _cell_keys(heading: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(V,) one int64 key per integer vote cell, given as (V,) heading, x and y cell indices: equal cells,
    equal keys."""
    shifted = [c - c.min() for c in (heading, x, y)]
    extent = [int(c.max()) + 1 for c in shifted]
    return (shifted[0] * extent[1] + shifted[1]) * extent[2] + shifted[2]
