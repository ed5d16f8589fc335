"""Alg. 2 RANSAC recovers a known transform from outlier-ridden candidates."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import pose_error
from shgm_slam.matching.pose import fit_pose
from shgm_slam.matching.ransac import ransac_alignment, squared_residuals

from .synthetic import correspondence_problem, random_pose


def test_squared_residuals_match_direct_evaluation():
    rng = np.random.default_rng(0)
    p = rng.uniform(-300, 300, (50, 3))
    q = rng.uniform(-300, 300, (50, 3))
    T = np.stack([random_pose(rng, translation_m=500) for _ in range(7)])
    direct = (
        np.linalg.norm(q[None] - (np.einsum("hij,kj->hki", T[:, :3, :3], p) + T[:, None, :3, 3]), axis=2) ** 2
    )
    np.testing.assert_allclose(squared_residuals(T, p, q), direct, rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize(("outlier_fraction", "iterations"), [(0.6, 1000), (0.9, 20000)])
def test_ransac_recovers_known_transform(outlier_fraction, iterations):
    """60 % outliers with the paper's 1000 iterations; 90 % needs ~ln(0.01)/ln(1-0.1^4) = 46k for 99 %,
    so 20000 iterations (86 %) with a fixed seed."""
    prob = correspondence_problem(30, outlier_fraction, seed=1)
    out = ransac_alignment(
        prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"],
        iterations=iterations, inlier_threshold_m=2.0, refine_iterations=3, seed=0,
    )  # fmt: skip
    assert out is not None
    dt, dr = pose_error(out.T_a_b, prob["T_a_b"])
    assert dt < 0.3 and dr < 0.3
    assert out.inliers[prob["inlier"]].mean() > 0.9  # true inliers found
    assert out.inliers[~prob["inlier"]].sum() <= 2  # few chance outliers inside 2 m
    assert out.support >= 27 and out.rival_support < out.support / 2


def test_ransac_is_deterministic_and_needs_three_candidates():
    prob = correspondence_problem(20, 0.5, seed=2)
    args = (prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"])
    first = ransac_alignment(*args, iterations=200, seed=7)
    second = ransac_alignment(*args, iterations=200, seed=7)
    np.testing.assert_array_equal(first.T_a_b, second.T_a_b)
    np.testing.assert_array_equal(first.inliers, second.inliers)
    assert ransac_alignment(*(x[:2] for x in args)) is None


def test_weights_enter_the_refinement():
    prob = correspondence_problem(20, 0.0, seed=3, noise_m=1.0)
    w = np.random.default_rng(0).uniform(0.1, 10.0, 20)
    out = ransac_alignment(prob["points_b"], prob["points_a"], prob["rows_a"], prob["rows_b"], w,
                           iterations=100, inlier_threshold_m=10.0, refine_iterations=3)  # fmt: skip
    np.testing.assert_allclose(out.T_a_b, fit_pose(prob["points_b"], prob["points_a"], w), atol=1e-9)
