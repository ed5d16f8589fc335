"""The shared adapter: card validation against real models, preprocessing, resize geometry, batches."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from onnx import TensorProto, helper

from shgm_slam.errors import DataError, ModelError
from shgm_slam.perception.card import ResizeMode, parse_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.onnx_model import measure_overhead, open_session
from shgm_slam.perception.resize import any_size_target, plan_resize
from shgm_slam.perception.segmentation import SegmentationModel
from tests.perception.onnx_builders import channel_model, coordinate_image, rank3_model, save_model, write_card

_ids = itertools.count()


def make_depth(
    tmp_path: Path, input_card: dict, output_card: dict | None = None, **model_kwargs
) -> DepthModel:
    """A channel-passthrough model (output = one input channel) behind a depth card."""
    path = channel_model(tmp_path / f"m{next(_ids)}.onnx", **model_kwargs)
    card = {
        "task": "depth",
        "input": input_card,
        "output": output_card or {"kind": "metric", "min_depth_m": 0.001},
    }
    return DepthModel(path, parse_card(card), threads=1)


def constant_image(rgb: tuple[int, int, int], width: int = 40, height: int = 30) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, dtype=np.uint8), (height, width, 3)).copy()


# --- resize geometry ------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", list(ResizeMode))
def test_plan_resize_boxes_are_consistent(mode: ResizeMode) -> None:
    for image_wh, target_wh in [((1242, 375), (640, 192)), ((100, 300), (64, 64)), ((50, 30), (200, 90))]:
        plan = plan_resize(image_wh, target_wh, mode)
        sx0, sy0, sx1, sy1 = plan.src_box
        dx0, dy0, dx1, dy1 = plan.dst_box
        assert 0 <= sx0 < sx1 <= image_wh[0] and 0 <= sy0 < sy1 <= image_wh[1]
        assert 0 <= dx0 < dx1 <= target_wh[0] and 0 <= dy0 < dy1 <= target_wh[1]
        if mode is ResizeMode.STRETCH:
            assert plan.src_box == (0, 0, *image_wh) and plan.dst_box == (0, 0, *target_wh)
        else:  # aspect ratio kept to within a pixel
            src_aspect = (sx1 - sx0) / (sy1 - sy0)
            smallest = min(dy1 - dy0, dx1 - dx0, sy1 - sy0, sx1 - sx0)
            assert (dx1 - dx0) / (dy1 - dy0) == pytest.approx(src_aspect, rel=2.0 / smallest)
        if mode is ResizeMode.KEEP_ASPECT_PAD:
            assert plan.src_box == (0, 0, *image_wh)
        if mode is ResizeMode.KEEP_ASPECT_CROP:
            assert plan.dst_box == (0, 0, *target_wh)


def test_any_size_target_rounds_per_mode() -> None:
    assert any_size_target((1242, 375), 32, ResizeMode.KEEP_ASPECT_PAD) == (1248, 384)
    assert any_size_target((1242, 375), 32, ResizeMode.KEEP_ASPECT_CROP) == (1216, 352)
    assert any_size_target((1242, 375), 32, ResizeMode.STRETCH) == (1248, 384)
    assert any_size_target((10, 10), 32, ResizeMode.KEEP_ASPECT_CROP) == (32, 32)


# --- preprocessing: layout, colour order, normalization, dtype -------------------------------------------
@pytest.mark.parametrize("nhwc", [False, True])
@pytest.mark.parametrize("channel", [0, 1, 2])
def test_layout_selects_the_right_channel(tmp_path: Path, nhwc: bool, channel: int) -> None:
    model = make_depth(
        tmp_path,
        {"size": [20, 15], "layout": "NHWC" if nhwc else "NCHW", "scale": 1},
        channel=channel,
        nhwc=nhwc,
    )
    depth = model.predict(constant_image((10, 20, 30)))
    assert depth.shape == (30, 40) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, [10, 20, 30][channel], rtol=1e-6)


@pytest.mark.parametrize(("order", "expected"), [("RGB", 10.0), ("BGR", 30.0)])
def test_colour_order_is_visible(tmp_path: Path, order: str, expected: float) -> None:
    model = make_depth(tmp_path, {"size": [20, 15], "color_order": order, "scale": 1}, channel=0)
    np.testing.assert_allclose(model.predict(constant_image((10, 20, 30))), expected, rtol=1e-6)


@pytest.mark.parametrize("channel", [0, 1, 2])
def test_scale_mean_std_normalization(tmp_path: Path, channel: int) -> None:
    mean, std = (0.1, 0.2, 0.3), (0.5, 0.25, 0.125)
    model = make_depth(tmp_path, {"size": [20, 15], "mean": list(mean), "std": list(std)}, channel=channel)
    rgb = (100, 150, 200)
    expected = (rgb[channel] / 255.0 - mean[channel]) / std[channel]
    np.testing.assert_allclose(model.predict(constant_image(rgb)), expected, rtol=1e-5)


def test_bgr_mean_std_are_in_model_channel_order(tmp_path: Path) -> None:
    model = make_depth(
        tmp_path, {"size": [20, 15], "color_order": "BGR", "scale": 1, "mean": [5, 0, 0], "std": [2, 1, 1]}
    )
    # model channel 0 is blue (30): (30 - 5) / 2
    np.testing.assert_allclose(model.predict(constant_image((10, 20, 30))), 12.5, rtol=1e-6)


def test_uint8_input_gets_raw_pixels(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"size": [20, 15], "dtype": "uint8"}, channel=2, in_type=TensorProto.UINT8)
    np.testing.assert_allclose(model.predict(constant_image((10, 20, 30))), 30.0)


def test_grayscale_image_is_replicated(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"size": [20, 15], "scale": 1}, channel=1)
    np.testing.assert_allclose(model.predict(np.full((30, 40), 77, dtype=np.uint8)), 77.0)


# --- resize back: stretch / pad / crop undone (checked against the pixel's own coordinates) ---------------
def _coordinate_depth(
    tmp_path: Path, mode: str, axis: int, image_wh: tuple[int, int], size: list[int] | None, **input_extra
) -> tuple[np.ndarray, np.ndarray]:
    """Depth = 1 + 10 * (normalized x or y of the pixel the model saw); returns (depth, expected)."""
    W, H = image_wh
    model = make_depth(
        tmp_path,
        {"size": size, "resize": mode, "pad_value": 255, **input_extra},
        {"kind": "relative", "scale": 10, "shift": 1},
        channel=axis,
    )
    depth = model.predict(coordinate_image(W, H))
    t = np.arange(W) / (W - 1) if axis == 0 else np.arange(H) / (H - 1)
    expected = 1 + 10 * (t[None, :] if axis == 0 else t[:, None]) * np.ones((H, W))
    return depth, expected


@pytest.mark.parametrize("mode", ["stretch", "keep_aspect_pad", "keep_aspect_crop"])
@pytest.mark.parametrize("axis", [0, 1])
def test_fixed_size_resize_is_undone(tmp_path: Path, mode: str, axis: int) -> None:
    W, H, Wt, Ht = 120, 50, 32, 24
    depth, expected = _coordinate_depth(tmp_path, mode, axis, (W, H), [Wt, Ht])
    valid = depth > 0
    if mode == "keep_aspect_crop":  # s = max(32/120, 24/50) = 0.48: a centred 67 px wide band is seen
        cols = np.flatnonzero(valid.all(axis=0))
        assert valid.any(axis=0).sum() == cols.size == round(Wt / 0.48)
        assert abs(cols[0] - (W - cols.size) // 2) <= 1
        assert valid.all(axis=1).sum() == 0 and valid.any(axis=1).all()
    else:
        assert valid.all()
    # one model pixel spans (image px per model px) / (image extent) of the normalized coordinate
    extent = W if axis == 0 else H
    model_px = (W / Wt) if mode == "stretch" or axis == 0 else max(W / Wt, H / Ht)
    if mode == "keep_aspect_crop":
        model_px = 1 / 0.48
    err = np.abs(depth - expected)[valid]
    assert err.max() <= 10 * 1.5 * model_px / (extent - 1) + 0.05
    assert np.median(err) <= 10 * 0.5 * model_px / (extent - 1) + 0.05


@pytest.mark.parametrize("mode", ["stretch", "keep_aspect_pad", "keep_aspect_crop"])
def test_any_size_model_pads_or_crops_to_a_multiple(tmp_path: Path, mode: str) -> None:
    W, H = 50, 30
    depth, expected = _coordinate_depth(tmp_path, mode, 0, (W, H), None, multiple_of=16)
    valid = depth > 0
    if mode == "keep_aspect_pad":  # 64 x 32 input, no rescaling: exact
        np.testing.assert_allclose(depth, expected, atol=10 * 0.5 / 255 + 1e-5)
    elif mode == "keep_aspect_crop":  # 48 x 16 centre crop, no rescaling
        assert valid.sum() == 48 * 16
        np.testing.assert_allclose(depth[valid], expected[valid], atol=10 * 0.5 / 255 + 1e-5)
    else:  # stretched to 48 x 32
        assert valid.all()
        assert np.abs(depth - expected).max() < 10 * 2 / (W - 1)


def test_non_contiguous_image_views_work(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"size": [40, 30], "scale": 1}, channel=0)
    img = coordinate_image(40, 30)
    np.testing.assert_allclose(model.predict(img[:, ::-1]), model.predict(img)[:, ::-1])


def test_free_dimension_override_pins_the_input(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"size": [32, 24]})
    assert tuple(model.input_spec.shape[1:]) == (3, 24, 32)
    assert model.fixed_wh == (32, 24)


def test_fixed_model_size_needs_no_card_size(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {}, shape=(1, 3, 12, 16))
    assert model.fixed_wh == (16, 12)
    model.predict(constant_image((1, 2, 3)))
    assert model.last_input_shape == (1, 3, 12, 16)


# --- batches --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [("N", 3, "H", "W"), (1, 3, "H", "W"), (2, 3, "H", "W")])
def test_predict_batch_with_dynamic_and_fixed_batch_axis(tmp_path: Path, shape: tuple) -> None:
    model = make_depth(tmp_path, {"size": [20, 15], "scale": 1}, shape=shape)
    images = [constant_image((v, 0, 0)) for v in (10, 20, 30)]
    depths = model.predict_batch(images)
    assert [float(d.mean()) for d in depths] == pytest.approx([10, 20, 30])
    assert model.last_input_shape[0] == (3 if shape[0] == "N" else shape[0])
    assert model.last_timings.inference_ms > 0


def test_any_size_batch_needs_one_image_size(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"multiple_of": 8})
    with pytest.raises(DataError, match="one size"):
        model.predict_batch([constant_image((1, 1, 1), 40, 30), constant_image((1, 1, 1), 80, 30)])
    with pytest.raises(DataError, match="at least one image"):
        model.predict_batch([])


# --- broken models --------------------------------------------------------------------------------------
def test_too_new_ir_and_opset_name_the_fix(tmp_path: Path) -> None:
    path = channel_model(tmp_path / "new.onnx", ir_version=14, opset=28)
    with pytest.raises(ModelError, match=r"IR version.*ir_version <= 10 and opset <= 21"):
        open_session(path)
    path = channel_model(tmp_path / "newop.onnx", ir_version=10, opset=28)
    with pytest.raises(ModelError, match=r"opset .*re-export it with ir_version <= 10 and opset <= 21"):
        open_session(path)


def _unknown_op_model(path: Path, domain: str, import_domain: bool) -> Path:
    """(N, 3, H, W) -> an operator onnxruntime does not have, in ``domain`` (imported or not)."""
    value = helper.make_tensor_value_info
    graph = helper.make_graph([helper.make_node("FooBarOp", ["x"], ["out"], domain=domain)], "test",
                              [value("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
                              [value("out", TensorProto.FLOAT, ["N", 1, "H", "W"])])  # fmt: skip
    imports = [helper.make_opsetid("", 17)] + [helper.make_opsetid(domain, 1)] * (bool(domain) and import_domain)
    path.write_bytes(helper.make_model(graph, ir_version=10, opset_imports=imports).SerializeToString())
    return path


@pytest.mark.parametrize(
    ("domain", "import_domain", "needle"),
    [
        ("com.example", True, r"operator com\.example:FooBarOp, which onnxruntime .* does not implement \(a custom"),
        ("", True, r"operator FooBarOp, which onnxruntime .* \(not an ONNX operator of opset 17"),
        ("com.example", False, r"invalid: a node uses the operator domain 'com\.example', which the model does not"),
    ],
)
def test_unknown_operators_are_named_not_called_a_newer_opset(
    tmp_path: Path, domain: str, import_domain: bool, needle: str
) -> None:
    """onnxruntime's text was cut at the operator's ``(-1) ``, dropping its name, and a custom domain without an
    opset import was called "an opset newer than onnxruntime reads", whose fix (an older opset) cannot help."""
    path = _unknown_op_model(tmp_path / "op.onnx", domain, import_domain)
    with pytest.raises(ModelError, match=needle) as info:
        open_session(path)
    assert "is newer than" not in str(info.value)


def test_output_without_the_batch_axis_is_a_model_error(tmp_path: Path) -> None:
    """A model whose output batch is fixed at 1 (here: averaged over the batch) while its input batch is dynamic
    ended ``perceive`` (batches of 8) with a ValueError from zip() deep inside the depth adapter."""
    value = helper.make_tensor_value_info
    path = save_model(tmp_path / "b1.onnx", [helper.make_node("ReduceMean", ["x"], ["out"], axes=[0, 1], keepdims=1)],
                      [value("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
                      [value("out", TensorProto.FLOAT, [1, 1, "H", "W"])])  # fmt: skip
    model = DepthModel(path, parse_card({"task": "depth", "input": {"size": [20, 15], "scale": 1}}), threads=1)
    assert model.predict(constant_image((10, 20, 30))).shape == (30, 40)  # one image: one output, as it should
    with pytest.raises(ModelError, match=r"shape \[1, 1, 15, 20\] for a batch of 3 image\(s\).*same batch axis"):
        model.predict_batch([constant_image((v, 0, 0)) for v in (10, 20, 30)])


def test_missing_and_corrupt_model_files(tmp_path: Path) -> None:
    card = parse_card({"task": "depth", "input": {"size": [8, 8]}})
    with pytest.raises(ModelError, match="does not exist"):
        DepthModel(tmp_path / "nope.onnx", card)
    (tmp_path / "junk.onnx").write_bytes(b"\x00not an onnx model\xff" * 10)
    with pytest.raises(ModelError, match="not a valid ONNX file"):
        DepthModel(tmp_path / "junk.onnx", card)


@pytest.mark.parametrize(
    ("input_card", "model_kwargs", "needle"),
    [
        ({"size": [8, 8]}, {"shape": ("N", 1, "H", "W")}, r"1 channel\(s\) on axis 1.*3-channel"),
        ({"size": [8, 8]}, {"shape": ("N", "H", "W", 3)}, "set layout: NHWC"),
        ({"size": [8, 8], "dtype": "uint8"}, {}, r"tensor\(float\) but the card says input\.dtype uint8"),
        ({"size": [8, 8]}, {"in_type": TensorProto.UINT8}, r"tensor\(uint8\).*input\.dtype float32"),
        ({}, {}, r"dynamic height/width.*set input\.size: \[W, H\].*multiple_of"),
        ({"size": [16, 8]}, {"shape": (1, 3, 12, 16)}, r"disagrees with the model's fixed H = 12"),
        ({"size": [8, 8], "name": "image"}, {}, r"input\.name 'image' is not an input.*inputs: x"),
    ],
)
def test_card_model_mismatches_are_clear(
    tmp_path: Path, input_card: dict, model_kwargs: dict, needle: str
) -> None:
    with pytest.raises(ModelError, match=needle):
        make_depth(tmp_path, input_card, **model_kwargs)


def test_missing_output_name_lists_outputs(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match=r"output\.name 'depth' is not an output.*outputs: out"):
        make_depth(tmp_path, {"size": [8, 8]}, {"name": "depth"})


def test_rank3_input_is_refused(tmp_path: Path) -> None:
    path = rank3_model(tmp_path / "r3.onnx")
    with pytest.raises(ModelError, match=r"rank 3.*rank-4"):
        DepthModel(path, parse_card({"task": "depth", "input": {"size": [8, 8]}}))


def test_wrong_task_and_card_next_to_model(tmp_path: Path) -> None:
    path = channel_model(tmp_path / "net.onnx")
    write_card(tmp_path / "net.yaml", {"task": "depth", "input": {"size": [8, 8]}})
    assert DepthModel(path).fixed_wh == (8, 8)
    with pytest.raises(ModelError, match="says task 'depth' but a segmentation model was expected"):
        SegmentationModel(path)


# --- bad images -----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("image", "needle"),
    [
        (np.zeros((30, 40, 3), dtype=np.float32), "uint8"),
        (np.zeros((30, 40, 4), dtype=np.uint8), r"shape \(H, W, 3\)"),
        (np.zeros((0, 40, 3), dtype=np.uint8), r"shape \(H, W, 3\)"),
        ([[1, 2, 3]], "numpy array"),
        (None, "numpy array"),
    ],
)
def test_bad_images_give_data_errors(tmp_path: Path, image: object, needle: str) -> None:
    model = make_depth(tmp_path, {"size": [8, 8]})
    with pytest.raises(DataError, match=needle):
        model.predict(image)  # type: ignore[arg-type]


def test_measure_overhead_reports_medians(tmp_path: Path) -> None:
    model = make_depth(tmp_path, {"size": [32, 16]})
    stats = measure_overhead(model, constant_image((5, 5, 5), 124, 37), repeats=3)
    assert set(stats) == {
        "preprocess_ms",
        "inference_ms",
        "postprocess_ms",
        "overhead_ms",
        "total_ms",
        "repeats",
    }
    assert stats["repeats"] == 3 and all(v >= 0 for v in stats.values())
    assert stats["total_ms"] >= stats["inference_ms"]
