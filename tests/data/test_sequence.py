"""Our layout: SequenceWriter -> ShgmSequence round trips, lazy loading, and clear errors for bad files."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from shgm_slam.data import SequenceWriter, ShgmSequence, decode_depth, encode_depth, open_sequence
from shgm_slam.errors import DataError
from shgm_slam.types import Frame, Sequence
from tests.data.conftest import INTRINSICS, make_frames, write_frames


def test_round_trip_equals_input(seq_dir: Path, frames: list[Frame]) -> None:
    seq = ShgmSequence(seq_dir)
    assert isinstance(seq, Sequence)
    assert len(seq) == len(frames) and seq.has_depth and seq.has_labels
    assert seq.intrinsics == INTRINSICS
    np.testing.assert_allclose(seq.timestamps_s, [f.timestamp_s for f in frames], atol=1e-9)
    np.testing.assert_allclose(seq.gt_poses, np.stack([f.T_world_cam for f in frames]), atol=1e-8)
    for written, read in zip(frames, seq, strict=True):
        assert read.index == read.source_index == written.index
        np.testing.assert_array_equal(read.image_rgb, written.image_rgb)
        np.testing.assert_array_equal(read.label_ids, written.label_ids)
        assert read.depth_m.dtype == np.float32
        valid = np.isfinite(written.depth_m) & (written.depth_m > 0)
        np.testing.assert_array_less(np.abs(read.depth_m[valid] - written.depth_m[valid]), 1 / 256)
        assert (read.depth_m[~valid] == 0).all()
        np.testing.assert_allclose(read.T_world_cam, written.T_world_cam, atol=1e-8)


def test_calib_has_four_kitti_projection_lines(seq_dir: Path) -> None:
    lines = (seq_dir / "calib.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in lines] == ["P0", "P1", "P2", "P3"]
    for line in lines:
        P = np.array(line.split(":")[1].split(), dtype=float).reshape(3, 4)
        np.testing.assert_allclose(P[:, :3], INTRINSICS.K)
        assert (P[:, 3] == 0).all()


def test_depth_encoding_clips_and_zeroes_invalid() -> None:
    d = np.array([[0.0, np.nan, -1.0, np.inf, 1.0, 300.0, 10.123]], dtype=np.float32)
    png = encode_depth(d)
    assert png.dtype == np.uint16
    assert png.tolist() == [[0, 0, 0, 0, 256, 65535, round(10.123 * 256)]]
    np.testing.assert_allclose(decode_depth(png)[0, 6], 10.123, atol=1 / 512)


def test_writer_streams_lines_before_close(tmp_path: Path) -> None:
    writer = SequenceWriter(tmp_path / "s", INTRINSICS)
    for frame in make_frames(3):
        writer.write(frame)
    assert len((tmp_path / "s" / "times.txt").read_text().splitlines()) == 3
    assert len((tmp_path / "s" / "poses.txt").read_text().splitlines()) == 3
    assert len(open_sequence(tmp_path / "s")) == 3  # an interrupted run is readable as is
    writer.close()
    writer.close()
    with pytest.raises(DataError, match="closed"):
        writer.write(make_frames(1)[0])


def test_writer_without_depth_labels_and_poses(tmp_path: Path) -> None:
    frames = make_frames(2, with_pose=False)
    for f in frames:
        f.depth_m = f.label_ids = None
    root = write_frames(tmp_path / "s", frames, write_depth=False, write_labels=False)
    assert not (root / "depth").exists() and not (root / "poses.txt").exists()
    seq = open_sequence(root)
    assert not seq.has_depth and not seq.has_labels and seq.gt_poses is None
    assert seq[1].depth_m is None and seq[1].T_world_cam is None


def test_writer_refuses_non_empty_folder_unless_overwrite(seq_dir: Path) -> None:
    with pytest.raises(DataError, match=str(seq_dir)):
        SequenceWriter(seq_dir, INTRINSICS)
    (seq_dir / "notes.md").write_text("keep me")
    write_frames(seq_dir, make_frames(2, seed=3), overwrite=True)
    assert len(open_sequence(seq_dir)) == 2
    assert len(list((seq_dir / "depth").iterdir())) == 2
    assert (seq_dir / "notes.md").read_text() == "keep me"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda f: setattr(f, "depth_m", None), "write_depth=False"),
        (lambda f: setattr(f, "label_ids", None), "write_labels=False"),
        (lambda f: setattr(f, "image_rgb", np.zeros((10, 10, 3), np.uint8)), "10x10"),
        (lambda f: setattr(f, "image_rgb", f.image_rgb.astype(np.float32)), "uint8"),
        (lambda f: setattr(f, "label_ids", f.label_ids.astype(np.int32) + 300), "0..255"),
        (lambda f: setattr(f, "T_world_cam", None), "T_world_cam"),
        (lambda f: setattr(f, "timestamp_s", float("nan")), "timestamp"),
    ],
)
def test_writer_rejects_bad_frames(tmp_path: Path, change, message: str) -> None:
    good, bad = make_frames(2)
    change(bad)
    with SequenceWriter(tmp_path / "s", INTRINSICS) as writer:
        writer.write(good)
        with pytest.raises(DataError, match=message):
            writer.write(bad)


def test_frames_load_lazily(seq_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seq = open_sequence(seq_dir)
    read: list[str] = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda path, *a: read.append(Path(path).name) or real_imread(path, *a))
    frame = seq[5]
    assert read == ["000005.png"] * 3  # image, depth, labels of frame 5 only
    assert frame.image_rgb is not None and frame.depth_m is not None and frame.label_ids is not None


@pytest.mark.parametrize(
    ("folder", "content"),
    [
        ("image_2", b"not a png"),  # corrupt PNG
        ("depth", np.ones((24, 32), np.uint8)),  # wrong dtype
        ("semantic", np.ones((24, 32), np.uint16)),  # wrong dtype
        ("semantic", np.ones((24, 32, 3), np.uint8)),  # colour labels
        ("image_2", np.ones((12, 16, 3), np.uint8)),  # wrong size
        ("depth", np.ones((12, 16), np.uint16)),  # wrong size
    ],
)
def test_bad_frame_file_names_the_file(seq_dir: Path, folder: str, content) -> None:
    path = seq_dir / folder / "000003.png"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        assert cv2.imwrite(str(path), content)
    seq = open_sequence(seq_dir)
    seq[2]  # other frames still load
    with pytest.raises(DataError, match=re.escape(str(path))):
        seq[3]


def _drop_last_line(path: Path) -> None:
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:-1]))


@pytest.mark.parametrize(
    ("damage", "culprit"),
    [
        (lambda r: _drop_last_line(r / "times.txt"), "times.txt"),
        (lambda r: _drop_last_line(r / "poses.txt"), "poses.txt"),
        (lambda r: (r / "times.txt").write_text((r / "times.txt").read_text() + "9.0\n"), "times.txt"),
        (lambda r: (r / "depth" / "000007.png").unlink(), "depth"),
        (lambda r: (r / "semantic" / "000008.png").write_bytes(b""), "semantic"),
        (lambda r: (r / "image_2" / "000004.png").unlink(), "image_2/000004.png"),
        (lambda r: (r / "calib.txt").unlink(), "calib.txt"),
        (lambda r: (r / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n"), "calib.txt"),
        (lambda r: (r / "calib.txt").write_text("P2: 1 0 0 0 0 1 0 0 0 0 1\n"), "calib.txt"),
        (lambda r: (r / "times.txt").unlink(), "times.txt"),
        (lambda r: (r / "times.txt").write_text("0.0\nabc\n"), "times.txt"),
    ],
)
def test_inconsistent_sequence_names_the_file(seq_dir: Path, damage, culprit: str) -> None:
    damage(seq_dir)
    with pytest.raises(DataError, match=re.escape(culprit)):
        open_sequence(seq_dir)
