"""Matching candidates from descriptor scores (Eq. 1 and the first loop of Alg. 2).

All node pairs are scored by one sparse product (``descriptors.score_entries``); pairs scoring above
the threshold are kept according to ``CandidateMode``: every pair (ALL, Alg. 2), the best node of A
for each node of B (BEST, the authors' release), mutual best pairs (MUTUAL) or the k best nodes of A
for each node of B (TOP_K, what the maximum-clique outlier rejection wants).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from shgm_slam.config import CandidateMode, MatchingConfig
from shgm_slam.descriptors import NodeDescriptors, ScoreEntries, score_entries


@dataclass(frozen=True)
class Candidates:
    """Candidate correspondences, sorted by descending score.

    Attributes:
        rows_a: (K,) int64 row indices into graph A.
        rows_b: (K,) int64 row indices into graph B.
        scores: (K,) float64 Eq. 1 scores in (threshold, 1].
    """

    rows_a: np.ndarray
    rows_b: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def take(self, index: np.ndarray) -> Candidates:
        """The candidates at ``index`` (integer indices or a boolean mask)."""
        return Candidates(self.rows_a[index], self.rows_b[index], self.scores[index])

    def best(self, count: int) -> Candidates:
        """The ``count`` highest-scoring candidates."""
        return self if count >= len(self) else self.take(np.arange(count))

    @staticmethod
    def empty() -> Candidates:
        return Candidates(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


def _rank_in_groups(groups: np.ndarray, scores: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Rank (0 = best) of each entry among the entries of its group by descending score.

    Ties are broken by ascending ``others`` (the node on the other side), so the ranking does not depend
    on the order of the entries: one lexsort on (group, -score, other).
    """
    order = np.lexsort((others, -scores, groups))
    sorted_groups = groups[order]
    first = np.searchsorted(sorted_groups, sorted_groups, side="left")
    rank = np.empty(groups.size, dtype=np.int64)
    rank[order] = np.arange(groups.size) - first
    return rank


def _by_score(rows_a: np.ndarray, rows_b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Order of candidates by descending score, ties by (row_b, row_a): independent of the input order."""
    return np.lexsort((rows_a, rows_b, -s))


def select_candidates(
    scores: sp.spmatrix, mode: CandidateMode, threshold: float, top_k: int = 1
) -> Candidates:
    """Pick candidates from an (N_a, N_b) sparse score matrix.

    Args:
        scores: Eq. 1 scores; absent entries count as 0.
        mode: ALL, BEST (per node of B), MUTUAL (best both ways) or TOP_K (k best per node of B).
        threshold: keep only scores strictly above this (T_s).
        top_k: k of TOP_K.
    """
    S = sp.coo_matrix(scores)
    return select_entries((S.row.astype(np.int64), S.col.astype(np.int64), S.data), mode, threshold, top_k)


def select_entries(entries: ScoreEntries, mode: CandidateMode, threshold: float, top_k: int = 1) -> Candidates:
    """``select_candidates`` from the (rows_a, rows_b, scores) entries of the score matrix (any order, no
    pair twice): the result does not depend on their order."""
    keep = entries[2] > threshold
    rows_a, rows_b, s = entries[0][keep], entries[1][keep], entries[2][keep]
    if s.size == 0:
        return Candidates.empty()
    if mode is CandidateMode.ALL:
        mask = np.ones(s.size, dtype=bool)
    elif mode is CandidateMode.BEST:
        mask = _rank_in_groups(rows_b, s, rows_a) == 0
    elif mode is CandidateMode.TOP_K:
        mask = _rank_in_groups(rows_b, s, rows_a) < top_k
    elif mode is CandidateMode.MUTUAL:
        mask = (_rank_in_groups(rows_b, s, rows_a) == 0) & (_rank_in_groups(rows_a, s, rows_b) == 0)
    else:  # pragma: no cover - exhaustive over the enum
        raise ValueError(f"unknown candidate mode {mode}")
    rows_a, rows_b, s = rows_a[mask], rows_b[mask], s[mask]
    order = _by_score(rows_a, rows_b, s)
    return Candidates(rows_a[order], rows_b[order], s[order])


MAX_FILL_PAIRS = 4_000_000
"""Graphs with more node pairs than this are not filled (their descriptors carry enough candidates)."""


def fill_same_label(
    cands: Candidates, scores: ScoreEntries, labels_a: np.ndarray, labels_b: np.ndarray, budget: int
) -> Candidates:
    """Append further same-label pairs to ``cands`` until there are ``budget`` candidates.

    Sparse maps miss many objects, so a node's neighbourhood, and with it its descriptor, differs between
    the robots and the true partner often scores 0 (verified later against the whole overlap, not trusted).
    The extra pairs come round-robin over B's nodes: every node's best remaining partner first (by
    score, ties by row), then every node's second, and so on.

    Args:
        cands: the selected candidates (kept first, in their order).
        scores: the (rows_a, rows_b, scores) entries of the (N_a, N_b) Eq. 1 scores (absent = 0).
        labels_a, labels_b: (N_a,), (N_b,) train ids.
        budget: total candidates wanted.
    """
    n_a, n_b = labels_a.shape[0], labels_b.shape[0]
    if len(cands) >= budget or n_a * n_b > MAX_FILL_PAIRS:
        return cands
    same = labels_a[:, None] == labels_b[None, :]
    same[cands.rows_a, cands.rows_b] = False
    rows_a, rows_b = np.nonzero(same)
    if rows_a.size == 0:
        return cands
    dense = np.zeros((n_a, n_b))  # n_a * n_b is at most MAX_FILL_PAIRS
    dense[scores[0], scores[1]] = scores[2]
    s = dense[rows_a, rows_b]
    rank = _rank_in_groups(rows_b, s, rows_a)
    order = np.lexsort((rows_a, -s, rows_b, rank))[: budget - len(cands)]
    return Candidates(
        np.concatenate([cands.rows_a, rows_a[order]]),
        np.concatenate([cands.rows_b, rows_b[order]]),
        np.concatenate([cands.scores, s[order]]),
    )


def match_candidates(
    a: NodeDescriptors,
    b: NodeDescriptors,
    cfg: MatchingConfig,
    labels_a: np.ndarray | None = None,
    labels_b: np.ndarray | None = None,
) -> Candidates:
    """Eq. 1 scores between two graphs' descriptors, then the candidate selection of ``cfg``; with
    ``cfg.fill_candidates`` and both graphs' (N,) train ids, filled up to ``cfg.max_candidates``."""
    scores = score_entries(a, b, same_label_only=cfg.same_label_only)
    cands = select_entries(scores, cfg.candidate_mode, cfg.score_threshold, cfg.top_k)
    if cfg.fill_candidates and labels_a is not None and labels_b is not None:
        cands = fill_same_label(cands, scores, labels_a, labels_b, cfg.max_candidates)
    return cands
