"""The robot front end's object extraction: thin objects of predicted depth are placed at their near part."""

from __future__ import annotations

from pathlib import Path

import pytest

import shgm_slam.robot.frontend as frontend_module
from shgm_slam.config import ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.labels import THIN_OBJECT_DEPTH_PERCENTILES, Label
from shgm_slam.runner import make_frontend
from tests.perception.test_ground_scale import _perceived_copy
from tests.spies import record_depth_percentiles


def _percentiles_used(front, monkeypatch: pytest.MonkeyPatch, frames: int = 6) -> list:
    seen = record_depth_percentiles(monkeypatch, frontend_module)
    for i in range(frames):
        front.process(i)
    return seen


def test_thin_objects_take_the_near_percentile_only_with_predicted_depth(
    tiny_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = '{"format": "shgm-perceive/1", "depth_model": {"path": "/m/depth.onnx"}, "seg_model": null}'
    cfg = ShgmConfig()
    assert cfg.extraction.predicted_depth_percentiles == THIN_OBJECT_DEPTH_PERCENTILES
    assert set(THIN_OBJECT_DEPTH_PERCENTILES) == {Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN}
    perceived = _perceived_copy(tiny_scenario / "car1", tmp_path / "p", model)
    predicted = make_frontend("car1", open_sequence(perceived), cfg)
    used = _percentiles_used(predicted, monkeypatch)
    assert used and all(u == THIN_OBJECT_DEPTH_PERCENTILES for u in used)
    measured = make_frontend("car1", open_sequence(tiny_scenario / "car1"), cfg)
    used = _percentiles_used(measured, monkeypatch)
    assert used and all(u is None for u in used)  # rendered (measured) depth keeps the mean
    mine = cfg.model_copy(update={"extraction": cfg.extraction.model_copy(
        update={"predicted_depth_percentiles": {Label.VEGETATION: 40.0}})})  # fmt: skip
    own = make_frontend("car1", open_sequence(tmp_path / "p"), mine)
    used = _percentiles_used(own, monkeypatch)
    assert used and all(u == {Label.VEGETATION: 40.0} for u in used)  # a configured mapping replaces the default
