"""Pairwise consistency and clique hypotheses: brute-force references and known-transform recovery."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import pose_error
from shgm_slam.matching.clique import _bit_rows, _greedy_clique, clique_hypotheses, consistency_matrix
from shgm_slam.matching.pose import DEFAULT_UP

from .synthetic import correspondence_problem


@pytest.mark.parametrize("gravity_aligned", [False, True])
def test_consistency_matrix_equals_pairwise_loops(gravity_aligned):
    rng = np.random.default_rng(0)
    k = 40
    pa, pb = rng.uniform(0, 30, (k, 3)), rng.uniform(0, 30, (k, 3))
    rows_a, rows_b = rng.integers(0, 25, k), rng.integers(0, 25, k)
    M = consistency_matrix(pa, pb, rows_a, rows_b, 3.0, True, gravity_aligned, DEFAULT_UP)
    up = DEFAULT_UP
    for i in range(k):
        for j in range(k):
            da, db = pa[i] - pa[j], pb[i] - pb[j]
            if gravity_aligned:
                ha, hb = da @ up, db @ up
                ok = (
                    abs(np.linalg.norm(da - ha * up) - np.linalg.norm(db - hb * up)) < 3.0
                    and abs(ha - hb) < 3.0
                )
            else:
                ok = abs(np.linalg.norm(da) - np.linalg.norm(db)) < 3.0
            ok = ok and i != j and rows_a[i] != rows_a[j] and rows_b[i] != rows_b[j]
            assert M[i, j] == ok, (i, j)


def _loop_consistency(pa, pb, rows_a, rows_b, eps, distinct, gravity_aligned, up=DEFAULT_UP):
    k = len(pa)
    M = np.zeros((k, k), dtype=bool)
    for i in range(k):
        for j in range(k):
            da, db = pa[i] - pa[j], pb[i] - pb[j]
            ha, hb = da @ up, db @ up
            if gravity_aligned:
                ok = abs(np.linalg.norm(da - ha * up) - np.linalg.norm(db - hb * up)) < eps and abs(ha - hb) < eps
            else:
                ok = abs(np.linalg.norm(da) - np.linalg.norm(db)) < eps
            same = rows_a[i] == rows_a[j] or rows_b[i] == rows_b[j]
            M[i, j] = ok and i != j and not (distinct and same)
    return M


@pytest.mark.parametrize("distinct", [True, False])
@pytest.mark.parametrize("gravity_aligned", [False, True])
def test_consistency_of_candidates_sharing_nodes_equals_pairwise_loops(gravity_aligned, distinct):
    """The matcher's case: candidates are node pairs, so their distances come from per-node tables."""
    rng = np.random.default_rng(1)
    nodes_a, nodes_b = rng.uniform(0, 30, (12, 3)), rng.uniform(0, 30, (15, 3))
    rows_a, rows_b = rng.integers(0, 12, 150), rng.integers(0, 15, 150)
    pa, pb = nodes_a[rows_a], nodes_b[rows_b]
    M = consistency_matrix(pa, pb, rows_a, rows_b, 3.0, distinct, gravity_aligned, DEFAULT_UP)
    np.testing.assert_array_equal(M, _loop_consistency(pa, pb, rows_a, rows_b, 3.0, distinct, gravity_aligned))


def _reference_greedy_clique(adjacency, seed, beat):
    """The greedy clique on bool matrices (the definition ``_greedy_clique`` implements on bit sets)."""
    clique = [seed]
    cand = np.flatnonzero(adjacency[seed])
    sub = adjacency[cand][:, cand]
    while cand.size:
        if len(clique) + cand.size <= beat:
            return []
        degree = sub.sum(axis=1)
        universal = degree == cand.size - 1
        if universal.any():
            clique.extend(cand[universal].tolist())
            keep = ~universal
        else:
            v = int(np.argmax(degree))
            clique.append(int(cand[v]))
            keep = sub[v]
        cand, sub = cand[keep], sub[keep][:, keep]
    return clique if len(clique) > beat else []


@pytest.mark.parametrize("size", [1, 40, 130])
def test_greedy_clique_on_bit_sets_equals_the_matrix_reference(size):
    rng = np.random.default_rng(size)
    for density in (0.2, 0.6, 0.95):
        adjacency = rng.random((size, size)) < density
        adjacency &= adjacency.T
        np.fill_diagonal(adjacency, False)
        rows = _bit_rows(adjacency)
        for seed in range(size):
            for beat in (2, 4):
                got = _greedy_clique(adjacency, rows, seed, beat).tolist()
                assert got == _reference_greedy_clique(adjacency, seed, beat), (density, seed, beat)


@pytest.mark.parametrize("outlier_fraction", [0.6, 0.9])
@pytest.mark.parametrize("gravity_aligned", [False, True])
def test_largest_clique_hypothesis_recovers_known_transform(outlier_fraction, gravity_aligned):
    prob = correspondence_problem(25, outlier_fraction, seed=4, gravity_aligned=gravity_aligned)
    hyps = clique_hypotheses(
        prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"],
        consistency_threshold_m=1.0, gravity_aligned=gravity_aligned, up=DEFAULT_UP,
    )  # fmt: skip
    assert hyps
    dt, dr = pose_error(hyps[0], prob["T_a_b"])
    assert dt < 0.3 and dr < 0.3


def test_candidate_cap_limits_the_search():
    prob = correspondence_problem(30, 0.6, seed=5)
    order = np.argsort(~prob["inlier"], kind="stable")  # the "best scored" candidates are inliers
    args = [prob[k][order] for k in ("points_b", "points_a", "rows_a", "rows_b")]
    hyps = clique_hypotheses(*args, consistency_threshold_m=1.0, max_candidates=12)
    assert hyps
    assert pose_error(hyps[0], prob["T_a_b"])[0] < 0.5


def test_no_clique_of_three_gives_no_hypothesis():
    pa = np.array([[0, 0, 0], [10, 0, 0], [0, 0, 10.0]])
    pb = np.array([[0, 0, 0], [30, 0, 0], [0, 0, 55.0]])
    assert clique_hypotheses(pb, pa, np.arange(3), np.arange(3)) == []
