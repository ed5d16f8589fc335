"""Pairwise consistency + maximum clique: brute-force references and known-transform recovery."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import pose_error
from shgm_slam.matching.clique import clique_alignment, consistency_matrix, max_clique
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


def test_max_clique_matches_exact_search_on_planted_cliques():
    nx = pytest.importorskip("networkx")
    rng = np.random.default_rng(1)
    for trial in range(6):
        k = 150
        A = np.triu(rng.random((k, k)) < 0.08, 1)
        planted = rng.choice(k, 6 + 2 * trial, replace=False)
        A[np.ix_(planted, planted)] = True
        A = np.triu(A, 1)
        A = A | A.T
        clique = max_clique(A)
        assert np.all(A[np.ix_(clique, clique)] | np.eye(clique.size, dtype=bool))  # it is a clique
        exact = max(len(c) for c in nx.find_cliques(nx.from_numpy_array(A.astype(np.uint8))))
        assert clique.size == exact
    assert max_clique(np.zeros((0, 0), bool)).size == 0
    within = np.ones(150, bool)
    within[planted] = False
    assert not np.isin(max_clique(A, within=within), planted).any()


@pytest.mark.parametrize("outlier_fraction", [0.6, 0.9])
@pytest.mark.parametrize("gravity_aligned", [False, True])
def test_clique_recovers_known_transform(outlier_fraction, gravity_aligned):
    prob = correspondence_problem(25, outlier_fraction, seed=4, gravity_aligned=gravity_aligned)
    out = clique_alignment(
        prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"],
        consistency_threshold_m=1.0, gravity_aligned=gravity_aligned, up=DEFAULT_UP,
    )  # fmt: skip
    assert out is not None
    dt, dr = pose_error(out.T_a_b, prob["T_a_b"])
    assert dt < 0.3 and dr < 0.3
    assert out.inliers[prob["inlier"]].mean() > 0.9
    assert out.inliers[~prob["inlier"]].sum() <= 2
    assert out.support >= 20 and out.rival_support <= 6


def test_candidate_cap_limits_the_search_but_not_the_inliers():
    prob = correspondence_problem(30, 0.6, seed=5)
    order = np.argsort(~prob["inlier"], kind="stable")  # the "best scored" 40 hold 30 inliers
    args = [prob[k][order] for k in ("points_b", "points_a", "rows_a", "rows_b")]
    out = clique_alignment(*args, consistency_threshold_m=1.0, max_candidates=12)
    assert out is not None and out.support == 12
    assert out.inliers[:30].all()  # inliers re-selected among all candidates


def test_no_clique_of_three_gives_none():
    pa = np.array([[0, 0, 0], [10, 0, 0], [0, 0, 10.0]])
    pb = np.array([[0, 0, 0], [30, 0, 0], [0, 0, 55.0]])
    assert clique_alignment(pb, pa, np.arange(3), np.arange(3)) is None


def test_refined_supports_are_reported_for_winner_and_rival():
    prob = correspondence_problem(25, 0.6, seed=4)
    out = clique_alignment(
        prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"], consistency_threshold_m=1.0
    )
    assert out is not None
    assert out.inlier_support == out.num_inliers >= 20
    assert out.rival_inlier_support <= 6  # outliers are random: no competing alignment
    assert out.inlier_support >= 2.5 * out.rival_inlier_support
