"""Models as real exports differ from the demo models: float16/double tensors, outputs without a batch axis, extra
inputs, batch axes dynamic in name only, runtime failures, dynamic class axes, label maps with more classes than the
card lists, misspelt cards, missing weights files, a segmentation model alone in ``perceive``. Each either works
(with the values it should give) or is one ModelError naming the model, the field or tensor, and the fix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.errors import ModelError
from shgm_slam.perception.card import parse_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.onnx_model import open_session
from shgm_slam.perception.preview import check_model, write_png
from shgm_slam.perception.segmentation import SegmentationModel
from tests.perception.onnx_builders import (
    NCHW_ANY,
    channel_model,
    conv_model,
    label_map_model,
    save_model,
    write_card,
)

F32, F16, F64, I64 = TensorProto.FLOAT, TensorProto.FLOAT16, TensorProto.DOUBLE, TensorProto.INT64
DEPTH_CARD = {"task": "depth", "input": {"size": [20, 15], "scale": 1}, "output": {"kind": "metric"}}


def _i64(name: str, values: list[int]) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(values, dtype=np.int64), name)


def red_model(
    path: Path,
    *,
    in_type: int = F32,
    out_type: int = F32,
    in_shape: tuple = NCHW_ANY,
    squeeze: list[int] | None = None,
    extra_input: str | None = None,
    extra_default: bool = False,
) -> Path:
    """Output = input channel 0 (red, in the model's input units) as ``out_type``: (N, 1, H, W), or with the axes
    ``squeeze`` removed ((H, W) for [0, 1]). ``extra_input``: a second (1,) float input added to it times 0 (a
    default value as an initializer with ``extra_default``)."""
    nodes = [helper.make_node("Slice", ["x", "s0", "s1", "ax"], ["r"]),
             helper.make_node("Cast", ["r"], ["rf"], to=F32)]  # fmt: skip
    inits = [_i64("s0", [0]), _i64("s1", [1]), _i64("ax", [1])]
    last, out_shape = "rf", [in_shape[0], 1, in_shape[2], in_shape[3]]
    inputs = [helper.make_tensor_value_info("x", in_type, list(in_shape))]
    if extra_input:
        nodes += [helper.make_node("Mul", [extra_input, "zero"], ["ez"]), helper.make_node("Add", [last, "ez"], ["e"])]
        inits.append(numpy_helper.from_array(np.zeros(1, np.float32), "zero"))
        inputs.append(helper.make_tensor_value_info(extra_input, F32, [1]))
        if extra_default:
            inits.append(numpy_helper.from_array(np.ones(1, np.float32), extra_input))
        last = "e"
    if squeeze:
        nodes.append(helper.make_node("Squeeze", [last, "sq"], ["q"]))
        inits.append(_i64("sq", squeeze))
        out_shape = [d for i, d in enumerate(out_shape) if i not in squeeze]
        last = "q"
    nodes.append(helper.make_node("Cast", [last], ["out"], to=out_type))
    return save_model(path, nodes, inputs, [helper.make_tensor_value_info("out", out_type, out_shape)], inits)


def fixed_reshape_model(path: Path, hw: tuple[int, int]) -> Path:
    """Output = red channel reshaped to a fixed (1, 1, H, W): runs only on one image of ``hw`` (H, W), though its
    batch axis is declared dynamic (as exports with a hard-coded batch of 1 in a Reshape)."""
    nodes = [helper.make_node("Slice", ["x", "s0", "s1", "ax"], ["r"]),
             helper.make_node("Reshape", ["r", "shape"], ["out"])]  # fmt: skip
    inits = [_i64("s0", [0]), _i64("s1", [1]), _i64("ax", [1]), _i64("shape", [1, 1, *hw])]
    return save_model(path, nodes, [helper.make_tensor_value_info("x", F32, list(NCHW_ANY))],
                      [helper.make_tensor_value_info("out", F32, ["N", 1, "h", "w"])], inits)  # fmt: skip


def image(red: int = 40, width: int = 40, height: int = 30) -> np.ndarray:
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = red, 7, 9
    return img


# --- float16 / double tensors ----------------------------------------------------------------------------
@pytest.mark.parametrize(("in_type", "out_type"), [(F16, F16), (F16, F32), (F64, F32), (F32, F16)])
def test_float16_and_double_models_are_fed_their_own_type(tmp_path: Path, in_type: int, out_type: int) -> None:
    """A float16 (or double) input was refused with "fix input.dtype in the card (float32 or uint8)", a fix the
    card cannot give; the normalized image is now cast to the model's float type."""
    path = red_model(tmp_path / "m.onnx", in_type=in_type, out_type=out_type)
    model = DepthModel(path, parse_card(DEPTH_CARD), threads=1)
    depths = model.predict_batch([image(40), image(90)])
    assert [float(d.mean()) for d in depths] == pytest.approx([40.0, 80.0])  # 90 clamped to max_depth_m
    seg = SegmentationModel(conv_model(tmp_path / "s.onnx", out_channels=19), parse_card(
        {"task": "segmentation", "input": {"size": [20, 15]}}), threads=1)  # fmt: skip
    assert seg.predict(image()).shape == (30, 40)


def test_an_integer_input_names_what_the_adapter_feeds(tmp_path: Path) -> None:
    path = red_model(tmp_path / "m.onnx", in_type=I64)
    with pytest.raises(ModelError, match=r"tensor\(int64\).*the adapter feeds float or uint8 images"):
        DepthModel(path, parse_card(DEPTH_CARD), threads=1)


# --- outputs without a batch axis ------------------------------------------------------------------------
@pytest.mark.parametrize("in_shape", [(1, 3, 15, 20), NCHW_ANY])
def test_depth_and_label_maps_without_a_batch_axis_run_one_image_per_call(tmp_path: Path, in_shape: tuple) -> None:
    """An (H, W) output was refused ("rank 2 ... set output.name to the depth output", the model's only output)."""
    depth = DepthModel(red_model(tmp_path / "d.onnx", in_shape=in_shape, squeeze=[0, 1]), parse_card(DEPTH_CARD),
                       threads=1)  # fmt: skip
    depths = depth.predict_batch([image(10), image(20), image(30)])
    assert [float(d.mean()) for d in depths] == pytest.approx([10.0, 20.0, 30.0])
    assert depth.batch_size == 1 and depth.last_input_shape[0] == 1
    seg_card = {**DEPTH_CARD, "task": "segmentation", "output": {"kind": "label_map"}}
    seg = SegmentationModel(red_model(tmp_path / "s.onnx", in_shape=in_shape, squeeze=[0, 1], out_type=I64),
                            parse_card(seg_card), threads=1)  # fmt: skip
    labels = seg.predict_batch([image(13), image(0)])
    assert (labels[0] == 13).all() and (labels[1] == 0).all()


def test_an_output_without_a_batch_axis_on_a_fixed_batch_of_two_is_refused(tmp_path: Path) -> None:
    path = save_model(tmp_path / "m.onnx", [helper.make_node("ReduceMean", ["x"], ["out"], axes=[0, 1], keepdims=0)],
                      [helper.make_tensor_value_info("x", F32, [2, 3, "H", "W"])],
                      [helper.make_tensor_value_info("out", F32, ["H", "W"])])  # fmt: skip
    with pytest.raises(ModelError, match=r"no batch axis but input 'x' takes a batch of 2"):
        DepthModel(path, parse_card(DEPTH_CARD), threads=1)


# --- inputs ----------------------------------------------------------------------------------------------
def test_a_second_required_input_is_named_when_the_model_opens(tmp_path: Path) -> None:
    """With input.name set, a model needing a second input opened fine and every frame failed with "check input.size
    / input.multiple_of / input.layout"; without it the error said to set input.name, which does not help."""
    path = red_model(tmp_path / "m.onnx", extra_input="focal")
    for input_card in ({"name": "x"}, {}):
        card = parse_card({**DEPTH_CARD, "input": {**DEPTH_CARD["input"], **input_card}})
        with pytest.raises(ModelError, match=r"needs 2 inputs \(x, focal\).*image as its only input"):
            DepthModel(path, card, threads=1)


def test_a_second_input_with_a_default_value_is_fine(tmp_path: Path) -> None:
    path = red_model(tmp_path / "m.onnx", extra_input="focal", extra_default=True)
    assert float(DepthModel(path, parse_card(DEPTH_CARD), threads=1).predict(image(25)).mean()) == pytest.approx(25)


# --- failures at run time --------------------------------------------------------------------------------
def test_a_model_failing_at_run_time_is_one_clean_line(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    """onnxruntime logged its own error line to stderr before ours, and our message carried its C++ source path and
    signature (``/onnxruntime_src/...reshape_helper.h:91 onnxruntime::ReshapeHelper::ReshapeHelper(...)``)."""
    model = DepthModel(fixed_reshape_model(tmp_path / "m.onnx", (16, 20)), parse_card(DEPTH_CARD), threads=1)
    capfd.readouterr()
    with pytest.raises(ModelError) as info:
        model.predict(image())
    message = str(info.value)
    assert "failed on an input of shape [1, 3, 15, 20]" in message and "Reshape" in message
    assert "onnxruntime_src" not in message and "ONNXRuntimeError" not in message and "\n" not in message
    assert capfd.readouterr().err == ""


def test_a_dynamic_batch_axis_that_takes_one_image_falls_back_to_single_calls(tmp_path: Path) -> None:
    """``perceive`` (batches of 8) ended with "failed on an input of shape [8, ...]: check input.size" on a model
    that ``run`` and ``check-model`` (one image) ran fine."""
    model = DepthModel(fixed_reshape_model(tmp_path / "m.onnx", (15, 20)), parse_card(DEPTH_CARD), threads=1)
    depths = model.predict_batch([image(10), image(20), image(30)])
    assert [float(d.mean()) for d in depths] == pytest.approx([10.0, 20.0, 30.0])
    assert model.batch_size == 1
    broken = DepthModel(fixed_reshape_model(tmp_path / "b.onnx", (16, 20)), parse_card(DEPTH_CARD), threads=1)
    with pytest.raises(ModelError, match=r"input of shape \[1, 3, 15, 20\]"):  # one image fails too: that error
        broken.predict_batch([image(10), image(20)])


# --- segmentation outputs --------------------------------------------------------------------------------
def test_an_integer_label_map_under_kind_logits_suggests_label_map(tmp_path: Path) -> None:
    """An (N, 1, H, W) int64 label map under the default ``kind: logits`` was told "1 classes on axis 1 but the card
    lists 19 ...: list every model class", not that it is a label map."""
    path = red_model(tmp_path / "m.onnx", out_type=I64)
    card = parse_card({**DEPTH_CARD, "task": "segmentation", "output": {"kind": "logits"}})
    with pytest.raises(ModelError, match=r"logits are tensor\(int64\).*output\.kind: label_map"):
        SegmentationModel(path, card, threads=1)


def _dynamic_class_axis_model(path: Path, num_classes: int) -> Path:
    """Logits of ``num_classes`` (a seeded 1x1 conv) sliced to the first H channels: onnxruntime cannot tell their
    count before a run (output (N, C, H, W) with C symbolic)."""
    w = np.random.default_rng(0).standard_normal((num_classes, 3, 1, 1)).astype(np.float32)
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"]),
        helper.make_node("Shape", ["x"], ["shape"]),
        helper.make_node("Slice", ["shape", "two", "three"], ["h"]),
        helper.make_node("Slice", ["c", "zero", "h", "one"], ["logits"]),
    ]
    inits = [numpy_helper.from_array(w, "w"), _i64("zero", [0]), _i64("one", [1]), _i64("two", [2]),
             _i64("three", [3])]  # fmt: skip
    return save_model(path, nodes, [helper.make_tensor_value_info("x", F32, list(NCHW_ANY))],
                      [helper.make_tensor_value_info("logits", F32, ["N", "C", "H", "W"])], inits)  # fmt: skip


def test_logits_with_another_class_count_than_the_card_are_refused_at_run_time(tmp_path: Path) -> None:
    """A class axis onnxruntime cannot size before a run passed the card check; 25 classes against 19 listed made
    every pixel of classes 19-24 silently ignore (and an NHWC/NCHW mix-up an argmax over the wrong axis)."""
    card = parse_card({"task": "segmentation", "input": {"multiple_of": 8}, "output": {"kind": "logits"}})
    model = SegmentationModel(_dynamic_class_axis_model(tmp_path / "m.onnx", 25), card, threads=1)
    assert not isinstance(model.output_spec.shape[1], int)
    with pytest.raises(ModelError, match=r"has 25 classes on axis 1 but the card lists 19 in output\.classes"):
        model.predict(image(width=40, height=32))
    fits = SegmentationModel(_dynamic_class_axis_model(tmp_path / "ok.onnx", 19), card, threads=1)
    assert fits.predict(image(width=40, height=32)).max() < 19


def test_check_model_notes_label_map_classes_beyond_the_card(tmp_path: Path) -> None:
    """Class indices past the card's list read as ignore with no word in ``check-model`` (a 150-class model under a
    19-class card looks like a model that sees little)."""
    path = label_map_model(tmp_path / "m.onnx")
    card = write_card(tmp_path / "m.yaml", {"task": "segmentation", "input": {"size": [20, 15], "scale": 1},
                                            "output": {"kind": "label_map"}})  # fmt: skip
    img = image(5)
    img[:, 20:, 0] = 22
    write_png(tmp_path / "img.png", img)
    report = check_model(path, card, tmp_path / "img.png", runs=1, threads=1)
    assert any("50.0 % of the pixels have class indices up to 22, beyond the 19 classes" in n for n in report.notes)
    img[:, 20:, 0] = 255  # the usual ignore value: no note
    write_png(tmp_path / "img.png", img)
    assert check_model(path, card, tmp_path / "img.png", runs=1, threads=1).notes == []


# --- cards -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("card", "needle"),
    [
        ({"task": "depth", "input": {"colour_order": "BGR"}}, r"'input\.colour_order'.*did you mean color_order\?"),
        ({"task": "depth", "inputs": {}}, r"'inputs'.*did you mean input\?"),
        ({"task": "depth", "output": {"knd": "metric"}}, r"'output\.knd'.*did you mean kind\?"),
        ({"task": "depth", "output": {"classes": "ade20k"}}, r"'output\.classes'.*known here: name, kind, scale"),
        ({"task": "depth", "output": {"kind": "metirc"}}, r"got 'metirc'; did you mean 'metric'\?"),
        ({"task": "depth", "input": {"layout": "nhcw"}}, r"'input\.layout'.*got 'nhcw'; did you mean 'NHWC'\?"),
        ({"task": "segmentation", "output": {"classes": "ade"}},
         r"'output\.classes': Input should be a list of class names, or 'cityscapes' or 'ade20k', got 'ade'; did "
         r"you mean 'ade20k'\?"),
    ],
)
def test_misspelt_card_fields_and_choices_suggest_the_right_one(card: dict, needle: str) -> None:
    """Errors said "Extra inputs are not permitted" (or, for classes, "field 'output.classes.tuple[str, ...]': Input
    should be a valid tuple") without the field or value meant."""
    with pytest.raises(ModelError, match=needle):
        parse_card(card)


