"""Fused trajectories of robots cut into segments: each frame rides on its own segment's last keyframe."""

from __future__ import annotations

import numpy as np

from shgm_slam.fusion import fuse_segments, last_keyframe_of_frames
from shgm_slam.geometry import se3


def test_last_keyframe_is_found_within_the_frames_segment() -> None:
    seg = np.array([0, 0, 0, 0, -1, -1, 1, 1, 1])
    kf = last_keyframe_of_frames(seg, {0: np.array([0, 2]), 1: np.array([7])})
    np.testing.assert_array_equal(kf, [0, 0, 1, 1, -1, -1, -1, 0, 0])


def test_placed_segments_are_corrected_and_unplaced_ones_stay_nan() -> None:
    n = 8
    T_odom = np.stack([se3.make_pose(np.eye(3), np.array([i, 0.0, 0.0])) for i in range(n)])
    seg = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    T_odom[4:] = T_odom[:4]  # segment 1 restarts at the identity
    kf_frames = {0: np.array([0, 2]), 1: np.array([4, 6])}
    kf_poses = {k: T_odom[f] for k, f in kf_frames.items()}
    shift = se3.make_pose(se3.rot_z(0.3), np.array([10.0, -2.0, 1.0]))
    fused = fuse_segments(T_odom, seg, kf_frames, kf_poses, {0: shift @ kf_poses[0]})
    np.testing.assert_allclose(fused[:4], shift @ T_odom[:4], atol=1e-12)
    assert np.isnan(fused[4:]).all()
    assert fuse_segments(T_odom, seg, kf_frames, kf_poses, {}) is None
