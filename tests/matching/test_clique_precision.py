"""Kilometre-scale maps against metre tolerances (issue 11): clique consistency in float64."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import make_pose, pose_error
from shgm_slam.matching.clique import clique_hypotheses, consistency_matrix, pairwise_distances
from shgm_slam.matching.pose import DEFAULT_UP

from .synthetic import correspondence_problem

SHIFT = np.array([5000.0, 3.0, -5000.0])  # 5 km east, 5 km south


def brute_force(pa: np.ndarray, pb: np.ndarray, eps: float) -> np.ndarray:
    da = np.linalg.norm(pa[:, None] - pa[None], axis=2)
    db = np.linalg.norm(pb[:, None] - pb[None], axis=2)
    ok = np.abs(da - db) < eps
    np.fill_diagonal(ok, False)
    return ok


def test_distances_at_a_5_km_extent_keep_millimetres():
    rng = np.random.default_rng(0)
    p = rng.uniform(-2500.0, 2500.0, (300, 3)) * [1.0, 0.01, 1.0]
    ref = np.linalg.norm(p[:, None] - p[None], axis=2)
    assert np.abs(pairwise_distances(p) - ref).max() < 1e-3  # float32 lost 1.4 m here
    assert np.abs(pairwise_distances(p + SHIFT) - ref).max() < 1e-3


def test_consistency_over_a_5_km_map_equals_the_float64_reference():
    prob = correspondence_problem(150, 0.5, seed=2, noise_m=1.0, extent_m=5000.0)
    pa, pb = prob["points_a"], prob["points_b"]
    rows = np.arange(len(pa))
    np.testing.assert_array_equal(consistency_matrix(pa, pb, rows, rows, 3.0, False), brute_force(pa, pb, 3.0))


@pytest.mark.parametrize("gravity_aligned", [False, True])
def test_a_graph_translated_by_5_km_gives_the_same_cliques(gravity_aligned):
    prob = correspondence_problem(25, 0.6, seed=4, gravity_aligned=gravity_aligned)
    args = dict(consistency_threshold_m=1.0, gravity_aligned=gravity_aligned, up=DEFAULT_UP)
    rows = (prob["rows_a"], prob["rows_b"])
    pa, pb = prob["points_a"], prob["points_b"]
    shift_a, shift_b = SHIFT, -0.5 * SHIFT
    M0 = consistency_matrix(pa, pb, *rows, 3.0, True, gravity_aligned, DEFAULT_UP)
    M1 = consistency_matrix(pa + shift_a, pb + shift_b, *rows, 3.0, True, gravity_aligned, DEFAULT_UP)
    np.testing.assert_array_equal(M0, M1)
    at_origin = clique_hypotheses(pb, pa, *rows, **args)
    shifted = clique_hypotheses(pb + shift_b, pa + shift_a, *rows, **args)
    assert len(at_origin) == len(shifted) > 0
    for T0, T1 in zip(at_origin, shifted, strict=True):  # T1 = shift_a · T0 · shift_b⁻¹
        expected = make_pose(np.eye(3), shift_a) @ T0 @ make_pose(np.eye(3), -shift_b)
        dt, dr = pose_error(T1, expected)
        assert dt < 1e-3 and dr < 1e-3
    dt, dr = pose_error(at_origin[0], prob["T_a_b"])
    assert dt < 0.3 and dr < 0.3
