"""Matching candidates from descriptor scores (Eq. 1 and the first loop of Alg. 2).

All node pairs are scored by one sparse product (``descriptors.similarity``); pairs scoring above
the threshold are kept according to ``CandidateMode``: every pair (ALL, Alg. 2), the best node of A
for each node of B (BEST, the authors' release), mutual best pairs (MUTUAL) or the k best nodes of A
for each node of B (TOP_K, what the maximum-clique outlier rejection wants).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from shgm_slam.config import CandidateMode, MatchingConfig
from shgm_slam.descriptors import NodeDescriptors, similarity


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


def _rank_in_groups(groups: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Rank (0 = best) of each entry among the entries of its group by descending score.

    One sort of the composite key ``group + (1 - score) / 2`` (scores lie in [0, 1]).
    """
    order = np.argsort(groups + 0.5 * (1.0 - scores))
    sorted_groups = groups[order]
    first = np.searchsorted(sorted_groups, sorted_groups, side="left")
    rank = np.empty(groups.size, dtype=np.int64)
    rank[order] = np.arange(groups.size) - first
    return rank


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
    keep = S.data > threshold
    rows_a, rows_b, s = S.row[keep].astype(np.int64), S.col[keep].astype(np.int64), S.data[keep]
    if s.size == 0:
        return Candidates.empty()
    if mode is CandidateMode.ALL:
        mask = np.ones(s.size, dtype=bool)
    elif mode is CandidateMode.BEST:
        mask = _rank_in_groups(rows_b, s) == 0
    elif mode is CandidateMode.TOP_K:
        mask = _rank_in_groups(rows_b, s) < top_k
    elif mode is CandidateMode.MUTUAL:
        mask = (_rank_in_groups(rows_b, s) == 0) & (_rank_in_groups(rows_a, s) == 0)
    else:  # pragma: no cover - exhaustive over the enum
        raise ValueError(f"unknown candidate mode {mode}")
    order = np.argsort(-s[mask], kind="stable")
    return Candidates(rows_a[mask][order], rows_b[mask][order], s[mask][order])


def match_candidates(a: NodeDescriptors, b: NodeDescriptors, cfg: MatchingConfig) -> Candidates:
    """Eq. 1 scores between two graphs' descriptors, then the candidate selection of ``cfg``."""
    scores = similarity(a, b, same_label_only=cfg.same_label_only)
    return select_candidates(scores, cfg.candidate_mode, cfg.score_threshold, cfg.top_k)
