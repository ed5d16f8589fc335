"""Odometry sources: ground truth and pose files relative to the first frame, errors, the factory."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import OdometryConfig, OdometryKind
from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y, so3_exp
from shgm_slam.io.trajectories import write_kitti_poses, write_tum
from shgm_slam.odometry.sources import (
    GroundTruthSource,
    KissIcpSource,
    OdometrySource,
    PoseFileSource,
    make_odometry,
)
from shgm_slam.types import Frame, Intrinsics

INTR = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_pose(so3_exp(rng.normal(0, 0.5, (n, 3))), rng.normal(0, 10, (n, 3)))


def _frames(poses: np.ndarray | None, n: int) -> list[Frame]:
    return [Frame(i, 0.1 * i, INTR, T_world_cam=None if poses is None else poses[i]) for i in range(n)]


def test_ground_truth_source_is_relative_to_the_first_frame():
    poses = _poses(6)
    src = GroundTruthSource()
    assert isinstance(src, OdometrySource)
    est = np.stack([src.update(f, np.zeros((0, 3))).T_odom_cam for f in _frames(poses, 6)])
    np.testing.assert_allclose(est, inverse(poses[0]) @ poses, atol=1e-9)
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-12)
    # relative motion between any two frames is the ground truth's
    np.testing.assert_allclose(inverse(est[2]) @ est[5], inverse(poses[2]) @ poses[5], atol=1e-9)


def test_ground_truth_source_without_poses_raises():
    with pytest.raises(DataError, match="no ground-truth pose"):
        GroundTruthSource().update(_frames(None, 1)[0], np.zeros((0, 3)))


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_pose_file_source_reads_kitti_and_tum(tmp_path, fmt):
    poses = _poses(5, seed=1)
    path = tmp_path / f"poses_{fmt}.txt"
    if fmt == "kitti":
        write_kitti_poses(path, poses)
    else:
        write_tum(path, np.arange(5) * 0.1, poses)
    src = PoseFileSource(path, 5)
    est = np.stack([src.update(f, np.zeros((0, 3))).T_odom_cam for f in _frames(None, 5)])
    np.testing.assert_allclose(est, inverse(poses[0]) @ poses, atol=1e-6)


def test_pose_file_count_mismatch_names_counts_and_file(tmp_path):
    path = tmp_path / "short.txt"
    write_kitti_poses(path, _poses(4))
    with pytest.raises(DataError, match=r"short\.txt has 4 poses but the sequence has 7 frames"):
        PoseFileSource(path, 7)


def test_pose_file_frame_out_of_range(tmp_path):
    path = tmp_path / "p.txt"
    write_kitti_poses(path, _poses(3))
    src = PoseFileSource(path, 3)
    with pytest.raises(DataError, match="frame 3 has no pose"):
        src.update(Frame(3, 0.3, INTR), np.zeros((0, 3)))


def test_factory_builds_every_kind(tmp_path):
    path = tmp_path / "p.txt"
    write_kitti_poses(path, make_pose(np.repeat(rot_y(0.1)[None], 3, 0), np.zeros((3, 3))))
    assert isinstance(make_odometry(OdometryConfig(kind=OdometryKind.KISS_ICP), 3), KissIcpSource)
    assert isinstance(make_odometry(OdometryConfig(kind=OdometryKind.GT), 3), GroundTruthSource)
    src = make_odometry(OdometryConfig(kind=OdometryKind.FILE, poses_file=path), 3)
    assert isinstance(src, PoseFileSource)
    with pytest.raises(DataError, match="3 poses but the sequence has 4 frames"):
        make_odometry(OdometryConfig(kind="file", poses_file=path), 4)


def test_kiss_source_reports_degenerate_frames():
    src = make_odometry(OdometryConfig(), 2)
    est = src.update(Frame(0, 0.0, INTR), np.zeros((10, 3)))
    assert not est.ok and "degenerate" in est.note
    np.testing.assert_allclose(est.T_odom_cam, np.eye(4))


def test_pose_file_source_on_kitti_ground_truth(shared_data):
    path = shared_data / "kitti" / "poses" / "07.txt"
    src = PoseFileSource(path, 1101)  # sequence 07 has 1101 frames
    np.testing.assert_allclose(src.T_odom_cam[0], np.eye(4), atol=1e-9)
    with pytest.raises(DataError, match="1101 poses but the sequence has 160 frames"):
        PoseFileSource(path, 160)  # e.g. only the 160 images that are on disk
