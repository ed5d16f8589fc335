"""KITTI odometry layout: the real sequence 07 frames, ground-truth lookup, partial downloads, P2 offset."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from shgm_slam.data import KittiSequence, SequenceLayout, detect_layout, open_sequence
from shgm_slam.errors import DataError
from shgm_slam.io.trajectories import read_kitti_poses, write_kitti_poses

SEQ07_K = dict(fx=707.0912, fy=707.0912, cx=601.8873, cy=183.1104, width=1226, height=370)


def _kitti_root(tmp_path: Path, shared_data: Path) -> Path:
    """``<tmp>/sequences/07`` -> the shared sequence 07 and ``<tmp>/poses/07.txt`` -> its ground truth."""
    (tmp_path / "sequences").mkdir()
    (tmp_path / "poses").mkdir()
    (tmp_path / "sequences" / "07").symlink_to(shared_data / "kitti" / "sequences" / "07")
    (tmp_path / "poses" / "07.txt").symlink_to(shared_data / "kitti" / "poses" / "07.txt")
    return tmp_path / "sequences" / "07"


def test_real_sequence_07_partial_download(tmp_path: Path, shared_data: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="shgm_slam.data.kitti"):
        seq = open_sequence(_kitti_root(tmp_path, shared_data))
    assert detect_layout(seq.root) is SequenceLayout.KITTI
    # shared 07 holds 160 images but 1101 times and poses: accepted, trimmed, with a warning each
    assert len(seq) == 160
    assert sum("1101 rows for 160 images" in r.getMessage() for r in caplog.records) == 2
    for key, value in SEQ07_K.items():
        assert getattr(seq.intrinsics, key) == pytest.approx(value)
    gt = read_kitti_poses(shared_data / "kitti" / "poses" / "07.txt")
    np.testing.assert_allclose(seq.gt_poses, gt[:160])  # P0 = [K|0]: no camera offset
    np.testing.assert_allclose(seq.timestamps_s[:2], [0.0, 0.1038752])
    frame = seq[159]
    assert frame.image_rgb.shape == (370, 1226, 3) and frame.image_rgb.dtype == np.uint8
    gray = cv2.imread(str(shared_data / "kitti/sequences/07/image_0/000159.png"), cv2.IMREAD_GRAYSCALE)
    for c in range(3):
        np.testing.assert_array_equal(frame.image_rgb[..., c], gray)
    np.testing.assert_allclose(frame.T_world_cam, gt[159])


def _trimmed_copy(dst: Path, shared_data: Path, n: int = 20) -> Path:
    src = shared_data / "kitti" / "sequences" / "07"
    (dst / "image_0").mkdir(parents=True)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    for i in range(n):
        shutil.copy(src / "image_0" / f"{i:06d}.png", dst / "image_0" / f"{i:06d}.png")
    (dst / "times.txt").write_text("".join((src / "times.txt").read_text().splitlines(keepends=True)[:n]))
    write_kitti_poses(dst / "poses.txt", read_kitti_poses(shared_data / "kitti/poses/07.txt")[:n])
    return dst


def test_trimmed_copy_is_consistent(tmp_path: Path, shared_data: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING):
        seq = open_sequence(_trimmed_copy(tmp_path / "07", shared_data))
    assert not caplog.records
    assert len(seq) == 20 and seq.gt_poses.shape == (20, 4, 4)
    assert seq[-1].source_index == 19


def test_fewer_times_than_images_is_an_error(tmp_path: Path, shared_data: Path) -> None:
    root = _trimmed_copy(tmp_path / "07", shared_data)
    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DataError, match=r"times\.txt has 2 rows but there are 20 images"):
        open_sequence(root)


def _synthetic_kitti(root: Path, P2: np.ndarray, n: int = 3) -> np.ndarray:
    """image_2 + image_0 folders, calib with P0/P2, poses.txt; returns the written T_world_cam0."""
    for folder in ("image_2", "image_0"):
        (root / folder).mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_2" / f"{i:06d}.png"), np.full((6, 8, 3), (10, 20, 30), np.uint8))
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((6, 8), 99, np.uint8))
    P0 = np.hstack([P2[:, :3], np.zeros((3, 1))])
    (root / "calib.txt").write_text(
        "".join(f"{k}: {' '.join(map(str, P.ravel()))}\n" for k, P in (("P0", P0), ("P2", P2)))
    )
    (root / "times.txt").write_text("".join(f"{0.1 * i}\n" for i in range(n)))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.arange(3 * n).reshape(n, 3)
    poses[1, :3, :3] = cv2.Rodrigues(np.array([0.1, 0.5, -0.2]))[0]
    write_kitti_poses(root / "poses.txt", poses)
    return poses


def _poses_times(root: Path, factor: float) -> None:
    """The folder's poses.txt with its translations multiplied by ``factor`` (other units)."""
    poses = read_kitti_poses(root / "poses.txt")
    poses[:, :3, 3] *= factor
    write_kitti_poses(root / "poses.txt", poses)


