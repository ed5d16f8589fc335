"""Tiny ONNX graphs for the perception tests, built with onnx.helper (pinned IR 10 / opset 17).

Each builder writes a model whose output is a known function of its input, so the adapters'
preprocessing (layout, colour order, normalization, resize/pad/crop) and postprocessing can be
checked against numpy ground truth. Dims given as strings are symbolic (dynamic) axes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
import yaml
from onnx import TensorProto, helper, numpy_helper

Dim = int | str
NCHW_ANY: tuple[Dim, ...] = ("N", 3, "H", "W")
NHWC_ANY: tuple[Dim, ...] = ("N", "H", "W", 3)


def save_model(
    path: Path,
    nodes: Sequence[onnx.NodeProto],
    inputs: Sequence[onnx.ValueInfoProto],
    outputs: Sequence[onnx.ValueInfoProto],
    initializers: Sequence[onnx.TensorProto] = (),
    *,
    ir_version: int = 10,
    opset: int = 17,
) -> Path:
    graph = helper.make_graph(list(nodes), "test", list(inputs), list(outputs), list(initializers))
    model = helper.make_model(graph, ir_version=ir_version, opset_imports=[helper.make_opsetid("", opset)])
    path.write_bytes(model.SerializeToString())
    return path


def write_card(path: Path, card: dict) -> Path:
    path.write_text(yaml.safe_dump(card, sort_keys=False))
    return path


def _const(name: str, values: Sequence[int]) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(values, dtype=np.int64), name)


def _out_shape(in_shape: Sequence[Dim], c_axis: int, channels: Dim) -> list[Dim]:
    shape = list(in_shape)
    shape[c_axis] = channels
    return shape


def channel_model(
    path: Path,
    *,
    channel: int = 0,
    nhwc: bool = False,
    shape: Sequence[Dim] | None = None,
    in_type: int = TensorProto.FLOAT,
    out_name: str = "out",
    squeeze: bool = False,
    ir_version: int = 10,
    opset: int = 17,
) -> Path:
    """Output = input channel ``channel`` as float: (N, 1, H, W) / (N, H, W, 1), (N, H, W) if ``squeeze``."""
    shape = tuple(shape or (NHWC_ANY if nhwc else NCHW_ANY))
    c_axis = 3 if nhwc else 1
    nodes = [helper.make_node("Slice", ["x", "starts", "ends", "axes"], ["sl"])]
    last = "sl"
    if in_type != TensorProto.FLOAT:
        nodes.append(helper.make_node("Cast", [last], ["cast"], to=TensorProto.FLOAT))
        last = "cast"
    out_shape = _out_shape(shape, c_axis, 1)
    if squeeze:
        nodes.append(helper.make_node("Squeeze", [last, "axes"], [out_name]))
        out_shape.pop(c_axis)
    else:
        nodes.append(helper.make_node("Identity", [last], [out_name]))
    inits = [_const("starts", [channel]), _const("ends", [channel + 1]), _const("axes", [c_axis])]
    return save_model(
        path,
        nodes,
        [helper.make_tensor_value_info("x", in_type, list(shape))],
        [helper.make_tensor_value_info(out_name, TensorProto.FLOAT, out_shape)],
        inits,
        ir_version=ir_version,
        opset=opset,
    )


def onehot_logits_model(
    path: Path, num_classes: int, *, nhwc: bool = False, shape: Sequence[Dim] | None = None
) -> Path:
    """Logits = one-hot of input channel 0 (read as a class index): argmax gives channel 0 back."""
    shape = tuple(shape or (NHWC_ANY if nhwc else NCHW_ANY))
    c_axis = 3 if nhwc else 1
    nodes = [
        helper.make_node("Slice", ["x", "starts", "ends", "axes"], ["sl"]),
        helper.make_node("Squeeze", ["sl", "axes"], ["sq"]),
        helper.make_node("Cast", ["sq"], ["idx"], to=TensorProto.INT64),
        helper.make_node("OneHot", ["idx", "depth", "values"], ["logits"], axis=-1 if nhwc else 1),
    ]
    inits = [
        _const("starts", [0]), _const("ends", [1]), _const("axes", [c_axis]), _const("depth", [num_classes]),
        numpy_helper.from_array(np.array([0.0, 1.0], dtype=np.float32), "values"),
    ]  # fmt: skip
    return save_model(
        path,
        nodes,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
        [helper.make_tensor_value_info("logits", TensorProto.FLOAT, _out_shape(shape, c_axis, num_classes))],
        inits,
    )


def label_map_model(path: Path, *, shape: Sequence[Dim] = NCHW_ANY, as_float: bool = False) -> Path:
    """Label map (N, H, W) int64 (``as_float``: float32, the value unrounded) = input channel 0 (read as a
    class index)."""
    nodes = [
        helper.make_node("Slice", ["x", "starts", "ends", "axes"], ["sl"]),
        helper.make_node("Squeeze", ["sl", "axes"], ["sq"]),
        helper.make_node("Cast", ["sq"], ["labels"], to=TensorProto.FLOAT if as_float else TensorProto.INT64),
    ]
    inits = [_const("starts", [0]), _const("ends", [1]), _const("axes", [1])]
    out_shape = [shape[0], shape[2], shape[3]]
    out_type = TensorProto.FLOAT if as_float else TensorProto.INT64
    return save_model(
        path,
        nodes,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
        [helper.make_tensor_value_info("labels", out_type, out_shape)],
        inits,
    )


def conv_model(path: Path, *, out_channels: int, shape: Sequence[Dim] = NCHW_ANY, hidden: int = 8) -> Path:
    """A small 3x3 conv net (3 -> hidden -> out_channels, ReLU, seeded weights): a realistic-shaped
    output for timing and smoke tests (positive values through a final Softplus)."""
    rng = np.random.default_rng(0)
    w1 = (rng.standard_normal((hidden, 3, 3, 3)) * 0.3).astype(np.float32)
    w2 = (rng.standard_normal((out_channels, hidden, 3, 3)) * 0.3).astype(np.float32)
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("Conv", ["r1", "w2"], ["c2"], pads=[1, 1, 1, 1]),
        helper.make_node("Softplus", ["c2"], ["out"]),
    ]
    return save_model(
        path,
        nodes,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, _out_shape(shape, 1, out_channels))],
        [numpy_helper.from_array(w1, "w1"), numpy_helper.from_array(w2, "w2")],
    )


def rank3_model(path: Path) -> Path:
    """Input of rank 3 (C, H, W): the adapter must refuse it."""
    return save_model(
        path,
        [helper.make_node("Identity", ["x"], ["out"])],
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [3, "H", "W"])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [3, "H", "W"])],
    )


def coordinate_image(width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 image whose R encodes x and G encodes y, both as round(255 * t), t in [0, 1]."""
    x = np.round(255.0 * np.arange(width) / (width - 1))
    y = np.round(255.0 * np.arange(height) / (height - 1))
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[:, :, 0] = x[None, :]
    img[:, :, 1] = y[:, None]
    img[:, :, 2] = 17
    return img
