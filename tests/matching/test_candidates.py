"""Candidate selection modes over a hand-made score matrix, and same-label masking."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from shgm_slam.config import CandidateMode, DescriptorConfig, MatchingConfig
from shgm_slam.descriptors import compute_descriptors
from shgm_slam.matching.candidates import match_candidates, select_candidates
from shgm_slam.types import GraphArrays

# rows = nodes of A, columns = nodes of B
SCORES = sp.csr_matrix(
    np.array(
        [
            [0.90, 0.60, 0.00],
            [0.80, 0.95, 0.40],
            [0.70, 0.55, 0.45],
            [0.00, 0.97, 0.30],
        ]
    )
)


def _pairs(c) -> list[tuple[int, int]]:
    return list(zip(c.rows_a.tolist(), c.rows_b.tolist(), strict=True))


def test_all_keeps_every_pair_strictly_above_threshold_sorted_by_score():
    c = select_candidates(SCORES, CandidateMode.ALL, threshold=0.55)
    assert _pairs(c) == [(3, 1), (1, 1), (0, 0), (1, 0), (2, 0), (0, 1)]  # 0.55 itself is not > 0.55
    assert np.all(np.diff(c.scores) <= 0)


def test_best_is_the_best_node_of_a_for_each_node_of_b():
    c = select_candidates(SCORES, CandidateMode.BEST, threshold=0.35)
    assert sorted(_pairs(c)) == [(0, 0), (2, 2), (3, 1)]


def test_mutual_needs_best_both_ways():
    c = select_candidates(SCORES, CandidateMode.MUTUAL, threshold=0.35)
    # (0,0): best of column 0 and of row 0; (3,1): best of column 1 and of row 3;
    # (2,2): best of column 2 but row 2's best is column 0
    assert sorted(_pairs(c)) == [(0, 0), (3, 1)]


def test_top_k_keeps_k_best_per_node_of_b():
    c = select_candidates(SCORES, CandidateMode.TOP_K, threshold=0.35, top_k=2)
    assert sorted(_pairs(c)) == [(0, 0), (1, 0), (1, 1), (1, 2), (2, 2), (3, 1)]
    assert len(select_candidates(SCORES, CandidateMode.TOP_K, 0.0, top_k=10)) == SCORES.nnz


def test_nothing_above_threshold_gives_no_candidates():
    c = select_candidates(SCORES, CandidateMode.ALL, threshold=0.99)
    assert len(c) == 0 and c.rows_a.dtype == np.int64


def _graph(labels, edges) -> GraphArrays:
    n = len(labels)
    return GraphArrays(np.arange(n), np.asarray(labels), np.zeros((n, 3)), np.ones(n), np.asarray(edges))


@pytest.mark.parametrize("same_label_only", [True, False])
def test_same_label_option(same_label_only):
    # a star: centre label 2 with leaves labelled 5; a second star with centre label 8, same leaves
    g = _graph([2, 5, 5, 5, 8, 5, 5, 5], [[0, 1], [0, 2], [0, 3], [4, 5], [4, 6], [4, 7]])
    d = compute_descriptors(g, DescriptorConfig(path_length=2))
    cfg = MatchingConfig(
        candidate_mode=CandidateMode.ALL, same_label_only=same_label_only, score_threshold=0.5
    )
    c = match_candidates(d, d, cfg)
    cross = g.label_ids[c.rows_a] != g.label_ids[c.rows_b]
    assert cross.any() != same_label_only  # centres 0 and 4 (labels 2, 8) match only across labels