# --- files -----------------------------------------------------------------------------------------------
def test_an_opset_newer_than_onnxruntime_says_which_it_reads(tmp_path: Path) -> None:
    """The message quoted the last 90 characters of onnxruntime's, cut mid-word ("(ntee backward compatibility...")."""
    path = channel_model(tmp_path / "m.onnx", opset=99)
    with pytest.raises(ModelError, match=r"its opset 99 is newer than onnxruntime \S+ reads \(up to \d+\): re-export"):
        open_session(path)


def test_a_missing_external_weights_file_is_named(tmp_path: Path) -> None:
    """A model saved with external data, moved without its weights file, gave onnxruntime's validation text."""
    model = onnx.load(conv_model(tmp_path / "src.onnx", out_channels=2))
    onnx.save_model(model, tmp_path / "m.onnx", save_as_external_data=True, location="m.onnx.data",
                    size_threshold=0)  # fmt: skip
    open_session(tmp_path / "m.onnx")
    (tmp_path / "m.onnx.data").unlink()
    with pytest.raises(ModelError, match=r"keeps its weights in the file \S*m\.onnx\.data, which does not exist"):
        open_session(tmp_path / "m.onnx")


# --- perceive and the CLI --------------------------------------------------------------------------------
def test_perceive_with_a_segmentation_model_alone(tmp_path: Path) -> None:
    """``perceive --seg-model`` alone was refused on every sequence: its probe fed a depth of 1 m everywhere to the
    sequence check, which calls that a sensor's saturated depth files."""
    from shgm_slam.data import open_sequence
    from shgm_slam.perception.perceive import perceive
    from shgm_slam.sim.simulate import simulate

    simulate("airsim-like", tmp_path / "sim", resolution=(160, 48), fps=4.0, compact=True, max_frames=3)
    seg = conv_model(tmp_path / "seg.onnx", out_channels=19)
    write_card(tmp_path / "seg.yaml", {"task": "segmentation", "input": {"size": [32, 16]}})
    result = perceive(tmp_path / "sim" / "car1", tmp_path / "out", seg_model=seg, threads=1)
    seq = open_sequence(tmp_path / "out")
    assert result.complete and seq.has_labels and not seq.has_depth


