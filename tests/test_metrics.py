"""Trajectory metrics: alignment invariance, hand-computed RMSE, evo cross-check, short and bad input."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import make_pose, rot_y, rot_z, so3_exp
from shgm_slam.metrics import AlignMode, RelationKind, ate, drift_percent, joint_ate, rpe, trajectory_length


def _trajectory(n: int = 50, seed: int = 0) -> np.ndarray:
    """A curvy 3-D trajectory of (n, 4, 4) poses."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 4 * np.pi, n)
    xyz = np.c_[20 * np.sin(s / 2), 0.5 * np.sin(3 * s), 3 * s]
    return make_pose(so3_exp(rng.normal(0, 0.3, (n, 3))), xyz)


def _noisy(poses: np.ndarray, sigma_m: float, seed: int = 1) -> np.ndarray:
    out = poses.copy()
    out[:, :3, 3] += np.random.default_rng(seed).normal(0, sigma_m, (len(poses), 3))
    return out


def test_rigidly_moved_copy_has_zero_error_after_se3_alignment():
    gt = _trajectory()
    T = make_pose(rot_z(0.7) @ rot_y(-0.4), [12.0, -3.0, 40.0])
    moved = T @ gt
    stats = ate(gt, moved, align=AlignMode.SE3)
    assert stats.valid and stats.rmse < 1e-6 and stats["max"] < 1e-6
    assert ate(gt, moved, align=AlignMode.NONE).rmse > 10.0
    # scaled copies need Sim(3)
    scaled = moved.copy()
    scaled[:, :3, 3] *= 0.6
    assert ate(gt, scaled, align=AlignMode.SE3).rmse > 1.0
    assert ate(gt, scaled, align=AlignMode.SIM3).rmse < 1e-6


def test_unaligned_ate_matches_hand_computed_statistics():
    gt = _trajectory()
    est = _noisy(gt, 0.3)
    e = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    stats = ate(gt, est, align="none")
    assert stats.rmse == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-12)
    assert stats.mean == pytest.approx(e.mean(), rel=1e-12)
    assert stats.median == pytest.approx(np.median(e), rel=1e-12)
    assert stats.std == pytest.approx(e.std(), rel=1e-12)
    assert stats.max == pytest.approx(e.max(), rel=1e-12)
    assert stats.as_dict()["num_poses"] == len(gt)


def test_matches_evo_main_ape_and_does_not_modify_inputs():
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape as evo_ape

    gt = _trajectory()
    est = make_pose(rot_z(0.3), [1.0, 2.0, 3.0]) @ _noisy(gt, 0.2)
    est[:, :3, 3] *= 1.3
    before = est.copy()
    t = np.arange(len(gt), dtype=float)
    for align, scale in ((AlignMode.SE3, False), (AlignMode.SIM3, True)):
        ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=t)
        traj = PoseTrajectory3D(poses_se3=list(est), timestamps=t)
        res = evo_ape(ref, copy.deepcopy(traj), evo_metrics.PoseRelation.translation_part, align=True,
                      correct_scale=scale)  # fmt: skip
        ours = ate(gt, est, align=align)
        for key in ("rmse", "mean", "median", "std", "max"):
            assert ours[key] == pytest.approx(res.stats[key], rel=1e-9)
    np.testing.assert_array_equal(est, before)


def test_rpe_is_frame_independent_and_sees_relative_errors():
    gt = _trajectory()
    moved = make_pose(rot_z(1.0), [5.0, 5.0, 5.0]) @ gt
    assert rpe(gt, moved).rmse < 1e-9
    assert rpe(gt, moved, relation=RelationKind.ROTATION_DEG).rmse < 1e-6
    est = gt.copy()
    est[10:, :3, 3] += [0.5, 0.0, 0.0]  # one jump of 0.5 m between frames 9 and 10
    stats = rpe(gt, est, delta_frames=1)
    assert stats.max == pytest.approx(0.5, rel=1e-9)
    assert stats.median < 1e-9


