"""What the server reads out for a robot's results (``server/results.py``): fused trajectories that pass through
the fused keyframes and match the truth in the shared frame, and each robot's ``server.json`` line."""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry.se3 import inverse
from shgm_slam.server.node import ServerNode
from shgm_slam.server.results import fused_trajectory, keyframe_trajectory, provisional_note, robot_summary
from shgm_slam.server.sessions import RobotSession


def test_the_fused_trajectory_passes_through_the_fused_keyframes(uninterrupted: ServerNode) -> None:
    server = uninterrupted.map
    for name, session in uninterrupted.robots.items():
        times, T_shared_cam = fused_trajectory(server, session)
        kf_times, T_odom_kf, T_shared_kf = keyframe_trajectory(server, session)
        assert T_shared_cam is not None and T_shared_kf is not None, f"{name} not placed"
        assert len(kf_times) == len(T_odom_kf) == len(T_shared_kf) == server.received(name) > 2
        assert np.all(np.diff(kf_times) > 0)  # in time order
        at = np.searchsorted(times, kf_times)
        assert np.allclose(times[at], kf_times)
        np.testing.assert_allclose(T_shared_cam[at], T_shared_kf, atol=1e-6)


def test_fused_trajectories_lie_on_the_truth_in_the_shared_frame(uninterrupted: ServerNode, robots) -> None:
    """Ground-truth odometry (the fixtures' config): only the placement can be off, and it is not."""
    T_shared_world = inverse(robots["car1"].gt_poses[0])  # the shared frame is car1's first camera frame
    for name, session in uninterrupted.robots.items():
        _, T_shared_cam = fused_trajectory(uninterrupted.map, session)
        truth = T_shared_world @ robots[name].gt_poses
        error_m = np.linalg.norm(T_shared_cam[:, :3, 3] - truth[:, :3, 3], axis=1)
        assert np.sqrt(np.mean(error_m**2)) < 2.0, name


def test_a_robot_without_keyframes_has_an_empty_trajectory(uninterrupted: ServerNode) -> None:
    times, T_odom_kf, T_shared_kf = keyframe_trajectory(uninterrupted.map, RobotSession("nobody", "s0"))
    assert times.shape == (0,) and T_odom_kf.shape == (0, 4, 4) and T_shared_kf is None


def test_each_robots_line_holds_its_own_agents_only(uninterrupted: ServerNode) -> None:
    server = uninterrupted.map
    dropped = {"car1#3": "segments used up", "car2#4": "segments used up"}
    for name, session in uninterrupted.robots.items():
        line = robot_summary(server, session, dropped)
        assert line["agents"] == line["placed"] == [name] and line["provisional"] == [] and line["waiting"] == []
        assert line["keyframes"] == server.received(name) and line["done"] and line["state"] == session.state.value
        assert line["dropped_segments"] == {f"{name}#{3 if name == 'car1' else 4}": "segments used up"}
        assert provisional_note(server, name) is None  # both confirmed
    assert robot_summary(None, RobotSession("car9", "s9"), dropped)["agents"] == []  # no map yet
