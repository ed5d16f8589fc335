"""Whole-sequence checks before a run: one clear error instead of every frame skipped or a robot that never moves."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.data import open_sequence
from shgm_slam.data.validate import check_sequence_start, probe_indices
from shgm_slam.errors import DataError, ModelError
from tests.data.conftest import make_frames, write_frames


def files(frame):
    return frame.depth_m, frame.label_ids


def test_probe_indices_cover_the_start_and_the_spread():
    assert probe_indices(1) == [0]
    assert probe_indices(100) == [0, 1, 2, 25, 50, 75]


def test_a_clean_sequence_passes(seq_dir: Path):
    check_sequence_start("car", open_sequence(seq_dir), files)


def test_one_bad_frame_is_left_to_the_run(seq_dir: Path):
    (seq_dir / "depth" / "000000.png").write_bytes(b"not a png")
    check_sequence_start("car", open_sequence(seq_dir), files)


def test_depth_all_zero_is_one_error(tmp_path: Path):
    frames = make_frames(6)
    for f in frames:
        f.depth_m = np.zeros_like(f.depth_m)
    seq = open_sequence(write_frames(tmp_path / "s", frames))
    with pytest.raises(DataError, match=r"robot 'car'.*depth has no valid pixel"):
        check_sequence_start("car", seq, files)


def test_every_depth_png_of_the_wrong_dtype_is_one_error(seq_dir: Path):
    for p in sorted((seq_dir / "depth").glob("*.png")):
        cv2.imwrite(str(p), np.full((24, 32), 7, np.uint8))
    with pytest.raises(DataError, match=r"none can be used.*uint8"):
        check_sequence_start("car", open_sequence(seq_dir), files)


def test_every_depth_png_of_the_wrong_size_is_one_error(seq_dir: Path):
    for p in sorted((seq_dir / "depth").glob("*.png")):
        cv2.imwrite(str(p), np.full((12, 16), 700, np.uint16))
    with pytest.raises(DataError, match="none can be used"):
        check_sequence_start("car", open_sequence(seq_dir), files)


def test_labels_all_ignore_is_one_error(tmp_path: Path):
    frames = make_frames(4)
    for f in frames:
        f.label_ids = np.full_like(f.label_ids, 255)
    with pytest.raises(DataError, match="no label is a Cityscapes train id"):
        check_sequence_start("car", open_sequence(write_frames(tmp_path / "s", frames)), files)


def test_labels_in_another_label_space_are_one_error(tmp_path: Path):
    """Cityscapes label ids (road 7, car 26) read as train ids: 7 a traffic sign, 26 ignored, silently."""
    frames = make_frames(4)
    for f in frames:
        f.label_ids = np.where(np.arange(f.label_ids.shape[1]) % 2 == 0, 7, 26).astype(np.uint8)[None].repeat(
            f.label_ids.shape[0], axis=0)  # fmt: skip
    with pytest.raises(DataError, match=r"50 % of the label pixels are 26, no Cityscapes train id.*label ids"):
        check_sequence_start("car", open_sequence(write_frames(tmp_path / "s", frames)), files)


def test_a_few_stray_label_values_are_left_alone(tmp_path: Path):
    frames = make_frames(4)
    for f in frames:
        f.label_ids[0, 0] = 77  # one pixel in 768: below 1 %
    check_sequence_start("car", open_sequence(write_frames(tmp_path / "s", frames)), files)


def test_model_outputs_nan_or_constant_are_model_errors(seq_dir: Path):
    seq = open_sequence(seq_dir)

    def nan_depth(frame):
        return np.full(frame.depth_m.shape, np.nan, np.float32), frame.label_ids

    with pytest.raises(ModelError, match=r"depth model d.onnx: no valid depth"):
        check_sequence_start("car", seq, nan_depth, depth_model="d.onnx")

    def flat_depth(frame):
        return np.full(frame.depth_m.shape, 80.0, np.float32), frame.label_ids

    with pytest.raises(ModelError, match="constant output"):
        check_sequence_start("car", seq, flat_depth, depth_model="d.onnx")
    with pytest.raises(DataError, match=r"depth is 80 m in every valid pixel of each frame"):
        check_sequence_start("car", seq, flat_depth)  # a constant depth file is not a model's fault: the data's

    def flat_per_frame(frame):  # a 1x1 output resized to the image: one value per frame, float noise aside
        value = np.float32(5.0 + frame.index)
        return np.full(frame.depth_m.shape, value) * (1 + 1e-7 * np.arange(frame.depth_m.size).reshape(
            frame.depth_m.shape) / frame.depth_m.size).astype(np.float32), frame.label_ids  # fmt: skip

    with pytest.raises(ModelError, match=r"one value in each frame \(5-.* m across frames, a 1x1 output"):
        check_sequence_start("car", seq, flat_per_frame, depth_model="d.onnx")
    with pytest.raises(DataError, match=r"depth is one value \(5-.* m\) in every valid pixel of each frame"):
        check_sequence_start("car", seq, flat_per_frame)

    def one_class(frame):
        return frame.depth_m, np.full(frame.label_ids.shape, 2, np.uint8)

    with pytest.raises(ModelError, match=r"segmentation model s.onnx: constant output"):
        check_sequence_start("car", seq, one_class, seg_model="s.onnx")

    def one_class_and_ignore(frame):  # a card listing fewer classes than the model outputs: the rest is ignore
        labels = np.full(frame.label_ids.shape, 255, np.uint8)
        labels[-4:] = 0
        return frame.depth_m, labels

    with pytest.raises(ModelError, match=r"constant output \(train id 0, road, wherever not ignore\).*one class"):
        check_sequence_start("car", seq, one_class_and_ignore, seg_model="s.onnx")  # as check-model refuses it


def test_depth_in_millimetres_is_one_error(seq_dir: Path):
    """Float depth in millimetres (given in memory or by a model) ran to the end: an odometry that did not move and
    no graph nodes, every object beyond the extraction range."""
    seq = open_sequence(seq_dir)

    def millimetres(frame):
        return frame.depth_m * 1000.0, frame.label_ids

    with pytest.raises(DataError, match=r"median valid depth .* m on robot 'car'.*in millimetres\? divide it by 1000"):
        check_sequence_start("car", seq, millimetres)
    with pytest.raises(ModelError, match=r"depth model d.onnx: median valid depth .*scale"):
        check_sequence_start("car", seq, millimetres, depth_model="d.onnx")

    def far_sky(frame):  # a renderer's far plane for the sky: far, but not most of the image
        depth = frame.depth_m.copy()
        depth[: depth.shape[0] // 3] = 1e4
        return depth, frame.label_ids

    check_sequence_start("car", seq, far_sky)

    def mostly_sky(frame, scale=1.0):  # a camera at the horizon: a sky value over most of each frame
        depth = frame.depth_m * scale
        depth[: 3 * depth.shape[0] // 4] = 1e4
        return depth, frame.label_ids

    check_sequence_start("car", seq, mostly_sky)  # refused as "median valid depth 1e+04 m" before
    with pytest.raises(DataError, match=r"median valid depth .* m on robot 'car'.*in millimetres\? divide it by 1000"):
        check_sequence_start("car", seq, lambda frame: mostly_sky(frame, 1000.0))  # the ground still in millimetres

    def varying_sky(frame, scale=1.0):  # a network's sky: far values that vary from pixel to pixel, most of the frame
        depth = frame.depth_m * scale
        rows = 3 * depth.shape[0] // 4
        depth[:rows] = np.random.default_rng(frame.index).uniform(3e3, 3e4, size=depth[:rows].shape)
        return depth, frame.label_ids

    check_sequence_start("car", seq, varying_sky)  # refused as "median valid depth 1.6e+04 m" before
    with pytest.raises(DataError, match=r"median valid depth .* m on robot 'car'.*in millimetres\? divide it by 1000"):
        check_sequence_start("car", seq, lambda frame: varying_sky(frame, 1000.0))


def test_depth_files_of_one_value_are_one_error(tmp_path: Path):
    """Every depth PNG 65535 (a sensor's saturation value): a run went on with KISS-ICP sliding through a sphere of
    256 m around the camera, a car's odometry 68 m off, exit 0 and no warning. A few invalid pixels (0) change
    nothing; one frame of real depth among them passes."""
    frames = make_frames(6)
    for f in frames:
        f.depth_m = np.where(f.depth_m > 0, 65535 / 256, 0.0).astype(np.float32)
    seq = open_sequence(write_frames(tmp_path / "s", frames))
    with pytest.raises(DataError, match=r"robot 'car'.*depth is 255\.996 m in every valid pixel.*saturated"):
        check_sequence_start("car", seq, files)
    frames[2] = make_frames(3)[2]
    check_sequence_start("car", open_sequence(write_frames(tmp_path / "t", frames)), files)


def test_run_on_all_zero_depth_exits_2_before_any_frame(tmp_path: Path):
    frames = make_frames(6)
    for f in frames:
        f.depth_m = np.zeros_like(f.depth_m)
    seq = write_frames(tmp_path / "s", frames)
    res = CliRunner().invoke(app, ["run", "--robot", f"car={seq}", "--rerun", "off", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "no valid pixel" in res.output.replace("\n", "")
    assert not (tmp_path / "o" / "metrics.json").exists()
