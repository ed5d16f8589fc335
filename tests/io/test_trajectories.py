"""KITTI/TUM pose files: round trips, evo cross-checks, format detection and clear errors."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from evo.tools import file_interface

from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import make_pose, so3_exp
from shgm_slam.io.trajectories import (
    PoseFormat,
    read_kitti_poses,
    read_poses_file,
    read_tum,
    write_kitti_poses,
    write_tum,
)


@pytest.fixture
def poses() -> np.ndarray:
    rng = np.random.default_rng(7)
    return np.stack([make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 50) for _ in range(25)])


@pytest.fixture
def stamps() -> np.ndarray:
    return 1.7e9 + 0.1 * np.arange(25)


def test_kitti_round_trip_and_evo(tmp_path: Path, poses: np.ndarray) -> None:
    path = tmp_path / "out" / "est.txt"
    write_kitti_poses(path, poses)
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())
    np.testing.assert_allclose(read_kitti_poses(path), poses, atol=1e-8)
    evo_path = file_interface.read_kitti_poses_file(str(path))
    np.testing.assert_allclose(np.stack(evo_path.poses_se3), poses, atol=1e-8)
    file_interface.write_kitti_poses_file(str(tmp_path / "evo.txt"), evo_path)
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "evo.txt"), poses, atol=1e-8)


def test_tum_round_trip_and_evo(tmp_path: Path, poses: np.ndarray, stamps: np.ndarray) -> None:
    path = tmp_path / "est.tum"
    write_tum(path, stamps, poses)
    lines = path.read_text().splitlines()
    assert all(len(line.split(" ")) == 8 and not line.endswith(" ") for line in lines)
    t, read = read_tum(path)
    np.testing.assert_allclose(t, stamps, atol=1e-9, rtol=0)
    np.testing.assert_allclose(read, poses, atol=1e-8)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.timestamps, stamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, atol=1e-8)
    file_interface.write_tum_trajectory_file(str(tmp_path / "evo.tum"), traj)
    _, read2 = read_tum(tmp_path / "evo.tum")
    np.testing.assert_allclose(read2, poses, atol=1e-6)


def test_read_poses_file_detects_the_format(tmp_path: Path, poses: np.ndarray, stamps: np.ndarray) -> None:
    write_kitti_poses(tmp_path / "a.txt", poses)
    write_tum(tmp_path / "b.txt", stamps, poses)
    (tmp_path / "c.txt").write_text("# t x y z qx qy qz qw\n\n" + (tmp_path / "b.txt").read_text())
    kitti = read_poses_file(tmp_path / "a.txt")
    assert kitti.format is PoseFormat.KITTI and kitti.timestamps_s is None
    for name in ("b.txt", "c.txt"):
        tum = read_poses_file(tmp_path / name)
        assert tum.format is PoseFormat.TUM
        np.testing.assert_allclose(tum.timestamps_s, stamps, atol=1e-9, rtol=0)
        np.testing.assert_allclose(tum.poses, poses, atol=1e-8)


def test_small_rotation_errors_are_repaired(tmp_path: Path, poses: np.ndarray) -> None:
    noisy = poses.copy()
    noisy[:, :3, :3] += np.random.default_rng(1).normal(scale=1e-4, size=(len(poses), 3, 3))
    write_kitti_poses(tmp_path / "p.txt", noisy)
    R = read_kitti_poses(tmp_path / "p.txt")[:, :3, :3]
    RtR = np.einsum("nji,njk->nik", R, R)
    np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(R, poses[:, :3, :3], atol=1e-3)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", "line 1: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 x\n", "line 2: not a number"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n", "line 2: non-finite"),
        ("2 0 0 0 0 2 0 0 0 0 2 0\n", "line 1: the 3x3 part is not a rotation"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0\n", "line 1: the 3x3 part is not a rotation"),
    ],
)
def test_bad_kitti_files(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DataError, match=re.escape(f"bad.txt {message}")):
        read_kitti_poses(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("# header\n0 1 2 3 0 0 0 1\n0 1 2 3 0 0 1\n", "line 3: expected 8 numbers"),
        ("0 1 2 3 0 0 0 2\n", "line 1: quaternion norm 2"),
        ("0 1 2 3 0 0 0 inf\n", "line 1: non-finite"),
    ],
)
def test_bad_tum_files(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(DataError, match=re.escape(f"bad.tum {message}")):
        read_tum(path)


def test_read_poses_file_errors(tmp_path: Path) -> None:
    (tmp_path / "ten.txt").write_text("0 1 2 3 4 5 6 7 8 9\n")
    with pytest.raises(DataError, match=re.escape("ten.txt line 1: 10 columns")):
        read_poses_file(tmp_path / "ten.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(DataError, match=re.escape("empty.txt has no pose rows")):
        read_poses_file(tmp_path / "empty.txt")
    with pytest.raises(DataError, match=re.escape("missing.txt does not exist")):
        read_poses_file(tmp_path / "missing.txt")


def test_writers_reject_bad_input(tmp_path: Path, poses: np.ndarray) -> None:
    with pytest.raises(DataError, match=re.escape("x.txt")):
        write_kitti_poses(tmp_path / "x.txt", poses[:, :3])
    bad = poses.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        write_kitti_poses(tmp_path / "x.txt", bad)
    with pytest.raises(DataError, match="one finite timestamp per pose"):
        write_tum(tmp_path / "x.tum", np.arange(3.0), poses)


def test_real_kitti_ground_truth(shared_data: Path) -> None:
    path = shared_data / "kitti" / "poses" / "00.txt"
    poses = read_kitti_poses(path)
    assert poses.shape == (4541, 4, 4)
    np.testing.assert_array_equal(poses[:, :3, :4].reshape(-1, 12), np.loadtxt(path))


def test_a_comment_line_is_skipped_by_every_reader(tmp_path: Path, poses: np.ndarray, stamps: np.ndarray) -> None:
    from shgm_slam.io.trajectories import read_comments

    note = "provisional: placed from one match\n(keyframes 3-9)"
    write_tum(tmp_path / "a.tum", stamps, poses, comment=note)
    write_kitti_poses(tmp_path / "a.txt", poses, comment=note)
    for path in (tmp_path / "a.tum", tmp_path / "a.txt"):
        first, *rows = path.read_text().splitlines()
        assert first == "# provisional: placed from one match (keyframes 3-9)" and len(rows) == len(poses)
        assert read_comments(path) == ["provisional: placed from one match (keyframes 3-9)"]
    np.testing.assert_allclose(read_tum(tmp_path / "a.tum")[1], poses, atol=1e-8)
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "a.txt"), poses, atol=1e-8)
    assert len(file_interface.read_tum_trajectory_file(str(tmp_path / "a.tum")).poses_se3) == len(poses)
    assert len(file_interface.read_kitti_poses_file(str(tmp_path / "a.txt")).poses_se3) == len(poses)
    write_tum(tmp_path / "plain.tum", stamps, poses)
    assert read_comments(tmp_path / "plain.tum") == []


def test_pose_files_far_beyond_any_world_or_out_of_time_order_are_refused(tmp_path):
    from shgm_slam.io.trajectories import read_poses_file

    far = tmp_path / "far.txt"
    far.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1e200 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match="line 2: a position farther than"):
        read_poses_file(far)
    backwards = tmp_path / "back.txt"
    backwards.write_text("1.0 0 0 0 0 0 0 1\n0.5 0 0 1 0 0 0 1\n")
    with pytest.raises(DataError, match=r"line 2: timestamp 0\.5 s is not after"):
        read_poses_file(backwards)
    repeated = tmp_path / "same.txt"
    repeated.write_text("0 0 0 0 0 0 0 1\n0 0 0 1 0 0 0 1\n")
    with pytest.raises(DataError, match="time order"):
        read_poses_file(repeated)


def test_a_pose_file_that_is_a_directory_says_so(tmp_path):
    (tmp_path / "poses.txt").mkdir()
    with pytest.raises(DataError, match=r"poses\.txt is a directory, not a file"):
        read_poses_file(tmp_path / "poses.txt")
