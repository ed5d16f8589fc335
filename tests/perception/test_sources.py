"""Perception sources: files, ONNX models with per-modality fallback, and the config factory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import PerceptionConfig
from shgm_slam.errors import DataError, ModelError
from shgm_slam.perception import (
    OnnxPerception,
    PerceptionOutput,
    PerceptionSource,
    SequenceFilesSource,
    make_perception,
)
from shgm_slam.perception.card import parse_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.types import Frame, Intrinsics, Sequence
from tests.perception.onnx_builders import channel_model, onehot_logits_model, write_card

INTR = Intrinsics(50.0, 50.0, 20.0, 15.0, 40, 30)


def make_frame(depth: bool = True, labels: bool = True, red: int = 7) -> Frame:
    img = np.zeros((30, 40, 3), dtype=np.uint8)
    img[:, :, 0] = red
    return Frame(
        index=3,
        timestamp_s=0.3,
        intrinsics=INTR,
        image_rgb=img,
        depth_m=np.full((30, 40), 12.5, dtype=np.float32) if depth else None,
        label_ids=np.full((30, 40), 2, dtype=np.uint8) if labels else None,
    )


def write_models(tmp_path: Path) -> tuple[Path, Path]:
    """A depth model (depth = red value) and a segmentation model (train id = red value), cards beside."""
    depth = channel_model(tmp_path / "depth.onnx")
    write_card(tmp_path / "depth.yaml", {"task": "depth", "input": {"size": [20, 15], "scale": 1}})
    seg = onehot_logits_model(tmp_path / "seg.onnx", 19)
    write_card(tmp_path / "seg.yaml", {"task": "segmentation", "input": {"size": [20, 15], "scale": 1}})
    return depth, seg


class TinySequence:
    """A Sequence with declared depth/label availability and no frames (all make_perception reads)."""

    name = "tiny"
    intrinsics = INTR

    def __init__(self, has_depth: bool, has_labels: bool) -> None:
        self._depth, self._labels = has_depth, has_labels

    def __len__(self) -> int:
        return 0

    def __getitem__(self, index: int) -> Frame:
        raise IndexError(index)

    @property
    def timestamps_s(self) -> np.ndarray:
        return np.zeros(0)

    @property
    def gt_poses(self) -> np.ndarray | None:
        return None

    @property
    def has_depth(self) -> bool:
        return self._depth

    @property
    def has_labels(self) -> bool:
        return self._labels


def test_files_source_passes_the_frame_through() -> None:
    source = SequenceFilesSource()
    assert isinstance(source, PerceptionSource)
    out = source.process(make_frame())
    assert isinstance(out, PerceptionOutput) and out.timings_ms == {}
    assert float(out.depth_m.mean()) == 12.5 and int(out.label_ids.max()) == 2
    with pytest.raises(DataError, match=r"no depth.*perception\.depth_model"):
        source.process(make_frame(depth=False))
    with pytest.raises(DataError, match=r"no labels.*perception\.seg_model"):
        source.process(make_frame(labels=False))


def test_onnx_perception_falls_back_per_modality(tmp_path: Path) -> None:
    depth_path, _ = write_models(tmp_path)
    source = OnnxPerception(depth_model=DepthModel(depth_path, threads=1))
    out = source.process(make_frame(depth=False, red=9))
    np.testing.assert_allclose(out.depth_m, 9.0)  # from the model
    assert int(out.label_ids.max()) == 2  # from the files
    assert set(out.timings_ms) == {"depth_preprocess", "depth_inference", "depth_postprocess"}
    with pytest.raises(DataError, match="no labels"):
        source.process(make_frame(depth=False, labels=False))


def test_make_perception_from_config(tmp_path: Path) -> None:
    assert isinstance(make_perception(PerceptionConfig(), True, True), SequenceFilesSource)
    with pytest.raises(DataError, match=r"no depth \(no depth/ folder.*perception\.depth_model"):
        make_perception(PerceptionConfig(), False, True)
    with pytest.raises(DataError, match=r"no labels \(no semantic/ folder.*perception\.seg_model"):
        make_perception(PerceptionConfig(), TinySequence(True, False))
    depth_path, seg_path = write_models(tmp_path)
    cfg = PerceptionConfig(depth_model=depth_path, seg_model=seg_path, threads=1)
    source = make_perception(cfg, TinySequence(False, False))
    assert isinstance(TinySequence(False, False), Sequence)
    assert isinstance(source, OnnxPerception)
    out = source.process(make_frame(depth=False, labels=False, red=13))
    np.testing.assert_allclose(out.depth_m, 13.0)
    assert (out.label_ids == 13).all()
    assert {"depth_inference", "seg_inference"} <= set(out.timings_ms)


def test_make_perception_reports_a_missing_card(tmp_path: Path) -> None:
    model = channel_model(tmp_path / "orphan.onnx")
    with pytest.raises(ModelError, match=r"orphan\.yaml not found"):
        make_perception(PerceptionConfig(depth_model=model), False, True)


def test_frame_without_image_is_a_data_error(tmp_path: Path) -> None:
    depth_path, _ = write_models(tmp_path)
    model = DepthModel(depth_path, parse_card({"task": "depth", "input": {"size": [20, 15]}}), threads=1)
    frame = make_frame()
    frame.image_rgb = None
    with pytest.raises(DataError, match="no image"):
        OnnxPerception(model).process(frame)
