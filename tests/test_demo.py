"""The demo's configuration: no per-robot settings (derived from the data), and the RGB-only settings."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import MATCHES_TO_ANCHOR, ExtractionConfig, OdometryConfig, OdometryKind
from shgm_slam.demo import MODELS_DIR, demo_config
from shgm_slam.errors import DataError
from shgm_slam.odometry.sources import resolve_kind
from shgm_slam.scene_scale import SceneScale, resolve_robot_config

UAV_SCALE = SceneScale(5, 50.0, 50.0, 53.0, 110.0, (50.0, 62.0, 80.0))
"""What the airsim-like UAV's first frames measure (44-54 m up, 50 deg oblique)."""


def test_files_demo_uses_kiss_icp_and_anchors_on_two_independent_matches():
    cfg = demo_config()
    assert cfg.perception.depth_model is None
    assert resolve_kind(cfg.odometry.kind, cfg.perception.depth_model is not None) is OdometryKind.KISS_ICP
    assert cfg.backend.for_depth(predicted_depth=False).min_closures_to_anchor == MATCHES_TO_ANCHOR == 2
    assert cfg.robots == {}


def test_demo_leaves_the_uav_settings_to_its_data():
    uav = resolve_robot_config(demo_config().for_robot("uav"), UAV_SCALE)
    assert uav.extraction.max_depth_m > 90.0  # the nearest ground is 53 m away
    assert uav.extraction.min_blob_fraction < ExtractionConfig.FLEET["min_blob_fraction"]
    assert uav.odometry.shuffle_points is True
    assert uav.odometry.visual_max_depth_m > 100.0
    car = resolve_robot_config(demo_config().for_robot("car1"), None)
    assert car.extraction.max_depth_m == ExtractionConfig.FLEET["max_depth_m"]
    assert car.odometry.voxel_size_m == OdometryConfig.FLEET["voxel_size_m"]
    assert np.isclose(car.extraction.min_blob_fraction, 5000.0 / (1024 * 576))


@pytest.mark.skipif(not (MODELS_DIR / "demo_depth.onnx").is_file(), reason="demo models not in models/")
def test_rgb_only_demo_uses_models_visual_odometry_and_confirmed_anchors():
    cfg = demo_config(rgb_only=True)
    assert cfg.perception.depth_model == MODELS_DIR / "demo_depth.onnx"
    assert resolve_kind(cfg.odometry.kind, True) is OdometryKind.VISUAL
    assert cfg.backend.for_depth(predicted_depth=True).min_closures_to_anchor == MATCHES_TO_ANCHOR
    assert cfg.odometry.visual_max_depth_m is None  # derived per robot


def test_rgb_only_without_models_names_the_training_script(monkeypatch, tmp_path):
    monkeypatch.setattr("shgm_slam.demo.MODELS_DIR", tmp_path)
    with pytest.raises(DataError, match="train_demo_models"):
        demo_config(rgb_only=True)


def test_plain_and_rgb_only_demos_write_separate_results(monkeypatch, tmp_path):
    """``demo --rgb-only`` must not overwrite the plain demo's results (results/demo vs results/demo-rgb)."""
    from types import SimpleNamespace

    from typer.testing import CliRunner

    import shgm_slam.cli as cli
    import shgm_slam.cli.system as system
    import shgm_slam.demo as demo

    outs = []
    monkeypatch.setattr(demo, "prepare_world", lambda cache, seed, fn: (tmp_path, {"car1": "car"}))
    monkeypatch.setattr(system, "_run_command", lambda robots, cfg, out, *a: outs.append(out) or SimpleNamespace())
    monkeypatch.setattr(system, "render_summary", lambda summary: None)
    for args in ([], ["--rgb-only"], ["--out", str(tmp_path / "mine")]):
        res = CliRunner().invoke(cli.app, ["demo", "--rerun", "off", *args])
        assert res.exit_code == 0, res.output
    assert outs == [demo.RESULTS_DIR, demo.RGB_ONLY_RESULTS_DIR, tmp_path / "mine"]
    assert demo.RESULTS_DIR != demo.RGB_ONLY_RESULTS_DIR


def test_a_demo_whose_first_render_was_interrupted_renders_again(monkeypatch, tmp_path):
    """Ctrl-C during the first ``make demo`` leaves a half-rendered world in the cache; the next ``demo`` must
    render it again, not stop on "car1 is not empty"."""
    from types import SimpleNamespace

    from typer.testing import CliRunner

    import shgm_slam.cli as cli
    import shgm_slam.cli.system as system

    half = tmp_path / "cache" / "airsim-like-seed0" / "car1" / "image_2"
    half.mkdir(parents=True)
    (half / "000000.png").write_bytes(b"")
    rendered = []

    def fake_simulate(scenario, out, *, seed, progress, overwrite):
        rendered.append(out)
        (out / "car1").mkdir(parents=True)
        (out / "scenario.json").write_text('{"robots": [{"name": "car1", "kind": "car"}]}')

    monkeypatch.setattr("shgm_slam.sim.cache.simulate", fake_simulate)
    monkeypatch.setattr(system, "_run_command", lambda *a: SimpleNamespace())
    monkeypatch.setattr(system, "render_summary", lambda summary: None)
    res = CliRunner().invoke(cli.app, ["demo", "--rerun", "off", "--cache", str(tmp_path / "cache"),
                                       "--out", str(tmp_path / "out")])  # fmt: skip
    assert res.exit_code == 0, res.output
    world = tmp_path / "cache" / "airsim-like-seed0"
    assert len(rendered) == 1 and (world / "scenario.json").is_file() and not (world / "car1" / "image_2").exists()