def test_image_2_preferred_and_gt_moved_to_camera_2(tmp_path: Path) -> None:
    K = np.array([[7.0, 0, 4], [0, 7, 3], [0, 0, 1]])  # a 60-degree view of 8x6 px
    t_cam2_cam0 = np.array([0.06, 0.001, 0.005])  # cam0's origin seen from camera 2
    poses_cam0 = _synthetic_kitti(tmp_path / "s", np.hstack([K, (K @ t_cam2_cam0)[:, None]]))
    seq = KittiSequence(tmp_path / "s")
    np.testing.assert_array_equal(seq[0].image_rgb[0, 0], (30, 20, 10))  # BGR file -> RGB
    expected = poses_cam0[:, :3, 3] - np.einsum("nij,j->ni", poses_cam0[:, :3, :3], t_cam2_cam0)
    np.testing.assert_allclose(seq.gt_poses[:, :3, 3], expected, atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses[:, :3, :3], poses_cam0[:, :3, :3], atol=1e-12)


def test_image_0_uses_p0(tmp_path: Path) -> None:
    K = np.array([[7.0, 0, 4], [0, 7.1, 3], [0, 0, 1]])
    _synthetic_kitti(tmp_path / "s", np.hstack([K, np.ones((3, 1))]))
    shutil.rmtree(tmp_path / "s" / "image_2")
    seq = KittiSequence(tmp_path / "s")
    assert (seq.intrinsics.fy, seq.intrinsics.width, seq.intrinsics.height) == (7.1, 8, 6)
    assert (seq[2].image_rgb == 99).all()


