"""ONNX models with wrong inputs and outputs (rank, type, channels, names, count, NaN or constant values,
IR/opset) and random cards: opening and running them gives depth/labels on the image grid or a
``ShgmError`` (mostly ModelError naming the model), never another exception."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import onnx
from hypothesis import event, given
from hypothesis import strategies as st
from onnx import TensorProto, helper, numpy_helper
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.data.validate import check_sequence_start
from shgm_slam.errors import ShgmError
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.segmentation import SegmentationModel
from shgm_slam.types import Frame, Intrinsics
from tests.fuzz.conftest import fuzz_settings, scratch
from tests.perception.onnx_builders import channel_model, save_model, write_card

ELEM = {
    "float": (TensorProto.FLOAT, np.float32),
    "double": (TensorProto.DOUBLE, np.float64),
    "uint8": (TensorProto.UINT8, np.uint8),
    "int64": (TensorProto.INT64, np.int64),
    "float16": (TensorProto.FLOAT16, np.float16),
}
FILLS = [np.nan, np.inf, -np.inf, 0.0, 1.0, -5.0, 3.0, 1e9, 255.0]
INTRINSICS = Intrinsics(fx=30.0, fy=30.0, cx=15.5, cy=11.5, width=32, height=24)
IMAGE = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)

dims = st.one_of(st.sampled_from([1, 3, 4, 8, 16, 24, 32]), st.sampled_from(["N", "H", "W", "C"]))
shapes = st.lists(dims, min_size=1, max_size=5)


def _const_model(path: Path, in_elem: str, in_shape: list, out_elem: str, out_shape: list[int], fill: float,
                 extra_output: bool, ir_version: int, opset: int) -> None:
    """Output = a constant tensor of ``out_shape`` filled with ``fill``, whatever the input."""
    onnx_type, np_type = ELEM[out_elem]
    with np.errstate(invalid="ignore", over="ignore"):
        value = np.full(out_shape, fill).astype(np_type)
    nodes = [helper.make_node("Constant", [], ["out"], value=numpy_helper.from_array(value, "v"))]
    outputs = [helper.make_tensor_value_info("out", onnx_type, out_shape)]
    if extra_output:
        nodes.append(helper.make_node("Identity", ["out"], ["out2"]))
        outputs.append(helper.make_tensor_value_info("out2", onnx_type, out_shape))
    inputs = [helper.make_tensor_value_info("x", ELEM[in_elem][0], in_shape)]
    save_model(path, nodes, inputs, outputs, ir_version=ir_version, opset=opset)


def _identity_model(path: Path, elem: str, shape: list, ir_version: int, opset: int) -> None:
    """Output = input (wrong channel counts and ranks pass straight through)."""
    t = ELEM[elem][0]
    save_model(path, [helper.make_node("Identity", ["x"], ["out"])], [helper.make_tensor_value_info("x", t, shape)],
               [helper.make_tensor_value_info("out", t, shape)], ir_version=ir_version, opset=opset)  # fmt: skip


_input_mutations = st.fixed_dictionaries(
    {},
    optional={
        "layout": st.sampled_from(["NCHW", "NHWC", "nchw", "HWC"]),
        "size": st.one_of(st.tuples(st.integers(-2, 64), st.integers(-2, 64)), st.just([8])),
        "dtype": st.sampled_from(["float32", "uint8", "int64"]),
        "multiple_of": st.integers(0, 32),
        "resize": st.sampled_from(["stretch", "keep_aspect_pad", "crop"]),
        "scale": st.sampled_from([0.0, 1.0, 1 / 255, -1.0]),
        "std": st.sampled_from([[1, 1, 1], [0, 0, 0], [1, 1]]),
    },
)
_output_mutations = st.fixed_dictionaries(
    {},
    optional={
        "kind": st.sampled_from(["metric", "relative", "disparity", "inverse", "logits", "label_map", "x"]),
        "name": st.sampled_from(["out", "out2", "missing"]),
        "scale": st.floats(allow_nan=True, allow_infinity=True, width=32),
        "shift": st.floats(-10, 10),
        "focal_x_baseline": st.sampled_from([1.0, 0.0, 100.0]),
        "min_depth_m": st.sampled_from([0.0, 0.5, 100.0]),
        "max_depth_m": st.sampled_from([0.1, 80.0, 1e9]),
        "classes": st.sampled_from(["cityscapes", "ade20k", "nope", ["road", "car"], []]),
    },
)


@st.composite
def cards(draw: st.DrawFn) -> dict:
    """A valid card for a 32x24 NCHW model, usually with one or two fields changed."""
    task = draw(st.sampled_from(["depth", "segmentation"]))
    card = {"task": task, "input": {"size": [32, 24]}, "output": {"kind": "metric" if task == "depth" else "logits"}}
    if draw(st.integers(0, 3)) == 0:
        card["input"].update(draw(_input_mutations))
    if draw(st.integers(0, 3)) == 0:
        card["output"].update(draw(_output_mutations))
    return card


_plausible = st.sampled_from([["N", 3, "H", "W"], [1, 3, 24, 32], ["N", 3, 24, 32], ["N", "H", "W", 3]])
in_shapes = st.one_of(_plausible, _plausible, _plausible, shapes)
out_shapes = st.one_of(
    st.sampled_from([[1, 1, 24, 32], [1, 24, 32], [1, 19, 24, 32], [1, 3, 24, 32], [1, 24, 32, 1], [1, 2, 12, 16]]),
    st.lists(st.sampled_from([1, 2, 3, 8, 19, 24, 32]), min_size=0, max_size=5),
)


def _exercise(model_path: Path, card: dict) -> None:
    """Open the model with its card, predict, probe like ``run``: only ShgmErrors may come out."""
    write_card(model_path.with_suffix(".yaml"), card)
    try:
        model = (DepthModel if card["task"] == "depth" else SegmentationModel)(model_path, threads=1)
        if isinstance(model, DepthModel):
            out = model.predict(IMAGE, INTRINSICS)
            assert out.shape == (24, 32) and out.dtype == np.float32
            assert np.isfinite(out).all() and (out >= 0).all()
        else:
            out = model.predict(IMAGE)
            assert out.shape == (24, 32) and out.dtype == np.uint8

        depth, labels = np.full((24, 32), 5.0, np.float32), np.full((24, 32), 13, np.uint8)
        frame = Frame(index=0, timestamp_s=0.0, intrinsics=INTRINSICS, image_rgb=IMAGE, depth_m=depth, label_ids=labels)

        def perceive(f):
            if isinstance(model, DepthModel):
                return model.predict(f.image_rgb, INTRINSICS), f.label_ids
            return f.depth_m, model.predict(f.image_rgb)

        event("predicted")
        check_sequence_start("fuzz", _OneFrame([frame]), perceive,  # type: ignore[arg-type]
                             **{"depth_model" if isinstance(model, DepthModel) else "seg_model": model_path})
        event("accepted")
    except ShgmError as exc:
        event(f"{type(exc).__name__}: {re.sub(r'/tmp/[^ ]*', '', str(exc))[:40]}")


class _OneFrame(list):
    name = "fuzz"


@fuzz_settings(150)
@given(
    in_elem=st.sampled_from(["float"] * 6 + list(ELEM)),
    in_shape=_plausible,
    out_elem=st.sampled_from(["float", "float", *ELEM]),
    out_shape=out_shapes,
    fill=st.sampled_from(FILLS),
    extra_output=st.booleans(),
    version=st.sampled_from([(10, 17), (10, 17), (10, 17), (8, 13), (7, 12), (3, 7), (10, 21), (13, 25), (10, 99)]),
    card=cards(),
)
def test_constant_output_models_fail_cleanly(in_elem, in_shape, out_elem, out_shape, fill, extra_output, version,
                                             card):  # fmt: skip
    with scratch() as d:
        path = d / "m.onnx"
        _const_model(path, in_elem, in_shape, out_elem, out_shape, fill, extra_output, *version)
        _exercise(path, card)


@fuzz_settings(80)
@given(elem=st.sampled_from(list(ELEM)), shape=in_shapes, card=cards())
def test_identity_models_with_wrong_shapes_fail_cleanly(elem, shape, card):
    with scratch() as d:
        path = d / "m.onnx"
        _identity_model(path, elem, shape, 10, 17)
        _exercise(path, card)


@fuzz_settings(20)
@given(data=st.binary(max_size=300), card=cards())
def test_garbage_model_files_are_model_errors(data, card):
    with scratch() as d:
        path = d / "m.onnx"
        path.write_bytes(data)
        _exercise(path, card)


def test_check_model_exits_2_when_no_output_is_valid(tmp_path):
    """A depth model whose every value is NaN: the report is printed, then exit 2 (not 'valid 0.0 %', exit 0)."""
    path = tmp_path / "nan.onnx"
    nodes = [helper.make_node("Slice", ["x", "s", "e", "a"], ["sl"]), helper.make_node("Mul", ["sl", "k"], ["out"])]
    inits = [numpy_helper.from_array(np.asarray(v, np.int64), n) for n, v in (("s", [0]), ("e", [1]), ("a", [1]))]
    inits.append(numpy_helper.from_array(np.asarray([np.nan], np.float32), "k"))
    save_model(path, nodes, [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
               [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", 1, "H", "W"])], inits)  # fmt: skip
    write_card(tmp_path / "nan.yaml", {"task": "depth", "input": {"size": [32, 24]}})
    res = CliRunner().invoke(app, ["check-model", str(path), "--runs", "1", "--threads", "1"])
    assert res.exit_code == 2, res.output
    assert "valid output 0 %" in " ".join(res.output.split())
    ok = channel_model(tmp_path / "ok.onnx")  # channel 0 of the image as metric depth: valid
    write_card(tmp_path / "ok.yaml", {"task": "depth", "input": {"size": [32, 24], "scale": 1.0}})
    assert CliRunner().invoke(app, ["check-model", str(ok), "--runs", "1", "--threads", "1"]).exit_code == 0
    assert onnx.load(str(path)).ir_version == 10


def _affine_of_channel_0(path: Path, k: float, c: float) -> Path:
    """A depth model whose output is ``k * (channel 0 of the input) + c`` (k = 0: the constant c)."""
    nodes = [helper.make_node("Slice", ["x", "s", "e", "a"], ["sl"]), helper.make_node("Mul", ["sl", "k"], ["m"]),
             helper.make_node("Add", ["m", "c"], ["out"])]  # fmt: skip
    inits = [numpy_helper.from_array(np.asarray(v, np.int64), n) for n, v in (("s", [0]), ("e", [1]), ("a", [1]))]
    inits += [numpy_helper.from_array(np.asarray([v], np.float32), n) for n, v in (("k", k), ("c", c))]
    save_model(path, nodes, [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
               [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["N", 1, "H", "W"])], inits)  # fmt: skip
    write_card(path.with_suffix(".yaml"), {"task": "depth", "input": {"size": [32, 24]}})
    return path


def test_check_model_exits_2_on_a_constant_output(tmp_path):
    """5 m everywhere: `run` refuses such a model, so check-model does too (it printed the report, exit 0)."""
    path = _affine_of_channel_0(tmp_path / "const.onnx", 0.0, 5.0)
    res = CliRunner().invoke(app, ["check-model", str(path), "--runs", "1", "--threads", "1"])
    assert res.exit_code == 2, res.output
    assert "constant output" in " ".join(res.output.split())


def test_perceive_refuses_a_useless_model_before_writing(tmp_path):
    """A depth model with no valid output or a constant one: perceive exits 2 and writes nothing (it wrote a
    whole sequence of empty depth, exit 0, that `run` then refused)."""
    from tests.data.conftest import make_frames, write_frames

    seq = write_frames(tmp_path / "seq", make_frames(4))
    for name, k, c in (("zero", 0.0, 0.0), ("const", 0.0, 5.0)):
        model = _affine_of_channel_0(tmp_path / f"{name}.onnx", k, c)
        out = tmp_path / f"out_{name}"
        res = CliRunner().invoke(app, ["perceive", str(seq), "--out", str(out), "--depth-model", str(model),
                                       "--threads", "1"])  # fmt: skip
        assert res.exit_code == 2 and "error:" in res.output, res.output
        assert not out.exists()
