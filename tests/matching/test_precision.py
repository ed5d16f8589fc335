"""The precision an accepted alignment reports (``matching.precision``): its covariance predicts the spread of the
fit over noise draws, and the error it predicts at a far point is the error that point gets."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import kabsch, kabsch_yaw, make_pose, rot_z, so3_exp, transform_points
from shgm_slam.matching.precision import alignment_covariance, predicted_error_m

UP = np.array([0.0, 0.0, 1.0])


def _street(rng: np.random.Generator, n: int = 14) -> np.ndarray:
    """(n, 3) objects along 60 m of street, a few metres either side, 0-6 m high (A's frame)."""
    return np.column_stack([rng.uniform(0, 60, n), rng.choice([-7.0, 7.0], n) + rng.normal(0, 1, n),
                            rng.uniform(0, 6, n)])  # fmt: skip


@pytest.mark.parametrize("gravity_aligned", [True, False])
def test_the_predicted_error_is_the_error_a_far_point_gets(gravity_aligned: bool) -> None:
    """Partners with 0.7 m of noise fitted over and over: the RMS error at a point 150 m beyond the overlap is
    what the covariance predicts (within 15 %), and the covariance is the spread of the fitted perturbation."""
    rng = np.random.default_rng(3)
    points_a = _street(rng)
    T_true = make_pose(rot_z(0.4) if gravity_aligned else so3_exp(np.array([0.05, -0.03, 0.4])), np.array([5.0, -2, 1]))
    points_b = transform_points(np.linalg.inv(T_true), points_a)
    far_a = np.array([210.0, 0.0, 2.0])
    errors, predicted, deltas = [], [], []
    for _ in range(400):
        noisy_a = points_a + rng.normal(0, 0.7 / np.sqrt(3), points_a.shape)
        T = kabsch_yaw(points_b, noisy_a, up=UP) if gravity_aligned else kabsch(points_b, noisy_a)
        cov = alignment_covariance(transform_points(T, points_b), noisy_a, gravity_aligned=gravity_aligned, up=UP)
        far_b = transform_points(np.linalg.inv(T_true), far_a[None])[0]
        errors.append(np.linalg.norm(transform_points(T, far_b[None])[0] - far_a))
        predicted.append(predicted_error_m(cov, far_a, gravity_aligned=gravity_aligned, up=UP))
        D = T @ np.linalg.inv(T_true)  # the left perturbation exp(delta) = T T_true^-1 (small)
        omega = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2
        deltas.append(np.concatenate([[omega @ UP] if gravity_aligned else omega, D[:3, 3]]))
    rms = np.sqrt(np.mean(np.square(errors)))
    assert rms == pytest.approx(np.sqrt(np.mean(np.square(predicted))), rel=0.15)
    assert rms > 1.0  # a far point: the turn matters (the test would not see a wrong rotation block otherwise)
    spread = np.cov(np.array(deltas).T)
    k = 4 if gravity_aligned else 6
    assert cov.shape == (k, k)
    np.testing.assert_allclose(np.sqrt(np.diag(spread)), np.sqrt(np.diag(cov)), rtol=0.25)


def test_too_few_partners_or_a_line_give_no_covariance() -> None:
    points = np.array([[0.0, 0, 0], [10, 0, 0]])
    assert alignment_covariance(points, points + 0.1, gravity_aligned=False, up=UP) is None  # 6 residuals, 6 unknowns
    line = np.column_stack([np.linspace(0, 50, 8), np.zeros(8), np.zeros(8)])
    assert alignment_covariance(line, line + 0.1, gravity_aligned=False, up=UP) is None  # the turn about the line
    cov = alignment_covariance(line, line + np.array([0.1, -0.1, 0.05]) * np.arange(8)[:, None] % 0.3,
                               gravity_aligned=True, up=UP)  # fmt: skip
    assert cov is not None and np.all(np.linalg.eigvalsh(cov) >= 0)  # yaw about z is seen along a line


def test_an_accepted_match_reports_its_precision() -> None:
    from shgm_slam.bench.localization_sparse import UP_WORLD, SparseOptions, make_pairs
    from shgm_slam.config import DescriptorConfig, MatchingConfig
    from shgm_slam.matching import match_graphs
    from shgm_slam.sim.city import CityParams, build_city

    pairs = make_pairs(build_city(CityParams(), seed=10), 10, SparseOptions(seeds=(10,), pairs_per_seed=3), 10.0)
    cfg = MatchingConfig().model_copy(update={"up_axis": UP_WORLD, "gravity_aligned": True})
    accepted = 0
    for pair in pairs:
        r = match_graphs(pair.graph_a, pair.graph_b, DescriptorConfig(), cfg)
        if not r.success:
            assert r.covariance is None and np.isnan(r.centroid_sigma_m)
            assert r.to_json_dict()["precision"] == {"covariance": None, "centroid_sigma_m": None}
            continue
        accepted += 1
        assert r.covariance.shape == (4, 4) and 0.0 < r.centroid_sigma_m < 2.0
        c = pair.graph_b.positions_xyz.mean(axis=0)[None]
        err = np.linalg.norm(transform_points(r.T_a_b, c) - transform_points(pair.T_a_b, c))
        assert err < 3.0 * r.centroid_sigma_m
        assert r.to_json_dict()["precision"]["centroid_sigma_m"] == pytest.approx(r.centroid_sigma_m, abs=1e-3)
    assert accepted >= 2
