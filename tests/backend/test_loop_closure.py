"""Intra-robot loop closures in the pose graph: canonical order, the odometry check, the consistency vote,
no anchoring, and the correction they bring to a drifting loop."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.consistency import ConsistencyThresholds, consistent_with_odometry
from shgm_slam.backend.pose_graph import ClosureStatus, MultiRobotPoseGraph
from shgm_slam.errors import BackendError
from shgm_slam.geometry import se3

N = 200  # keyframes on a circle of radius 40 m (~250 m, 1.26 m apart), the last ones revisit the first


def _circle(n: int = N, radius_m: float = 40.0, laps: float = 1.15) -> np.ndarray:
    """(n, 4, 4) KITTI-style camera poses (y down, z forward) driving a circle in the x-z plane."""
    ang = np.linspace(0.0, 2 * np.pi * laps, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3], T[:, 2, 3] = radius_m * np.sin(ang), radius_m * (1 - np.cos(ang))
    for k, a in enumerate(ang):
        T[k, :3, :3] = se3.rot_y(a)  # forward (z) along the tangent
    return T


def _drift(gt: np.ndarray, yaw_deg: float = 0.05, scale: float = 1.02) -> np.ndarray:
    deltas = se3.inverse(gt[:-1]) @ gt[1:]
    deltas[:, :3, 3] *= scale
    deltas = se3.make_pose(se3.rot_y(np.radians(yaw_deg)), np.zeros(3)) @ deltas
    out = [gt[0]]
    for d in deltas:
        out.append(out[-1] @ d)
    return np.stack(out)


@pytest.fixture
def loop():
    gt = _circle()
    odo = _drift(gt)
    pg = MultiRobotPoseGraph(["car", "other"])
    for k, T in enumerate(odo):
        pg.add_keyframe("car", k, T)
    revisits = [(2, 176), (6, 180), (10, 184), (14, 188), (18, 192)]
    return pg, gt, odo, revisits


def _true(gt: np.ndarray, i: int, j: int) -> np.ndarray:
    return se3.inverse(gt[i]) @ gt[j]


def _ate(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def test_loop_closures_correct_a_drifting_loop(loop) -> None:
    pg, gt, odo, revisits = loop
    for m, (i, j) in enumerate(revisits):
        d = pg.add_loop_closure("car", i, j, _true(gt, i, j), num_inliers=10, match_id=m)
        assert d.accepted, d.reason
    assert all(c.in_graph for c in pg.closures())
    est = pg.estimate()["car"]
    assert _ate(est, gt) < 0.3 * _ate(odo, gt), (_ate(est, gt), _ate(odo, gt))
    assert pg.stats().anchored_robots == ("car",)  # a loop closure anchors nothing


def test_canonical_order_is_older_keyframe_first(loop) -> None:
    pg, gt, _, _ = loop
    pg.add_inter_robot_closure("car", 180, "car", 6, _true(gt, 180, 6))
    (c,) = pg.closures()
    assert (c.robot_a, c.kf_a, c.robot_b, c.kf_b) == ("car", 6, "car", 180)
    np.testing.assert_allclose(c.T_a_b, _true(gt, 6, 180), atol=1e-9)
    with pytest.raises(BackendError, match="itself"):
        pg.add_loop_closure("car", 5, 5, np.eye(4))


def test_the_consistency_vote_rejects_a_wrong_loop_closure(loop) -> None:
    pg, gt, _, revisits = loop
    for m, (i, j) in enumerate(revisits[:3]):
        pg.add_loop_closure("car", i, j, _true(gt, i, j), num_inliers=10, match_id=m)
    # perceptual aliasing: the right keyframes, but 12 m off along the road (within the odometry check)
    i, j = revisits[3]
    wrong = _true(gt, i, j) @ se3.make_pose(np.eye(3), np.array([0.0, 0.0, 12.0]))
    d = pg.add_loop_closure("car", i, j, wrong, num_inliers=30, match_id=3)
    assert not d.accepted
    assert "inconsistent with the maximum consistent set" in d.reason
    assert sum(c.status is ClosureStatus.ACCEPTED for c in pg.closures()) == 3


def test_a_loop_closure_far_from_the_odometry_is_rejected(loop) -> None:
    pg, gt, _, revisits = loop
    i, j = revisits[0]
    turned = se3.make_pose(se3.rot_y(np.pi), np.zeros(3)) @ _true(gt, i, j)  # 180 deg off: an aliased match
    d = pg.add_loop_closure("car", i, j, turned)
    assert not d.accepted
    assert "disagrees with car's odometry" in d.reason
    assert not pg.closures()[0].in_graph
    # it does not vote: the right closure afterwards is the only one in the set
    assert pg.add_loop_closure("car", i, j, _true(gt, i, j)).accepted


def test_loop_closure_of_an_unanchored_robot_waits_and_anchors_nothing() -> None:
    gt = _circle(60)
    pg = MultiRobotPoseGraph(["ref", "car"])
    pg.add_keyframe("ref", 0, np.eye(4))
    for k, T in enumerate(gt):
        pg.add_keyframe("car", k, T)
    d = pg.add_loop_closure("car", 0, 59, _true(gt, 0, 59))
    assert d.accepted and "stored until car is anchored" in d.reason
    assert not pg.is_anchored("car")
    # once an inter-robot closure places it, the stored loop closure enters the graph
    assert pg.add_inter_robot_closure("ref", 0, "car", 0, gt[0]).accepted
    assert pg.is_anchored("car") and all(c.in_graph for c in pg.closures())


def test_consistent_with_odometry_tolerance_grows_with_the_loop() -> None:
    gt = _circle(50)
    path = np.r_[0, np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))]
    th = ConsistencyThresholds()
    off = _true(gt, 0, 49) @ se3.make_pose(np.eye(3), np.array([8.0, 0.0, 0.0]))
    ok, trans_m, _ = consistent_with_odometry(off, 0, 49, gt, path, th)
    assert ok and trans_m == pytest.approx(8.0)  # 5 m + 5 % of ~240 m
    short = _true(gt, 0, 2) @ se3.make_pose(np.eye(3), np.array([8.0, 0.0, 0.0]))
    ok, trans_m, _ = consistent_with_odometry(short, 0, 2, gt, path, th)
    assert not ok and trans_m == pytest.approx(8.0)  # the same error over a few metres of odometry