def test_straight_line_trajectories_are_still_aligned():
    gt = np.repeat(np.eye(4)[None], 20, axis=0)
    gt[:, 2, 3] = np.arange(20.0)  # collinear positions: evo's Umeyama refuses them
    moved = make_pose(rot_y(0.5), [3.0, 0.0, 1.0]) @ gt
    assert ate(gt, moved, align="se3").rmse < 1e-9
    scaled = moved.copy()
    scaled[:, :3, 3] *= 2.0
    assert ate(gt, scaled, align="sim3").rmse < 1e-9


def test_short_or_non_finite_trajectories_give_nan_with_a_reason():
    gt = _trajectory(2)
    stats = ate(gt, gt)
    assert not stats.valid and np.isnan(stats.rmse) and "only 2 poses" in stats.reason
    assert np.isnan(rpe(gt, gt).rmse)
    assert "delta" in rpe(_trajectory(5), _trajectory(5), delta_frames=5).reason
    bad = _trajectory()
    bad[3, 0, 3] = np.nan
    assert "NaN" in ate(_trajectory(), bad).reason
    still = np.repeat(np.eye(4)[None], 5, axis=0)
    assert "coincide" in ate(still, still, align="sim3").reason


def test_bad_input_raises_data_error():
    with pytest.raises(DataError, match="10 ground-truth poses but 9 estimated"):
        ate(_trajectory(10), _trajectory(9))
    with pytest.raises(DataError, match=r"\(N, 4, 4\)"):
        ate(np.zeros((5, 3, 4)), np.zeros((5, 3, 4)))
    with pytest.raises(DataError, match="unknown AlignMode"):
        ate(_trajectory(), _trajectory(), align="umeyama")


def test_trajectory_length():
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[:, :3, 3] = [[0, 0, 0], [3, 4, 0], [3, 4, 2], [3, 4, 2]]
    assert trajectory_length(poses) == pytest.approx(7.0)
    assert trajectory_length(poses[:1]) == 0.0


def test_on_kitti_ground_truth(shared_data):
    from shgm_slam.io.trajectories import read_kitti_poses

    gt = read_kitti_poses(shared_data / "kitti" / "poses" / "07.txt")
    assert trajectory_length(gt) == pytest.approx(694.7, abs=0.5)  # the published length of sequence 07
    moved = make_pose(rot_y(1.2), [100.0, -2.0, 50.0]) @ gt
    assert ate(gt, moved).rmse < 1e-6
    assert ate(gt, moved, align="none").rmse > 50.0


def _drive(n: int = 400, step_m: float = 1.0) -> np.ndarray:
    """(n, 4, 4) a drive turning gently (yaw about the camera's y axis), ``step_m`` per frame."""
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ make_pose(rot_y(0.004), [0.0, 0.0, step_m]))
    return np.stack(poses)


def test_drift_is_zero_for_any_rigidly_moved_copy_and_the_scale_error_for_a_scaled_one():
    gt = _drive()
    moved = make_pose(rot_z(0.7) @ rot_y(1.1), [40.0, -3.0, 7.0]) @ gt
    assert drift_percent(gt, moved) < 1e-6
    scaled = gt.copy()
    scaled[:, :3, 3] *= 1.1
    assert 9.5 < drift_percent(gt, scaled) <= 10.0  # 10 % of each stretch's chord (the drive curves)


def test_drift_sees_a_heading_error_growing_with_distance():
    gt = _drive()
    est = [np.eye(4)]
    for k in range(1, len(gt)):  # every step turns 0.01 rad too far
        est.append(est[-1] @ (np.linalg.inv(gt[k - 1]) @ gt[k]) @ make_pose(rot_y(0.01), [0.0, 0.0, 0.0]))
    short = drift_percent(gt, np.stack(est), lengths_m=(50.0,))
    long = drift_percent(gt, np.stack(est), lengths_m=(200.0,))
    assert 0 < short < long  # heading error: the lateral error per metre grows with the stretch


