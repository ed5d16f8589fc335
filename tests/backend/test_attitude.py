"""Attitude factors from ground normals: the measured sigma, the height they save, when they enter."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.attitude import normal_sigma_rad, up_at_start
from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.errors import BackendError
from shgm_slam.geometry import se3

UP_CAM = np.array([0.0, -1.0, 0.0])  # KITTI camera frame: y points down


def _tilted(up: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """(K, 3) unit vectors: ``up`` (K, 3) tilted by isotropic Gaussian angles of ``sigma_rad`` per axis."""
    return np.stack([se3.so3_exp(rng.normal(0.0, sigma_rad, 3)) @ u for u in up])


def _drifting_chain(n: int, pitch_drift_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(truth, odometry): a level straight drive, 2 m per keyframe, and odometry that pitches up a little
    more every keyframe (its height error grows with the square of the distance)."""
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 2, 3] = 2.0 * np.arange(n)
    step = se3.make_pose(se3.rot_x(pitch_drift_rad), [0.0, 0.0, 2.0])
    odo = [np.eye(4)]
    for _ in range(n - 1):
        odo.append(odo[-1] @ step)
    return gt, np.stack(odo)


def _normals_odom(gt: np.ndarray, odo: np.ndarray, sigma_rad: float, seed: int = 0) -> np.ndarray:
    """(K, 3) what a front end sends: the true camera-frame up, measured with noise, in the odometry frame."""
    rng = np.random.default_rng(seed)
    n_cam = _tilted(np.einsum("kji,j->ki", gt[:, :3, :3], UP_CAM), sigma_rad, rng)
    return np.einsum("kij,kj->ki", odo[:, :3, :3], n_cam)


@pytest.mark.parametrize("sigma_rad", [2e-4, 3e-3, 2e-2])
def test_measured_sigma_matches_the_true_scatter(sigma_rad):
    rng = np.random.default_rng(1)
    up = _tilted(np.tile(UP_CAM, (4000, 1)), sigma_rad, rng)
    est = normal_sigma_rad(up)
    assert est == pytest.approx(sigma_rad, rel=0.08)


def test_measured_sigma_ignores_a_slow_drift_and_skips_missing_normals():
    # the odometry frame turns slowly (drift): successive normals still differ by the noise alone
    rng = np.random.default_rng(2)
    k = np.arange(3000)
    drifted = np.stack([se3.rot_x(1e-4 * i) @ UP_CAM for i in k])
    up = _tilted(drifted, 1e-3, rng)
    up[::7] = np.nan
    assert normal_sigma_rad(up) == pytest.approx(1e-3, rel=0.1)
    assert normal_sigma_rad(up[:1]) is None


def test_up_at_start_removes_a_linear_drift_that_the_mean_keeps():
    k = np.arange(20)
    drifted = np.stack([se3.rot_x(2e-3 * i) @ UP_CAM for i in k])  # the odometry pitches 2 mrad per keyframe
    walk = (k * 2e-3) ** 2 / 4.0  # a drift model of that order (its variance grows along the chain)
    up = up_at_start(drifted, walk, sigma_rad=1e-5)
    assert np.linalg.norm(up) == pytest.approx(1.0)
    assert np.degrees(np.arccos(up @ UP_CAM)) < 0.01
    mean = drifted.mean(axis=0) / np.linalg.norm(drifted.mean(axis=0))
    assert np.degrees(np.arccos(mean @ UP_CAM)) > 1.0
    with pytest.raises(ValueError):
        up_at_start(drifted[:0], walk[:0], 1e-3)
    with pytest.raises(ValueError):
        up_at_start(drifted, walk[:5], 1e-3)
    with pytest.raises(ValueError):
        up_at_start(drifted, -walk - 1.0, 1e-3)
    with pytest.raises(ValueError):
        up_at_start(drifted, walk, 0.0)


def test_up_at_start_beats_a_line_through_the_normals_on_a_random_walk():
    """Exact normals on a drift that is not linear in the keyframe index (a random walk): the estimate
    follows the first keyframes, where a line's intercept is pulled by the walk's later wanderings."""
    rng = np.random.default_rng(5)
    k = np.arange(20)
    step_sigma = 2e-3
    err_gls, err_line = [], []
    for _ in range(50):
        tilt = np.cumsum(rng.normal(0.0, step_sigma, size=(20, 3)), axis=0)
        tilt[0] = 0.0
        ups = np.stack([se3.so3_exp(t) @ UP_CAM for t in tilt])
        up = up_at_start(ups, k * step_sigma**2, sigma_rad=1e-5)
        err_gls.append(np.arccos(np.clip(up @ UP_CAM, -1, 1)))
        coef = np.linalg.lstsq(np.column_stack([np.ones(20), k]), ups, rcond=None)[0][0]
        err_line.append(np.arccos(np.clip(coef @ UP_CAM / np.linalg.norm(coef), -1, 1)))
    assert np.median(err_gls) < 1e-4
    assert np.median(err_line) > 10 * np.median(err_gls)