def test_cli_check_model_float16_runs_and_a_failing_model_exits_2(tmp_path: Path) -> None:
    path = red_model(tmp_path / "half.onnx", in_type=F16, out_type=F16)
    write_card(tmp_path / "half.yaml", DEPTH_CARD)
    result = CliRunner().invoke(app, ["check-model", str(path), "--runs", "1", "--threads", "1"])
    assert result.exit_code == 0, result.output
    assert "tensor(float16)" in result.output
    path = fixed_reshape_model(tmp_path / "fails.onnx", (16, 20))
    write_card(tmp_path / "fails.yaml", DEPTH_CARD)
    result = CliRunner().invoke(app, ["check-model", str(path), "--runs", "1", "--threads", "1"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "fails.onnx failed on an input of shape [1, 3, 15, 20]" in " ".join(result.output.split())


def test_check_model_notes_depth_that_sits_at_the_card_s_clamp(tmp_path: Path) -> None:
    """A wrong output kind whose values all fall outside the card's range (inverse depth declared metric reads
    0.1-0.15 m) showed only as a narrow value range in ``check-model``; most valid pixels at a bound now get a note."""
    path = red_model(tmp_path / "m.onnx")
    write_card(path.with_suffix(".yaml"), DEPTH_CARD)
    bright = write_png(tmp_path / "bright.png", image(red=200))  # 200 "m" in the model's units: all at 80 m
    report = check_model(path, image_path=bright, runs=1, threads=1)
    assert any("sits at the card's max_depth_m (80 m)" in n for n in report.notes)
    fine = write_png(tmp_path / "fine.png", image(red=40))
    assert not any("sits at the card" in n for n in check_model(path, image_path=fine, runs=1, threads=1).notes)
