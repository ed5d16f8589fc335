"""Pairwise consistency and clique hypotheses: brute-force references and known-transform recovery."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import pose_error
from shgm_slam.matching.clique import clique_hypotheses, consistency_matrix
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
