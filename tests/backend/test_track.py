"""A robot's record in the pose graph: keyframe poses, path length and ground normals, kept as they came."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.track import RobotTrack
from shgm_slam.geometry.se3 import make_pose, rot_y


def test_keyframes_path_and_normals_are_kept_as_they_came_past_the_buffers_growth() -> None:
    track = RobotTrack(index=1)
    poses = [make_pose(rot_y(0.01 * k), [0.0, 0.0, 1.5 * k]) for k in range(40)]  # past 16 and 32 buffered rows
    for k, T in enumerate(poses):
        track.append(T, np.array([0.0, -1.0, 0.0]) if k % 3 == 0 else None)
    odom, path = track.odometry()
    np.testing.assert_array_equal(odom, np.stack(poses))
    np.testing.assert_allclose(path, 1.5 * np.arange(40))  # the odometry's own path length, metres
    assert track.path_m == path.tolist()
    assert track.measured == list(range(0, 40, 3))
    assert np.isnan(track.up_odom[1]).all() and np.array_equal(track.up_odom[3], [0.0, -1.0, 0.0])
    assert not track.anchored and track.anchor_closure is None


def test_an_empty_track_has_an_empty_odometry() -> None:
    odom, path = RobotTrack(index=0).odometry()
    assert odom.shape == (0, 4, 4) and path.shape == (0,)
