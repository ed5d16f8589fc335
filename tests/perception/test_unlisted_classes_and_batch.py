"""What the networks did, said where a user looks: label-map classes beyond the card (a warning once per model; a
ModelError when most pixels have one), and ``perceive``'s batch when a model refused a batch (perceive.json and the
summary line)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.errors import ModelError
from shgm_slam.labels import IGNORE_ID
from shgm_slam.perception.card import parse_card
from shgm_slam.perception.perceive import MANIFEST
from shgm_slam.perception.segmentation import SegmentationModel
from tests.perception.onnx_builders import conv_model, label_map_model, write_card

LABEL_MAP_CARD = {"task": "segmentation", "input": {"size": [40, 20], "scale": 1}, "output": {"kind": "label_map"}}


def class_image(red: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 image whose red channel is the class index ``label_map_model`` reads back."""
    img = np.zeros((*red.shape, 3), dtype=np.uint8)
    img[..., 0] = red
    return img


def test_label_map_classes_beyond_the_card_are_said_once_and_refused_when_most(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Class indices past the card's 19 read as ignore in ``run`` with no word (only ``check-model`` noted them);
    a model of another label space under the default card made labels that were mostly ignore, silently."""
    model = SegmentationModel(label_map_model(tmp_path / "m.onnx"), parse_card(LABEL_MAP_CARD), threads=1)
    classes = np.broadcast_to(np.arange(40) % 19, (20, 40)).astype(np.uint8)
    few = classes.copy()
    few[:2] = 22  # 10 % of the pixels
    few[2, :4] = 30
    with caplog.at_level("WARNING"):
        labels = model.predict(class_image(few))
        assert (labels[:2] == IGNORE_ID).all() and (labels[3:] == classes[3:]).all()  # still read as ignore
        model.predict(class_image(few))
    said = [r.getMessage() for r in caplog.records if "beyond the 19 classes" in r.getMessage()]
    assert len(said) == 1, said  # once for this model
    assert "model m.onnx: 10.5 % of an image's pixels have class indices (22, 30)" in said[0]
    assert "output.classes" in said[0] and "output.mapping" in said[0]
    caplog.clear()
    other = SegmentationModel(label_map_model(tmp_path / "m.onnx"), parse_card(LABEL_MAP_CARD), threads=1)
    with caplog.at_level("WARNING"):
        other.predict(class_image(few))  # another robot's model: said for it too
    assert "beyond the 19 classes" in caplog.text
    most = classes.copy()
    most[:15] = 150  # 75 %: the card does not describe this model
    fresh = SegmentationModel(label_map_model(tmp_path / "m.onnx"), parse_card(LABEL_MAP_CARD), threads=1)
    with pytest.raises(ModelError, match=r"model m\.onnx: 75\.0 % .*\(150\) beyond the 19 classes.*output\.classes"):
        fresh.predict(class_image(most))  # on its first image: before a run or perceive does any work
    # after a first image that fits, one frame mostly of an unlisted class reads as ignore and the run goes on (a
    # ModelError there ended a run at that frame, maybe hours in: ``run`` catches only data errors per frame)
    assert (model.predict(class_image(most))[:15] == IGNORE_ID).all()


def single_image_seg_model(path: Path, hw: tuple[int, int]) -> Path:
    """``conv_model``'s 19-class logits reshaped to a fixed (1, 19, H, W): runs one image, though its batch axis is
    declared dynamic (an export with a hard-coded batch of 1)."""
    conv_model(path, out_channels=19)
    model = onnx.load(path)
    graph = model.graph
    graph.initializer.append(numpy_helper.from_array(np.asarray([1, 19, *hw], dtype=np.int64), "one_image"))
    graph.node.append(helper.make_node("Reshape", ["out", "one_image"], ["logits"]))
    del graph.output[:]
    graph.output.append(helper.make_tensor_value_info("logits", TensorProto.FLOAT, ["N", 19, "H", "W"]))
    onnx.save(model, path)
    return path


def test_perceive_says_the_batch_a_model_was_fed_and_why(tmp_path: Path) -> None:
    """A model that failed on a batch was fed one image per call with a log warning only: ``perceive.json`` and the
    summary line said the batch asked for (8)."""
    from shgm_slam.sim.simulate import simulate

    simulate("airsim-like", tmp_path / "sim", resolution=(160, 48), fps=4.0, compact=True, max_frames=3)
    seg = single_image_seg_model(tmp_path / "seg.onnx", (16, 32))
    write_card(tmp_path / "seg.yaml", {"task": "segmentation", "input": {"size": [32, 16]}})
    runner = CliRunner()
    result = runner.invoke(app, ["perceive", str(tmp_path / "sim" / "car1"), "--out", str(tmp_path / "out"),
                                 "--seg-model", str(seg), "--threads", "1"])  # fmt: skip
    assert result.exit_code == 0, result.output
    line = " ".join(result.output.split())
    assert ("batch segmentation 1 (asked 8; segmentation: it failed on a batch of 3 images (a batch axis dynamic in "
            "name only) but runs one image)") in line  # fmt: skip
    last_run = json.loads((tmp_path / "out" / MANIFEST).read_text())["last_run"]
    assert last_run["batch_size"] == 8
    assert last_run["batch_used"] == {"segmentation": {"size": 1, "why": "it failed on a batch of 3 images (a batch "
                                                       "axis dynamic in name only) but runs one image"}}  # fmt: skip

    fine = conv_model(tmp_path / "fine.onnx", out_channels=19)
    write_card(tmp_path / "fine.yaml", {"task": "segmentation", "input": {"size": [32, 16]}})
    result = runner.invoke(app, ["perceive", str(tmp_path / "sim" / "car1"), "--out", str(tmp_path / "fine_out"),
                                 "--seg-model", str(fine), "--threads", "1", "--batch-size", "2"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "; batch 2)" in " ".join(result.output.split())
    last_run = json.loads((tmp_path / "fine_out" / MANIFEST).read_text())["last_run"]
    assert last_run["batch_used"] == {"segmentation": {"size": 2, "why": None}}
