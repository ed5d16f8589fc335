"""Depth adapter: every output kind converts to metres; clamping, invalid values, resize-back."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.errors import ModelError
from shgm_slam.perception.card import parse_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.types import Intrinsics
from tests.perception.onnx_builders import channel_model

_ids = itertools.count()


def raw_value_model(tmp_path: Path, output: dict, size: list[int] = (20, 15), **kwargs) -> DepthModel:
    """Raw model output = the red channel's pixel value (scale 1), converted per ``output``."""
    path = channel_model(tmp_path / f"d{next(_ids)}.onnx", **kwargs)
    card = {"task": "depth", "input": {"size": list(size), "scale": 1}, "output": output}
    return DepthModel(path, parse_card(card), threads=1)


def red_image(value: int, width: int = 40, height: int = 30) -> np.ndarray:
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[:, :, 0] = value
    return img


@pytest.mark.parametrize(
    ("output", "raw", "expected_m"),
    [
        ({"kind": "metric"}, 20, 20.0),
        ({"kind": "relative", "scale": 0.5, "shift": 2.0}, 20, 12.0),
        ({"kind": "inverse", "scale": 0.01}, 20, 5.0),
        ({"kind": "inverse", "scale": "1/100", "shift": 0.05}, 15, 5.0),
        ({"kind": "disparity", "focal_x_baseline": 100.0}, 10, 5.0),  # 10 px at half width = 20 image px
    ],
)
def test_depth_kinds_convert_to_metres(tmp_path: Path, output: dict, raw: int, expected_m: float) -> None:
    model = raw_value_model(tmp_path, output)
    depth = model.predict(red_image(raw))
    assert depth.shape == (30, 40) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, expected_m, rtol=1e-5)


def test_disparity_with_baseline_uses_the_frames_fx(tmp_path: Path) -> None:
    model = raw_value_model(tmp_path, {"kind": "disparity", "baseline_m": 0.5})
    assert model.needs_intrinsics
    with pytest.raises(ModelError, match="intrinsics"):
        model.predict(red_image(10))
    fx_200 = Intrinsics(200.0, 200.0, 20.0, 15.0, 40, 30)
    np.testing.assert_allclose(model.predict(red_image(10), fx_200), 200 * 0.5 / 20, rtol=1e-5)
    # intrinsics of the same camera at twice the resolution: fx scales with the image width
    fx_400_at_80 = Intrinsics(400.0, 400.0, 40.0, 30.0, 80, 60)
    np.testing.assert_allclose(model.predict(red_image(10), fx_400_at_80), 5.0, rtol=1e-5)


def test_disparity_accounts_for_the_model_resolution(tmp_path: Path) -> None:
    # the same 10 px disparity means twice the depth when the model sees the image at full width
    half = raw_value_model(tmp_path, {"kind": "disparity", "focal_x_baseline": 100.0}, size=[20, 15])
    full = raw_value_model(tmp_path, {"kind": "disparity", "focal_x_baseline": 100.0}, size=[40, 30])
    assert float(full.predict(red_image(10)).mean()) == pytest.approx(
        2 * float(half.predict(red_image(10)).mean())
    )


def test_clamp_and_invalid_values(tmp_path: Path) -> None:
    model = raw_value_model(tmp_path, {"kind": "metric", "min_depth_m": 1.0, "max_depth_m": 80.0})
    assert float(model.predict(red_image(200)).max()) == 80.0  # clamped to max
    assert float(model.predict(red_image(0)).max()) == 0.0  # 0 = invalid, not clamped up to min
    inv = raw_value_model(tmp_path, {"kind": "inverse"})
    assert float(inv.predict(red_image(0)).max()) == 0.0  # 1/0 = inf -> invalid
    rel = raw_value_model(tmp_path, {"kind": "relative", "shift": -50.0})
    assert float(rel.predict(red_image(20)).max()) == 0.0  # negative depth -> invalid


def test_invalid_pixels_do_not_bleed_into_valid_ones(tmp_path: Path) -> None:
    # left half invalid (0), right half 50 m; upsampling from the half-resolution model output must not
    # produce in-between depths at the boundary
    model = raw_value_model(tmp_path, {"kind": "metric"}, size=[20, 15])
    img = red_image(0, width=80, height=30)
    img[:, 40:, 0] = 50
    depth = model.predict(img)
    valid = depth > 0
    np.testing.assert_allclose(depth[valid], 50.0, rtol=1e-5)
    assert abs(int(valid[0].argmax()) - 40) <= 2  # the boundary stays in place