@pytest.mark.parametrize(
    ("damage", "culprit"),
    [
        (lambda r: [shutil.rmtree(r / f) for f in ("image_0", "image_2")], "neither image_2/ nor image_0/"),
        (lambda r: [p.unlink() for p in (r / "image_2").iterdir()], "image_2 has no .png"),
        # a copy beside the frames was reported as the next frame missing, which was there
        (lambda r: shutil.copy(r / "image_2" / "000001.png", r / "image_2" / "000001_copy.png"),
         "000001_copy.png is not a frame"),
        (lambda r: (r / "image_2" / "000001.png").unlink(), "000001.png is missing"),
        (lambda r: (r / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n"), "calib.txt has no P2"),
        (lambda r: (r / "poses.txt").write_text("1 0 0\n"), "poses.txt line 1"),
        (lambda r: (r / "calib.txt").write_text("P2: 0 0 4 0 0 0 3 0 0 0 1 0\n"), "focal lengths must be positive"),
        (lambda r: (r / "calib.txt").write_text("P2: -700 0 4 0 0 700 3 0 0 0 1 0\n"), "mirrors the map"),
        (lambda r: (r / "calib.txt").write_text("P2: 700 0 4 0 0 700 3 0 0 0 1 0\n"), "calib for another resolution"),
        (lambda r: (r / "calib.txt").write_text("P2: 7 0 600 0 0 7 3 0 0 0 1 0\n"), "principal point (600, 3)"),
        (lambda r: (r / "calib.txt").write_bytes(b"P2: 7\xff\xfe 0 4\n"), "not UTF-8 text"),
        (lambda r: (r / "calib.txt").write_text("P2: nan 0 4 0 0 700 3 0 0 0 1 0\n"), "P2 line of 12 finite numbers"),
        (lambda r: (r / "times.txt").write_text("0.0\n0.1\n0.1\n"), "line 3 (0.1 s) is not after line 2"),
        (lambda r: (r / "times.txt").write_text("0.2\n0.1\n0.3\n"), "timestamps must increase"),
        (lambda r: (r / "times.txt").write_text("0.0\nnan\n0.3\n"), "line 2 holds nan"),
        # a 10 Hz camera's times in microseconds (read as 28 hours apart) and a step of 1 us
        (lambda r: (r / "times.txt").write_text("".join(f"{1e5 * i}\n" for i in range(3))), "1e+05 s apart"),
        (lambda r: (r / "times.txt").write_text("".join(f"{1e-6 * i}\n" for i in range(3))), "must be in seconds"),
        # ground truth in millimetres: the fused ATE came out in kilometres, without a word
        (lambda r: _poses_times(r, 1000.0), "poses.txt: the ground truth moves at 5.2e+04 m/s"),
    ],
)
def test_bad_kitti_folder_names_the_problem(tmp_path: Path, damage, culprit: str) -> None:
    _synthetic_kitti(tmp_path / "s", np.hstack([np.eye(3), np.zeros((3, 1))]))
    damage(tmp_path / "s")
    with pytest.raises(DataError, match=re.escape(culprit)):
        KittiSequence(tmp_path / "s")


@pytest.mark.parametrize(
    ("P_row", "words"),
    [
        ([700.0, 5000.0, 150.0, 0.0, 0.0, 700.0, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "pinhole"),  # skew
        ([1e300, 0.0, 150.0, 0.0, 0.0, 1e300, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "focal lengths"),
        ([1e-300, 0.0, 150.0, 0.0, 0.0, 1e-300, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "focal lengths"),
        # KITTI's 707 px mistyped as 0.912 (fx only): a 179.7-degree view and pixels stretched 775-fold
        ([0.912, 0.0, 150.0, 0.0, 0.0, 707.0, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "field of view"),
        ([7.07, 0.0, 150.0, 0.0, 0.0, 7.07, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "field of view"),  # in cm?
        ([300.0, 0.0, 150.0, 0.0, 0.0, 707.0, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "differ 2.36-fold"),
        ([7.07e5, 0.0, 150.0, 0.0, 0.0, 7.07e5, 45.0, 0.0, 0.0, 0.0, 1.0, 0.0], "field of view"),  # in mm?
    ],
)
def test_a_skewed_or_absurd_focal_projection_is_refused(P_row, words):
    from shgm_slam.data.kitti import check_projection

    P = np.asarray(P_row).reshape(3, 4)
    with pytest.raises(DataError, match=words):
        check_projection(P, 320, 96, Path("calib.txt"), "P2")


@pytest.mark.parametrize("hfov_deg", [10.0, 60.0, 90.0, 150.0])
def test_real_cameras_fields_of_view_pass(hfov_deg):
    from shgm_slam.data.kitti import check_projection
    from shgm_slam.sim.render import make_intrinsics

    for w, h in ((1242, 375), (320, 96), (640, 480)):
        K = make_intrinsics(w, h, hfov_deg)
        check_projection(np.array([[K.fx, 0, K.cx, 0], [0, K.fy, K.cy, 0], [0, 0, 1, 0]]), w, h, Path("c"), "P2")
    kitti = np.array([[718.856, 0, 607.1928, 45.38], [0, 718.856, 185.2157, -0.1130], [0, 0, 1, 3.7e-3]])
    check_projection(kitti, 1241, 376, Path("calib.txt"), "P2")


def test_a_corrupt_frame_advises_a_frame_range_that_leaves_it_out(seq_dir: Path) -> None:
    """Deleting the corrupt file would leave a gap in the numbering, which is refused: the advice is a range."""
    from shgm_slam.data.kitti import read_png

    path = seq_dir / "image_2" / "000003.png"
    path.write_bytes(b"not a png")
    with pytest.raises(DataError, match=re.escape("re-export that file, or use a frame range that leaves it out "
                                                  "(SEQ:0-3 or SEQ:4-)")):  # fmt: skip
        read_png(path, cv2.IMREAD_COLOR)
    after = open_sequence(f"{seq_dir}:4-")  # the advice works
    assert after[0].image_rgb is not None
    (seq_dir / "image_2" / "000000.png").write_bytes(b"")
    with pytest.raises(DataError, match=re.escape("(SEQ:1-)")):
        read_png(seq_dir / "image_2" / "000000.png", cv2.IMREAD_COLOR)


@pytest.mark.parametrize("name", ["calib.txt", "times.txt"])
def test_a_sequence_file_that_is_a_directory_says_so(seq_dir: Path, name: str) -> None:
    (seq_dir / name).unlink()
    (seq_dir / name).mkdir()
    with pytest.raises(DataError, match=re.escape(f"{name} is a directory, not a file")):
        open_sequence(seq_dir)
