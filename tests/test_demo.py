"""The demo's configuration: UAV overrides and the RGB-only settings."""

from __future__ import annotations

import pytest

from shgm_slam.config import OdometryKind
from shgm_slam.demo import MODELS_DIR, demo_config
from shgm_slam.errors import DataError
from shgm_slam.odometry.sources import resolve_kind

KINDS = {"car1": "car", "car2": "car", "uav": "uav"}


def test_files_demo_uses_kiss_icp_and_trusts_single_matches():
    cfg = demo_config(KINDS)
    assert cfg.perception.depth_model is None
    assert resolve_kind(cfg.odometry.kind, cfg.perception.depth_model is not None) is OdometryKind.KISS_ICP
    assert cfg.backend.min_closures_to_anchor == 1
    assert cfg.for_robot("uav").extraction.max_depth_m == 100.0
    assert cfg.for_robot("car1").extraction.max_depth_m == cfg.extraction.max_depth_m


@pytest.mark.skipif(not (MODELS_DIR / "demo_depth.onnx").is_file(), reason="demo models not in models/")
def test_rgb_only_demo_uses_models_visual_odometry_and_confirmed_anchors():
    cfg = demo_config(KINDS, rgb_only=True)
    assert cfg.perception.depth_model == MODELS_DIR / "demo_depth.onnx"
    assert resolve_kind(cfg.odometry.kind, True) is OdometryKind.VISUAL
    assert cfg.backend.min_closures_to_anchor == 2
    assert cfg.for_robot("uav").odometry.visual_max_depth_m == 150.0


def test_rgb_only_without_models_names_the_training_script(monkeypatch, tmp_path):
    monkeypatch.setattr("shgm_slam.demo.MODELS_DIR", tmp_path)
    with pytest.raises(DataError, match="train_demo_models"):
        demo_config(KINDS, rgb_only=True)
