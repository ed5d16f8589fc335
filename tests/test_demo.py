"""The demo's configuration: no per-robot settings (derived from the data), and the RGB-only settings."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import MATCHES_TO_ANCHOR, ExtractionConfig, OdometryConfig, OdometryKind
from shgm_slam.demo import DEMO_DEPTH_MODEL, DEMO_SEG_MODEL, MODELS_DIR, demo_config, demo_model_paths, model_dirs
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


def test_rgb_only_without_models_names_where_it_looked_and_what_to_do(monkeypatch, tmp_path):
    monkeypatch.setattr("shgm_slam.demo.model_dirs", lambda: [tmp_path / "checkout", tmp_path / "venv"])
    with pytest.raises(DataError) as err:
        demo_config(rgb_only=True)
    message = str(err.value)
    assert str(tmp_path / "checkout") in message and str(tmp_path / "venv") in message
    assert "train_demo_models" in message and "--depth-model" in message


def test_installed_models_are_found_when_the_checkout_has_none(tmp_path):
    """A wheel (``pip install .``, not editable) puts the models under ``share/shgm-slam/models``."""
    checkout, installed = tmp_path / "checkout", tmp_path / "installed"
    checkout.mkdir()
    (checkout / DEMO_DEPTH_MODEL).write_bytes(b"only one of the two")
    installed.mkdir()
    for name in (DEMO_DEPTH_MODEL, DEMO_SEG_MODEL):
        (installed / name).write_bytes(b"onnx")
    assert demo_model_paths([checkout, installed]) == (installed / DEMO_DEPTH_MODEL, installed / DEMO_SEG_MODEL)


def test_the_checkout_comes_first_and_the_environment_is_searched():
    dirs = model_dirs()
    assert dirs[0] == MODELS_DIR
    assert any(d.parts[-3:] == ("share", "shgm-slam", "models") for d in dirs[1:])


def test_every_committed_model_file_is_shipped_by_the_package():
    """``pyproject.toml``'s data-files globs cover every file of models/."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((MODELS_DIR.parent / "pyproject.toml").read_text())
    globs = project["tool"]["setuptools"]["data-files"]["share/shgm-slam/models"]
    shipped = {p.name for g in globs for p in MODELS_DIR.parent.glob(g)}
    assert {DEMO_DEPTH_MODEL, DEMO_SEG_MODEL, "demo_depth.yaml", "demo_seg.yaml"} <= shipped
    assert shipped == {p.name for p in MODELS_DIR.iterdir() if p.is_file()}


def test_rgb_only_demo_without_models_fails_before_rendering_the_world(monkeypatch, tmp_path):
    from typer.testing import CliRunner

    import shgm_slam.cli as cli
    import shgm_slam.demo as demo

    rendered = []
    monkeypatch.setattr(demo, "model_dirs", lambda: [tmp_path])
    monkeypatch.setattr(demo, "prepare_world", lambda *a: rendered.append(a) or (tmp_path, {}))
    res = CliRunner().invoke(cli.app, ["demo", "--rgb-only", "--rerun", "off"])
    assert res.exit_code == 2, res.output
    assert "demo models" in res.output and rendered == []


def test_plain_and_rgb_only_demos_write_separate_results(monkeypatch, tmp_path):
    """``demo --rgb-only`` must not overwrite the plain demo's results (results/demo vs results/demo-rgb)."""
    from types import SimpleNamespace

    from typer.testing import CliRunner

    import shgm_slam.cli as cli
    import shgm_slam.cli.system as system
    import shgm_slam.demo as demo

    outs = []
    monkeypatch.setattr(demo, "prepare_world", lambda cache, seed, fn: (tmp_path, {"car1": "car"}))
    monkeypatch.setattr(system, "_run_command", lambda robots, cfg, out, *a: outs.append(out) or SimpleNamespace(
        interrupted=False, front_ends_lost=[]))
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
    monkeypatch.setattr(system, "_run_command", lambda *a: SimpleNamespace(interrupted=False, front_ends_lost=[]))
    monkeypatch.setattr(system, "render_summary", lambda summary: None)
    res = CliRunner().invoke(cli.app, ["demo", "--rerun", "off", "--cache", str(tmp_path / "cache"),
                                       "--out", str(tmp_path / "out")])  # fmt: skip
    assert res.exit_code == 0, res.output
    world = tmp_path / "cache" / "airsim-like-seed0"
    assert len(rendered) == 1 and (world / "scenario.json").is_file() and not (world / "car1" / "image_2").exists()


def test_the_viewer_command_is_the_one_beside_this_python(monkeypatch, tmp_path):
    from shgm_slam.cli.system import viewer_command

    monkeypatch.setattr("sys.executable", str(tmp_path / "python"))
    assert viewer_command() == "rerun"  # none beside it: the PATH's
    (tmp_path / "rerun").write_text("#!/bin/sh\n")
    assert viewer_command() == str(tmp_path / "rerun")
