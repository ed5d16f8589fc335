"""A robot whose odometry jumps: ground-truth poses as a poses file, teleported from one frame on."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import write_kitti_poses
from shgm_slam.types import Sequence


def jumping_odometry(
    seq_dir: Path, tmp_path: Path, frame: int, jump_m: float = 30.0
) -> tuple[Sequence, ShgmConfig, np.ndarray]:
    """The sequence in ``seq_dir``, a config whose odometry reads its ground truth (relative to its first frame)
    moved ``jump_m`` along x from ``frame`` on, and that ground truth ((N, 4, 4) T_cam0_cam)."""
    seq = open_sequence(str(seq_dir))
    gt = se3.inverse(seq.gt_poses[0]) @ seq.gt_poses
    odo = gt.copy()
    odo[frame:, 0, 3] += jump_m
    write_kitti_poses(tmp_path / "odo.txt", odo)
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, tmp_path / "odo.txt"
    return seq, cfg, gt
