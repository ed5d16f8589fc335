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


def last_keyframe_of_frames(frame_segment: np.ndarray, kf_frames: dict[int, np.ndarray]) -> np.ndarray:
    """(N,) index of each frame's last keyframe (at or before it) within its own segment; -1 for frames
    in no segment or before their segment's first keyframe.

    Args:
        frame_segment: (N,) segment index of each frame (-1: none).
        kf_frames: segment index -> (K,) increasing frame indices of that segment's keyframes.
    """
    out = np.full(frame_segment.shape, -1, dtype=np.int64)
    frames = np.arange(len(frame_segment))
    for seg, kfs in kf_frames.items():
        rows = frame_segment == seg
        if len(kfs):
            out[rows] = np.searchsorted(np.asarray(kfs), frames[rows], side="right") - 1
    return out


def fuse_segments(
    T_odom_cam: np.ndarray,
    frame_segment: np.ndarray,
    kf_frames: dict[int, np.ndarray],
    T_odom_kf: dict[int, np.ndarray],
    T_shared_kf: dict[int, np.ndarray],
) -> np.ndarray | None:
    """Per-frame fused poses of one robot whose frames are cut into trajectory segments.

    Args:
        T_odom_cam: (N, 4, 4) each frame in its own segment's odometry frame (NaN rows: no segment).
        frame_segment: (N,) segment of each frame (-1: none).
        kf_frames: segment -> (K,) frame index of each keyframe.
        T_odom_kf: segment -> (K, 4, 4) keyframe poses in the segment's odometry frame.
        T_shared_kf: segment -> (K, 4, 4) fused keyframe poses, for the segments placed in the shared frame.

    Returns:
        (N, 4, 4) ``T_shared_cam`` (NaN for frames of unplaced segments), or None when none is placed.
    """
    placed = [k for k, T in T_shared_kf.items() if T is not None and len(T)]
    if not placed:
        return None
    frame_kf = last_keyframe_of_frames(frame_segment, kf_frames)
    out = np.full_like(T_odom_cam, np.nan)
    for k in placed:
        K = min(len(T_shared_kf[k]), len(T_odom_kf[k]))
        rows = (frame_segment == k) & (frame_kf < K)
        out[rows] = fuse_frames(T_odom_cam[rows], frame_kf[rows], T_odom_kf[k][:K], T_shared_kf[k][:K])
    return out
