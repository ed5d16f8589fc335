"""Ground truth moved into a run's shared frame: the first robot's first camera frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.geometry.se3 import make_pose, rot_y, rot_z
from shgm_slam.shared_frame import SharedTruth, shared_frame_ground_truth


@dataclass
class _Truth:
    """The part of a sequence this reads: its ground truth (None: none)."""

    gt_poses: np.ndarray | None


def _drive(start: np.ndarray, n: int = 5) -> np.ndarray:
    return np.stack([start @ make_pose(rot_y(0.1 * k), [0.0, 0.0, 2.0 * k]) for k in range(n)])


def test_the_first_robot_starts_at_the_identity_and_the_others_keep_their_relative_pose() -> None:
    start_a = make_pose(rot_z(0.7), [500.0, -200.0, 30.0])
    start_b = make_pose(rot_z(-1.2), [620.0, -150.0, 31.0])
    gt = shared_frame_ground_truth({"car1": _Truth(_drive(start_a)), "car2": _Truth(_drive(start_b))})
    np.testing.assert_allclose(gt["car1"][0], np.eye(4), atol=1e-12)
    # the relation of any two poses is that of the world frame: only the frame moved
    np.testing.assert_allclose(
        np.linalg.inv(gt["car1"][2]) @ gt["car2"][3], np.linalg.inv(_drive(start_a)[2]) @ _drive(start_b)[3], atol=1e-9
    )


def test_truth_that_cannot_be_placed_is_left_out() -> None:
    a, b = _Truth(_drive(np.eye(4))), _Truth(_drive(make_pose(np.eye(3), [5.0, 0.0, 0.0])))
    assert list(shared_frame_ground_truth({"car1": a, "car2": b}, gt_shared_frame=False)) == ["car1"]  # other worlds
    assert shared_frame_ground_truth({"car1": _Truth(None), "car2": b}) == {}  # the reference has none
    assert list(shared_frame_ground_truth({"car1": a, "car2": _Truth(None)})) == ["car1"]
    assert shared_frame_ground_truth({}) == {}


def test_frame_by_frame_truth_is_the_whole_truths_rows_and_none_where_it_has_none() -> None:
    a = _Truth(_drive(make_pose(rot_z(0.7), [500.0, -200.0, 30.0])))
    b = _Truth(_drive(make_pose(rot_z(-1.2), [620.0, -150.0, 31.0]), n=3))  # shorter than its frames could be
    robots = {"car1": a, "car2": b}
    whole, each = shared_frame_ground_truth(robots), SharedTruth(robots)
    for name, poses in whole.items():
        for i, T in enumerate(poses):
            np.testing.assert_allclose(each.position(name, i), T[:3, 3], atol=1e-9)
    assert each.position("car2", 3) is None and each.position("car2", -1) is None and each.position("uav", 0) is None
    assert SharedTruth(robots, gt_shared_frame=False).position("car2", 0) is None  # other worlds: not placed
    assert SharedTruth({"car1": _Truth(None), "car2": b}).position("car2", 0) is None  # the reference has none
    assert SharedTruth({}).position("car1", 0) is None
