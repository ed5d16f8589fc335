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


@pytest.mark.parametrize("mode", list(CandidateMode))
def test_ties_are_broken_by_node_rows_whatever_the_entry_order(mode):
    """Equal scores: the lower row of A wins (top-k, best), whatever order the sparse entries come in."""
    rng = np.random.default_rng(0)
    dense = rng.choice([0.6, 0.8], size=(12, 9))  # many exact ties
    expected = select_candidates(sp.coo_matrix(dense), mode, 0.5, top_k=3)
    coo = sp.coo_matrix(dense)
    for _ in range(5):
        perm = rng.permutation(coo.nnz)
        shuffled = sp.coo_matrix((coo.data[perm], (coo.row[perm], coo.col[perm])), shape=dense.shape)
        got = select_candidates(shuffled, mode, 0.5, top_k=3)
        assert _pairs(got) == _pairs(expected)
    if mode is CandidateMode.BEST:
        for b in range(dense.shape[1]):  # the winner of each column is the first row with its maximum
            assert (int(expected.rows_a[expected.rows_b == b][0]), b) == (int(np.argmax(dense[:, b])), b)


def test_fill_adds_same_label_pairs_round_robin_up_to_the_budget():
    from shgm_slam.matching.candidates import fill_same_label

    labels_a, labels_b = np.array([5, 5, 8, 8, 8]), np.array([8, 5, 8])
    chosen = select_candidates(sp.csr_matrix(np.zeros((5, 3))), CandidateMode.TOP_K, 0.5, 2)
    no_scores = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    filled = fill_same_label(chosen, no_scores, labels_a, labels_b, budget=5)
    assert len(filled) == 5
    assert np.all(labels_a[filled.rows_a] == labels_b[filled.rows_b])
    assert len(set(_pairs(filled))) == 5
    assert sorted(filled.rows_b[:3].tolist()) == [0, 1, 2]  # every node of B gets its first partner first
    again = fill_same_label(chosen, no_scores, labels_a, labels_b, budget=5)
    assert _pairs(again) == _pairs(filled)
