"""Fused trajectories: every frame rides on its last keyframe's pose-graph correction."""

from __future__ import annotations

import logging

import numpy as np

from shgm_slam.geometry import se3

log = logging.getLogger(__name__)


def fuse_frames(
    T_odom_cam: np.ndarray, frame_kf: np.ndarray, T_odom_kf: np.ndarray, T_shared_kf: np.ndarray
) -> np.ndarray:
    """Per-frame fused poses: each frame rides on its last keyframe's correction.

    Args:
        T_odom_cam: (N, 4, 4) odometry poses of all frames (NaN rows for skipped frames).
        frame_kf: (N,) index of the last keyframe at or before each frame (-1 before the first).
        T_odom_kf: (K, 4, 4) keyframe poses in the odometry frame.
        T_shared_kf: (K, 4, 4) optimized keyframe poses in the shared frame.

    Returns:
        (N, 4, 4) ``T_shared_cam``; NaN where the frame was skipped or precedes the first keyframe.
    """
    out = np.full_like(T_odom_cam, np.nan)
    ok = frame_kf >= 0
    k = frame_kf[ok]
    correction = T_shared_kf[k] @ se3.inverse(T_odom_kf[k])
    out[ok] = correction @ T_odom_cam[ok]
    return out