def test_drift_of_a_too_short_or_broken_trajectory_is_nan():
    gt = _drive(20)
    assert np.isnan(drift_percent(gt, gt))  # 19 m: shorter than the shortest stretch
    bad = _drive()
    bad[5, 0, 3] = np.nan
    assert np.isnan(drift_percent(_drive(), bad))
    with pytest.raises(DataError):
        drift_percent(_drive(), _drive(10))


def test_joint_ate_removes_only_the_shared_gauge():
    """One rigid motion of the whole fleet (the first robot's drift) is removed; one robot placed off
    relative to the others is not, and the joint error is the same in any frame of the estimate."""
    gt_a, gt_b = _trajectory(60, seed=0), _trajectory(40, seed=3)
    gt_b[:, :3, 3] += [30.0, 0.0, -10.0]
    gauge = make_pose(rot_z(0.2) @ rot_y(0.05), [4.0, -2.0, 1.0])
    per_robot, together = joint_ate([gt_a, gt_b], [gauge @ gt_a, gauge @ gt_b])
    assert together.valid and together.rmse < 1e-6 and max(s.rmse for s in per_robot) < 1e-6
    assert ate(gt_b, gauge @ gt_b, align=AlignMode.NONE).rmse > 1.0  # the shared frame sees the gauge
    # B placed 2 m off relative to A: each aligned alone is perfect, jointly the disagreement shows
    off = gauge @ gt_b
    off[:, :3, 3] += [2.0, 0.0, 0.0]
    per_robot, together = joint_ate([gt_a, gt_b], [gauge @ gt_a, off])
    assert ate(gt_b, off, align=AlignMode.SE3).rmse < 1e-6
    assert 0.3 < per_robot[0].rmse < 2.0 and 0.3 < per_robot[1].rmse < 2.0
    n_a, n_b = len(gt_a), len(gt_b)
    pooled = np.sqrt((n_a * per_robot[0].rmse**2 + n_b * per_robot[1].rmse**2) / (n_a + n_b))
    assert together.rmse == pytest.approx(pooled, rel=1e-9) and together.num_poses == n_a + n_b
    moved, _ = joint_ate([gt_a, gt_b], [make_pose(rot_z(-1.1), [50.0, 5.0, 0.0]) @ e for e in (gauge @ gt_a, off)])
    assert [s.rmse for s in moved] == pytest.approx([s.rmse for s in per_robot], rel=1e-6)


def test_joint_ate_of_one_robot_is_its_se3_aligned_ate():
    gt = _trajectory()
    est = make_pose(rot_z(0.4), [3.0, 1.0, 0.0]) @ _noisy(gt, 0.4)
    (one,), together = joint_ate([gt], [est])
    assert one.rmse == pytest.approx(ate(gt, est, align=AlignMode.SE3).rmse, rel=1e-6)
    assert together.rmse == pytest.approx(one.rmse)


def test_joint_ate_degenerate_input_gives_nan_with_a_reason():
    gt = _trajectory(10)
    bad = gt.copy()
    bad[3, 0, 3] = np.nan
    per_robot, together = joint_ate([gt, gt[:2]], [bad, gt[:2]])
    assert not together.valid and "NaN" in together.reason and all(not s.valid for s in per_robot)
    per_robot, together = joint_ate([gt[:1], gt[:1]], [gt[:1], gt[:1]])
    assert not together.valid and "only 2 poses" in together.reason
    still = np.repeat(gt[:1], 5, axis=0)
    assert "coincide" in joint_ate([gt[:5]], [still])[1].reason
    # a robot with fewer than 3 poses still counts in a joint fit of enough poses
    per_robot, together = joint_ate([gt, gt[:2]], [gt, gt[:2]])
    assert together.valid and per_robot[1].valid and per_robot[1].rmse < 1e-6
    with pytest.raises(DataError, match="trajectories"):
        joint_ate([gt], [])