def test_up_at_start_averages_noisy_normals_without_drift():
    rng = np.random.default_rng(6)
    sigma = 5e-3
    errs = []
    for _ in range(50):
        ups = _tilted(np.tile(UP_CAM, (40, 1)), sigma, rng)
        up = up_at_start(ups, np.full(40, 1e-10), sigma_rad=sigma)
        errs.append(np.arccos(np.clip(up @ UP_CAM, -1, 1)))
    # the mean of 40 normals: about sigma * sqrt(2) / sqrt(40) off (a Rayleigh median ~1.18 of its scale)
    assert np.median(errs) < 2.0 * sigma / np.sqrt(40.0)


def _fused_height_error(attitude: bool, n: int = 600, sigma_rad: float = 1e-3) -> tuple[float, MultiRobotPoseGraph]:
    gt, odo = _drifting_chain(n, pitch_drift_rad=2e-4)
    ups = _normals_odom(gt, odo, sigma_rad)
    pg = MultiRobotPoseGraph(["car"], attitude=attitude)
    for k in range(n):
        pg.add_keyframe("car", k, odo[k], ups[k])
    est = pg.estimate()["car"]
    return float(np.abs(est[:, 1, 3] - gt[:, 1, 3]).max()), pg


def test_attitude_factors_remove_the_height_drift_of_pitching_odometry():
    err_off, pg_off = _fused_height_error(attitude=False)
    err_on, pg_on = _fused_height_error(attitude=True)
    # odometry alone: 2e-4 rad more pitch per keyframe over 1.2 km rises ~70 m
    assert err_off > 30.0
    assert err_on < 0.02 * err_off
    assert pg_off.stats().attitude_factors == 0 and pg_off.up_shared is None
    assert pg_on.stats().attitude_factors == 600
    np.testing.assert_allclose(pg_on.up_shared, UP_CAM, atol=2e-3)  # the first camera is level here


def test_shared_up_follows_the_first_keyframe_when_the_odometry_wanders():
    """Exact normals, odometry whose roll and pitch wander (a random walk of 1 mrad per keyframe, 4 mrad
    over the warm-up): the shared up is keyframe 0's, not a fit through the wandering ones."""
    rng = np.random.default_rng(7)
    n = 40
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 2, 3] = 2.0 * np.arange(n)
    odo = [np.eye(4)]
    for _ in range(n - 1):
        tilt = se3.so3_exp(np.array([rng.normal(0.0, 1e-3), 0.0, rng.normal(0.0, 1e-3)]))
        odo.append(odo[-1] @ se3.make_pose(tilt, [0.0, 0.0, 2.0]))
    odo = np.stack(odo)
    ups = _normals_odom(gt, odo, 1e-6)
    pg = MultiRobotPoseGraph(["car"], attitude_warmup=20)
    for k in range(n):
        pg.add_keyframe("car", k, odo[k], ups[k])
    assert pg.up_shared is not None
    assert np.arccos(np.clip(pg.up_shared @ UP_CAM, -1.0, 1.0)) < 2e-4


def test_attitude_waits_for_warmup_and_for_anchoring():
    gt, odo = _drifting_chain(60, pitch_drift_rad=0.0)
    ups = _normals_odom(gt, odo, 1e-3)
    pg = MultiRobotPoseGraph(["a", "b"], attitude_warmup=20)
    for k in range(19):
        pg.add_keyframe("a", k, odo[k], ups[k])
    assert pg.stats().attitude_factors == 0  # 19 normals: no sigma yet
    pg.add_keyframe("a", 19, odo[19], ups[19])
    assert pg.stats().attitude_factors == 20
    pg.add_keyframe("a", 20, odo[20])  # a keyframe without a ground fit gets no factor
    assert pg.stats().attitude_factors == 20
    for k in range(30):
        pg.add_keyframe("b", k, odo[k], ups[k])
    assert pg.stats().attitude_factors == 20  # b is not anchored: its keyframes are not in iSAM2
    T_a10_b10 = se3.inverse(odo[10]) @ odo[10]
    assert pg.add_inter_robot_closure("a", 10, "b", 10, T_a10_b10, num_inliers=10).accepted
    assert pg.stats().attitude_factors == 50


def test_bad_normals_are_refused():
    pg = MultiRobotPoseGraph(["a"])
    with pytest.raises(BackendError, match="up_odom"):
        pg.add_keyframe("a", 0, np.eye(4), np.array([0.0, 0.0, 0.0]))
    with pytest.raises(BackendError, match="up_odom"):
        pg.add_keyframe("a", 0, np.eye(4), np.array([np.nan, 1.0, 0.0]))
    with pytest.raises(BackendError, match="attitude_warmup"):
        MultiRobotPoseGraph(["a"], attitude_warmup=1)
