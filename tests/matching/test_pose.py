"""Eq. 2 weighted least squares against an independent numerical minimisation, and its helpers."""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from shgm_slam.geometry.se3 import pose_error, so3_exp
from shgm_slam.matching.pose import (
    DEFAULT_UP,
    correspondence_weights,
    fit_pose,
    one_to_one,
    padded_correspondence_weights,
    refine_alignment,
    residuals_m,
    spread_m,
)

from .synthetic import random_pose


def _energy(T: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> float:
    """Eq. 2: (1 / N_p) sum_k W_k |q_k - R p_k - t|^2."""
    return float(np.mean(w * np.sum((q - p @ T[:3, :3].T - T[:3, 3]) ** 2, axis=1)))


def test_weighted_fit_equals_numerical_minimum_of_eq2():
    rng = np.random.default_rng(0)
    p = rng.uniform(-20, 20, (15, 3))
    T_true = random_pose(rng)
    q = p @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 1.0, p.shape)  # noisy: weights matter
    w = rng.uniform(0.1, 5.0, 15)
    T = fit_pose(p, q, w)

    def cost(x: np.ndarray) -> float:
        R = so3_exp(x[:3])
        return float(np.mean(w * np.sum((q - p @ R.T - x[3:]) ** 2, axis=1)))

    best = min(  # random starts: an independent search of the same minimum
        (minimize(cost, np.r_[rng.normal(0, 2, 3), q.mean(0) - p.mean(0)], method="BFGS") for _ in range(5)),
        key=lambda r: r.fun,
    )
    assert _energy(T, p, q, w) <= best.fun + 1e-9
    T_num = np.eye(4)
    T_num[:3, :3], T_num[:3, 3] = so3_exp(best.x[:3]), best.x[3:]
    dt, dr = pose_error(T, T_num)
    assert dt < 1e-4 and dr < 1e-4
    assert _energy(fit_pose(p, q, None), p, q, w) > _energy(T, p, q, w)  # unweighted is worse on Eq. 2


def test_gravity_aligned_fit_is_a_yaw_and_minimises_eq2_over_yaw():
    rng = np.random.default_rng(1)
    p = rng.uniform(-20, 20, (12, 3))
    T_true = random_pose(rng, gravity_aligned=True)
    q = p @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.5, p.shape)
    w = rng.uniform(0.5, 2.0, 12)
    T = fit_pose(p, q, w, gravity_aligned=True, up=DEFAULT_UP)
    np.testing.assert_allclose(T[:3, :3] @ DEFAULT_UP, DEFAULT_UP, atol=1e-12)  # rotation about up only
    for yaw in np.linspace(-np.pi, np.pi, 73):  # no yaw (with its optimal translation) does better
        R = so3_exp(DEFAULT_UP * yaw)
        t = np.sum(w[:, None] * (q - p @ R.T), axis=0) / w.sum()
        Ty = np.eye(4)
        Ty[:3, :3], Ty[:3, 3] = R, t
        assert _energy(T, p, q, w) <= _energy(Ty, p, q, w) + 1e-9


def test_padded_weights_equal_the_weights_of_each_row():
    rng = np.random.default_rng(8)
    for _ in range(50):
        b, m = int(rng.integers(1, 6)), int(rng.integers(1, 30))
        lengths = rng.integers(0, m + 1, b)
        sizes_a = rng.choice([0.0, -1.0, 2.0, 1e4], size=(b, m)) * rng.random((b, m)) ** int(rng.integers(0, 3))
        sizes_b = rng.uniform(0, 1e3, (b, m)) * (rng.random((b, m)) < 0.8)
        got = padded_correspondence_weights(sizes_a, sizes_b, lengths)
        for row, n in enumerate(lengths):
            np.testing.assert_array_equal(got[row, :n], correspondence_weights(sizes_a[row, :n], sizes_b[row, :n]))
            assert not got[row, n:].any()


def test_correspondence_weights_are_normalised_geometric_means():
    w = correspondence_weights(np.array([100.0, 400.0, 1e9, 1.0]), np.array([100.0, 100.0, 1e9, 1e-6]))
    raw = np.sqrt([1e4, 4e4, 1e18, 1e-6])
    np.testing.assert_allclose(w, np.clip(raw / np.median(raw), 0.1, 10.0))
    assert w.max() == 10.0 and w.min() == 0.1
    np.testing.assert_array_equal(correspondence_weights(np.zeros(3), np.zeros(3)), np.ones(3))


def test_one_to_one_keeps_the_best_candidate_per_node():
    rows_a = np.array([0, 0, 1, 2, 3])
    rows_b = np.array([5, 6, 6, 7, 7])
    residuals = np.array([0.5, 0.1, 0.2, 0.3, 0.4])
    keep = one_to_one(rows_a, rows_b, residuals, np.ones(5, bool))
    # a0: candidate 1 (0.1) beats 0; b6: candidate 1 beats 2; b7: candidate 3 (0.3) beats 4
    np.testing.assert_array_equal(keep, [False, True, False, True, False])


def test_refine_recovers_transform_and_rejects_outliers():
    rng = np.random.default_rng(2)
    p = rng.uniform(0, 50, (40, 3))
    T_true = random_pose(rng)
    q = p @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.05, p.shape)
    q[:8] += rng.uniform(20, 40, (8, 3))  # outliers
    T0 = T_true.copy()
    T0[:3, 3] += [1.0, -1.0, 0.5]  # a rough hypothesis
    rows = np.arange(40)
    out = refine_alignment(T0, p, q, rows, rows, None, threshold_m=5.0, iterations=5)
    np.testing.assert_array_equal(out.inliers, np.arange(40) >= 8)
    dt, dr = pose_error(out.T_a_b, T_true)
    assert dt < 0.1 and dr < 0.1
    assert out.rmse_m < 0.15
    np.testing.assert_allclose(out.rmse_m, np.sqrt(np.mean(residuals_m(out.T_a_b, p, q)[8:] ** 2)))


def test_spread_detects_degenerate_inliers():
    line = np.outer(np.linspace(0, 30, 10), [1.0, 0.0, 1.0])
    assert spread_m(line) < 1e-6  # collinear: rotation about the line is free
    assert spread_m(line, gravity_aligned=True) > 40  # but a horizontal line fixes the yaw
    vertical = np.outer(np.linspace(0, 30, 10), DEFAULT_UP)
    assert spread_m(vertical, gravity_aligned=True) < 1e-6
    square = np.array([[0, 0, 0], [20, 0, 0], [0, 0, 20], [20, 0, 20]], float)
    assert spread_m(square) > 19
    assert spread_m(square[:1]) == 0.0


def test_median_equals_np_median():
    from shgm_slam.matching.pose import _median

    rng = np.random.default_rng(0)
    for size in range(1, 40):
        values = rng.lognormal(size=size)
        assert _median(values) == np.median(values)
