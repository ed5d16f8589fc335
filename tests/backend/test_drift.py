"""A robot's odometry rotation drift measured from its loop closures: the estimator against simulated
random walks and systematic drift, the levels, and the pose graph taking it up (and restoring it)."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.drift import (
    LEVEL_STEP,
    UNIT_RATE_RAD_PER_M,
    closure_rate,
    drift_level,
    loop_rotation_error_rad,
    measured_rate,
)
from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.geometry import se3
from tests.backend.test_loop_closure import _circle, _drift

CLOSURE_SIGMA_RAD = 0.1  # the configured closure rotation sigma


def _yaw_drift(gt: np.ndarray, yaw_deg_per_step: float) -> np.ndarray:
    """Odometry whose every step turns ``yaw_deg_per_step`` more than the truth (a systematic heading drift)."""
    return _drift(gt, yaw_deg_per_step, scale=1.0)


def test_loop_rotation_error_is_the_rotation_the_odometry_missed() -> None:
    gt = _circle(100)
    odo = _yaw_drift(gt, 0.1)
    error = loop_rotation_error_rad(odo[0], odo[99], se3.inverse(gt[0]) @ gt[99])
    # 99 steps 0.1 deg too far left about the camera's y axis: the closure turns them back
    np.testing.assert_allclose(error, [0.0, -np.radians(9.9), 0.0], atol=1e-9)
    assert np.allclose(loop_rotation_error_rad(gt[3], gt[50], se3.inverse(gt[3]) @ gt[50]), 0.0)


def test_closure_rate_recovers_the_rate_of_a_random_walk() -> None:
    """Many loops of a random walk of known rate: the median of the closures' estimates is the rate (up to
    the median of a chi-square of 3 degrees of freedom over 3, ~0.79 in variance)."""
    rng = np.random.default_rng(3)
    floor, rate, steps = 0.001, 0.004, np.full(120, 2.0)
    sigma = floor + rate * steps
    errors = (rng.normal(0.0, 1.0, (400, 120, 3)) * sigma[None, :, None]).sum(axis=1)
    rates = [closure_rate(e, steps, floor) for e in errors]
    assert measured_rate(rates) == pytest.approx(rate * np.sqrt(0.79), rel=0.1)


def test_closure_rate_is_zero_when_the_floor_explains_the_error() -> None:
    steps = np.full(50, 2.0)  # the floor alone: 0.001 rad per step, sqrt(50 / 3) * 0.001 rad = 0.7 deg over the loop
    assert closure_rate(np.zeros(3), steps, 0.001) == 0.0
    assert closure_rate(np.array([0.0, 0.012, 0.0]), steps, 0.001) == 0.0
    rate = closure_rate(np.array([0.0, 0.1, 0.0]), steps, 0.001)
    assert np.sum((0.001 + rate * steps) ** 2) == pytest.approx(0.1**2 / 3)  # the error's variance per axis
    assert closure_rate(np.array([0.0, 0.3, 0.0]), np.zeros(0), 0.001) == 0.0  # no steps: nothing to blame


def test_measured_rate_is_the_median() -> None:
    assert measured_rate([]) == 0.0
    assert measured_rate([0.0, 0.01, 0.002]) == 0.002


def test_levels_round_up_to_powers_of_the_step_and_never_go_below_the_prior() -> None:
    assert drift_level(0.0005, 0.001) == 0.001
    assert drift_level(0.001, 0.001) == 0.001
    assert drift_level(0.0012, 0.001) == pytest.approx(0.001 * LEVEL_STEP)
    assert drift_level(0.002, 0.001) == pytest.approx(0.002)
    assert drift_level(0.0021, 0.001) == pytest.approx(0.001 * LEVEL_STEP**3)
    assert drift_level(3e-4, 0.0) == pytest.approx(UNIT_RATE_RAD_PER_M * LEVEL_STEP**4)
    assert drift_level(0.0, 0.0) == 0.0
    for measured in np.geomspace(1e-4, 1.0, 50):  # a level is at least what was measured, less than a step more
        level = drift_level(measured, 0.001)
        assert level >= measured and (measured < 0.001 or level < measured * LEVEL_STEP * (1 + 1e-9))


def _loop_graph(yaw_deg_per_step: float) -> tuple[MultiRobotPoseGraph, np.ndarray, list[tuple[int, int]]]:
    """A 250 m circle driven 1.15 times (1.26 m keyframes), its odometry drifting in heading, with a tight
    prior rate, and revisits of the first keyframes by the last ones."""
    gt = _circle(200)
    odo = _yaw_drift(gt, yaw_deg_per_step)
    pg = MultiRobotPoseGraph(
        ["car"], odometry_sigmas=(0.001, 0.01), odometry_drift=(0.001, 0.01), closure_sigmas=(CLOSURE_SIGMA_RAD, 3.0)
    )
    for k, T in enumerate(odo):
        pg.add_keyframe("car", k, T)
    return pg, gt, [(2, 176), (6, 180), (10, 184), (14, 188), (18, 192)]


def _close_loops(pg: MultiRobotPoseGraph, gt: np.ndarray, revisits: list[tuple[int, int]]) -> None:
    for m, (i, j) in enumerate(revisits):
        d = pg.add_loop_closure("car", i, j, se3.inverse(gt[i]) @ gt[j], num_inliers=10, match_id=m)
        assert d.accepted, d.reason


def _ate(pg: MultiRobotPoseGraph, gt: np.ndarray) -> float:
    est = pg.estimate()["car"]
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - (se3.inverse(gt[0]) @ gt)[:, :3, 3]) ** 2, axis=1))))


def test_a_loop_that_drifts_in_heading_raises_its_robots_rate_and_is_straightened() -> None:
    """0.063 deg per 1.26 m step (5 deg per 100 m): 11 deg over the loop. The tight prior rate would keep the
    bent loop; the rate the closures measure lets them straighten it."""
    pg, gt, revisits = _loop_graph(0.063)
    before = _ate(pg, gt)
    _close_loops(pg, gt, revisits)
    rate = pg.measured_drift("car")
    assert rate is not None and rate > 0.002
    assert pg.stats().rebuilds >= 1
    assert _ate(pg, gt) < 0.3 * before

    fixed = MultiRobotPoseGraph(
        ["car"], odometry_sigmas=(0.001, 0.01), odometry_drift=(0.001, 0.01), closure_sigmas=(CLOSURE_SIGMA_RAD, 3.0)
    )
    fixed._refresh_drift = lambda robot: False  # the prior's rate whatever the closures say
    for k, T in enumerate(_yaw_drift(gt, 0.063)):
        fixed.add_keyframe("car", k, T)
    _close_loops(fixed, gt, revisits)
    assert _ate(pg, gt) < 0.5 * _ate(fixed, gt)


def test_a_loop_that_drifts_little_keeps_the_prior() -> None:
    pg, gt, revisits = _loop_graph(0.005)  # 0.9 deg over 174 steps: what the prior's floor and rate expect
    _close_loops(pg, gt, revisits)
    assert pg.measured_drift("car") is None
    assert pg.stats().rebuilds == 0


def test_a_restored_graph_uses_the_rate_its_closures_measured() -> None:
    pg, gt, revisits = _loop_graph(0.063)
    _close_loops(pg, gt, revisits)
    fresh = MultiRobotPoseGraph(
        ["car"], odometry_sigmas=(0.001, 0.01), odometry_drift=(0.001, 0.01), closure_sigmas=(CLOSURE_SIGMA_RAD, 3.0)
    )
    fresh.restore_state(pg.state(), {"car": np.stack(pg._robots["car"].T_odom_kf)})
    assert fresh.measured_drift("car") == pg.measured_drift("car")
    pg.converge(), fresh.converge()  # the same optimum (iSAM2 alone stops short of it by millimetres)
    np.testing.assert_allclose(fresh.estimate()["car"][:, :3, 3], pg.estimate()["car"][:, :3, 3], atol=1e-4)
    assert fresh.to_g2o().count("EDGE") == pg.to_g2o().count("EDGE")
