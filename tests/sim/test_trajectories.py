"""Robot trajectories: camera frames, fillets, lanes, speeds and the overlap measure."""

from __future__ import annotations

import numpy as np

from shgm_slam.sim.trajectories import (
    CAR_CAMERA_HEIGHT_M,
    RobotKind,
    Trajectory,
    arc_length,
    camera_poses,
    car_trajectories,
    fillet_path,
    lane_path,
    min_distance_m,
    shared_view_length_m,
    uav_trajectory,
    view_centres,
)


def test_camera_poses_are_kitti_camera_frames():
    fwd = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, -1.0, 0.0]])
    T = camera_poses(np.zeros((3, 3)), fwd, np.radians([0.0, 30.0, 90.0]), 0.0)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (3, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R[0, :, 2], [1, 0, 0], atol=1e-12)  # z forward
    np.testing.assert_allclose(R[0, :, 1], [0, 0, -1], atol=1e-12)  # y down
    np.testing.assert_allclose(R[0, :, 0], [0, -1, 0], atol=1e-12)  # x right (world y is left of +x)
    np.testing.assert_allclose(R[1, :, 2], [0, np.cos(np.radians(30)), -0.5], atol=1e-12)  # pitched down
    np.testing.assert_allclose(R[2, :, 2], [0, 0, -1], atol=1e-12)  # looking straight down


def test_fillet_path_turns_with_the_requested_radius():
    corners = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 80.0]])
    path = fillet_path(corners, 8.0)
    s = arc_length(path)
    assert abs(s[-1] - (180 - 2 * 8 + np.pi * 8 / 2)) < 0.5  # straight parts shortened, quarter circle added
    # the arc centre is (92, 8): points in the turn are 8 m from it
    turn = (path[:, 0] > 92.01) & (path[:, 1] < 7.99)
    np.testing.assert_allclose(np.linalg.norm(path[turn] - [92.0, 8.0], axis=1), 8.0, atol=0.05)
    lane = lane_path(path, 2.0)  # drive on the right: heading +x, right is -y
    assert np.allclose(lane[5, 1], -2.0, atol=1e-6)


def test_car_cameras_drive_smoothly_at_camera_height():
    corners = np.array([[0.0, 0.0], [150.0, 0.0], [150.0, 120.0]])
    lane = lane_path(fillet_path(corners, 8.0), 2.2)
    rng = np.random.default_rng(0)
    fwd, back = car_trajectories(lane, {"fwd": False, "back": True}, 10.0, 10.0, rng)
    np.testing.assert_allclose(fwd.positions_xyz, back.positions_xyz)
    np.testing.assert_allclose(fwd.positions_xyz[:, 2], CAR_CAMERA_HEIGHT_M)
    dots = np.einsum("ni,ni->n", fwd.T_world_cam[:, :3, 2], back.T_world_cam[:, :3, 2])
    assert np.all(dots < -0.99)  # the backward camera looks back
    speed = np.linalg.norm(np.diff(fwd.positions_xyz, axis=0), axis=1) * 10.0
    assert speed.max() < 11.0 and speed.min() > 2.0  # cruise ~10 m/s, slower in the curve
    assert speed[len(speed) // 2 - 20 : len(speed) // 2 + 20].min() < 0.8 * speed.max()
    yaw = np.unwrap(np.arctan2(fwd.T_world_cam[:, 1, 2], fwd.T_world_cam[:, 0, 2]))
    assert np.abs(np.diff(yaw)).max() < np.radians(8)  # no heading jumps
    assert abs(fwd.path_length_m - arc_length(lane)[-1]) < 12.0


def test_uav_flies_high_with_an_oblique_camera():
    rng = np.random.default_rng(1)
    uav = uav_trajectory("uav", np.array([[0.0, 0.0], [200.0, 0.0], [200.0, 150.0]]), 7.0, 10.0, rng)
    z = uav.positions_xyz[:, 2]
    assert uav.kind is RobotKind.UAV and z.min() >= 30 and z.max() <= 60
    pitch = np.degrees(np.arcsin(-uav.T_world_cam[:, 2, 2]))
    np.testing.assert_allclose(pitch, 50.0, atol=1.5)
    centres = view_centres(uav.T_world_cam)
    ahead = np.linalg.norm(centres - uav.positions_xyz[:, :2], axis=1)
    np.testing.assert_allclose(ahead, z / np.tan(np.radians(50.0)), rtol=0.05)


def test_overlap_measures():
    line = np.stack([np.linspace(0, 300, 301), np.zeros(301)], 1)
    rng = np.random.default_rng(2)
    a = car_trajectories(line, {"a": False}, 10.0, 10.0, rng)[0]
    far = Trajectory("far", RobotKind.CAR, a.T_world_cam.copy(), a.timestamps_s)
    far.T_world_cam[:, 1, 3] += 500.0
    assert abs(shared_view_length_m(a, a) - a.path_length_m) < 1.0
    assert shared_view_length_m(a, far) == 0.0
    assert abs(min_distance_m(a, far) - 500.0) < 1e-6
    half = a.truncated(len(a) // 2)
    assert abs(shared_view_length_m(a, half) - 0.5 * a.path_length_m) < 40.0  # + view radius and look-ahead
