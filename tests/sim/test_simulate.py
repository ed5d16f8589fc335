"""``simulate`` end to end: sequences that read back, ground-truth files, determinism, CLI and bench."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.bench.simulate import run_simulate_benchmark, simulate_markdown
from shgm_slam.cli import app
from shgm_slam.data import open_sequence
from shgm_slam.errors import ConfigError, SimulationError
from shgm_slam.labels import Label
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario
from shgm_slam.sim.simulate import parse_resolution, simulate
from tests.conftest import TINY_SCENARIO


def test_tiny_scenario_reads_back(tiny_scenario):
    meta = json.loads((tiny_scenario / "scenario.json").read_text())
    world = json.loads((tiny_scenario / "world.json").read_text())
    assert meta["format"] == "shgm-scenario/1" and meta["resolution"] == [320, 96]
    assert [r["name"] for r in meta["robots"]] == ["car1", "car2", "uav"]
    assert world["format"] == "shgm-world/1" and len(world["objects"]) > 100
    assert set(world["robots"]) == {"car1", "car2", "uav"}
    np.testing.assert_array_equal(world["robots"]["uav"]["T_world_robot"], np.eye(4))
    plan = build_scenario("airsim-like", ScenarioOptions(seed=0, fps=4.0, compact=True, uav_speed_mps=12.0))
    for robot, traj in zip(meta["robots"], plan.robots, strict=True):
        seq = open_sequence(tiny_scenario / robot["name"])
        assert len(seq) == robot["frames"] == len(traj) and 30 <= len(seq) <= 80
        assert seq.has_depth and seq.has_labels and seq.intrinsics.size_wh == (320, 96)
        np.testing.assert_allclose(seq.gt_poses, traj.T_world_cam, atol=1e-6)  # poses.txt = the plan
        frame = seq[len(seq) // 2]
        assert frame.image_rgb.shape == (96, 320, 3) and frame.depth_m.dtype == np.float32
        sky = frame.label_ids == Label.SKY
        assert np.all(frame.depth_m[sky] == 0.0) and (frame.depth_m[~sky] > 0).mean() > 0.9
        assert frame.depth_m.max() <= 200.0
    shared = meta["overlap"]["shared_view_m"]
    assert shared["car1"]["car2"] > 60 and shared["uav"]["car1"] > 60 and shared["uav"]["car2"] > 60


def test_same_seed_same_output_other_seed_differs(tmp_path):
    kw = dict(resolution=(64, 24), max_frames=2, compact=True)
    simulate("airsim-like", tmp_path / "a", seed=3, **kw)
    simulate("airsim-like", tmp_path / "b", seed=3, **kw)
    simulate("airsim-like", tmp_path / "c", seed=4, **kw)
    world = {k: (tmp_path / k / "world.json").read_text() for k in "abc"}
    assert world["a"] == world["b"] != world["c"]
    first = {k: cv2.imread(str(tmp_path / k / "car1" / "image_2" / "000000.png")) for k in "abc"}
    assert np.array_equal(first["a"], first["b"]) and not np.array_equal(first["a"], first["c"])
    assert len(open_sequence(tmp_path / "a" / "uav")) == 2


def test_corruption_changes_depth_and_labels(tmp_path):
    from shgm_slam.sim.corruption import CorruptionLevels

    kw = dict(resolution=(64, 24), max_frames=1, compact=True, seed=1)
    simulate("synthia-like", tmp_path / "clean", **kw)
    simulate(
        "synthia-like",
        tmp_path / "noisy",
        corruption=CorruptionLevels(depth_noise=0.1, label_confusion=1.0),
        **kw,
    )
    clean, noisy = (
        open_sequence(tmp_path / "clean" / "forward")[0],
        open_sequence(tmp_path / "noisy" / "forward")[0],
    )
    np.testing.assert_array_equal(clean.image_rgb, noisy.image_rgb)
    assert not np.array_equal(clean.depth_m, noisy.depth_m)
    assert np.mean(clean.label_ids != noisy.label_ids) > 0.3


def test_errors_are_clear(tmp_path):
    with pytest.raises(SimulationError, match="WIDTHxHEIGHT"):
        parse_resolution("640-192")
    with pytest.raises(SimulationError, match="known scenarios"):
        simulate("nope", tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(SimulationError, match="it is a file"):
        simulate("airsim-like", tmp_path / "file", compact=True)
    simulate("airsim-like", tmp_path / "d", resolution=(32, 16), max_frames=1, compact=True)
    with pytest.raises(SimulationError, match="--overwrite"):
        simulate("airsim-like", tmp_path / "d", resolution=(32, 16), max_frames=1, compact=True)
    (tmp_path / "d" / "scenario.json").unlink()  # as if the render had been stopped before its end
    unfinished = r"unfinished render \(car1, car2, uav but no scenario.json\); pass --overwrite"
    with pytest.raises(SimulationError, match=unfinished):
        simulate("airsim-like", tmp_path / "d", resolution=(32, 16), max_frames=1, compact=True)
    simulate("airsim-like", tmp_path / "d", resolution=(32, 16), max_frames=1, compact=True, overwrite=True)
    assert (tmp_path / "d" / "scenario.json").is_file()


def test_overwriting_with_another_scenario_leaves_no_stale_robots(tmp_path):
    """car1, car2 and uav of an airsim-like render stayed beside a synthia-like one written over it, and
    still read as sequences of the folder's scenario."""
    out = tmp_path / "s"
    simulate("airsim-like", out, resolution=(32, 16), max_frames=1, compact=True)
    (out / "notes").mkdir()  # a folder of the user's: not the scenario's, kept
    simulate("synthia-like", out, resolution=(32, 16), max_frames=1, compact=True, overwrite=True)
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["backward", "forward", "notes"]


def test_cli_simulate(tmp_path):
    runner = CliRunner()
    args = [
        "simulate",
        "--scenario",
        "airsim-like",
        "--out",
        str(tmp_path / "s"),
        "--compact",
        "--resolution",
    ]
    args += ["48x16", "--max-frames", "2", "--label-noise", "0.1", "--depth-noise", "0.02"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (
        "car1" in result.output
        and "uav" in result.output
        and (tmp_path / "s" / "uav" / "poses.txt").is_file()
    )
    assert json.loads((tmp_path / "s" / "scenario.json").read_text())["supersample"] == 1
    smooth = ["simulate", "--scenario", "airsim-like", "--out", str(tmp_path / "ss"), "--compact", "--resolution",
              "48x16", "--max-frames", "1", "--supersample", "2"]  # fmt: skip
    result = runner.invoke(app, smooth)
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "ss" / "scenario.json").read_text())["supersample"] == 2
    one, two = (cv2.imread(str(tmp_path / k / "car1" / "image_2" / "000000.png")) for k in ("s", "ss"))
    assert one.shape == two.shape and not np.array_equal(one, two)  # the same view, its colour averaged
    bad = runner.invoke(app, [*smooth[:-1], "0"])
    assert bad.exit_code == 2
    bad = runner.invoke(app, ["simulate", "--scenario", "nope", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "known scenarios" in bad.output
    bad = runner.invoke(
        app, ["simulate", "--scenario", "disjoint", "--out", str(tmp_path / "x"), "--resolution", "9"]
    )
    assert bad.exit_code == 2 and "WIDTHxHEIGHT" in bad.output


def test_bench_simulate_reports_speed_and_memory(tmp_path):
    results = run_simulate_benchmark(
        tmp_path / "bench.json",
        resolution=(48, 16),
        short_frames=2,
        long_frames=4,
        work_dir=tmp_path,
        compact=True,
    )
    assert json.loads((tmp_path / "bench.json").read_text()) == results
    assert results["short"]["frames"] == 6 and results["long"]["frames"] == 12
    assert results["short"]["fps"] > 0 and results["long"]["peak_rss_mb"] > 0
    assert "render only" in simulate_markdown(results)


def test_tiny_scenario_options_are_documented():
    assert TINY_SCENARIO["scenario"] == "airsim-like" and TINY_SCENARIO["compact"]


def test_cli_simulate_flies_the_uav_at_the_altitude_asked_for(tmp_path):
    runner = CliRunner()
    base = ["simulate", "--scenario", "airsim-like", "--compact", "--resolution", "32x16", "--max-frames", "3"]
    result = runner.invoke(app, [*base, "--out", str(tmp_path / "high"), "--uav-altitude", "80-90"])
    assert result.exit_code == 0, result.output
    poses = np.loadtxt(tmp_path / "high" / "uav" / "poses.txt").reshape(-1, 3, 4)
    assert np.all((poses[:, 2, 3] >= 80.0) & (poses[:, 2, 3] <= 90.0))
    scen = json.loads((tmp_path / "high" / "scenario.json").read_text())
    assert scen["notes"]["uav_altitude_m"] == [80.0, 90.0]
    result = runner.invoke(app, [*base, "--out", str(tmp_path / "default")])
    assert json.loads((tmp_path / "default" / "scenario.json").read_text())["notes"]["uav_altitude_m"] == [44.0, 54.0]
    cars = [np.loadtxt(tmp_path / k / "car1" / "poses.txt") for k in ("high", "default")]
    assert np.array_equal(*cars)  # only the UAV's altitude differs
    for alt, words in (("8o", "LOW-HIGH"), ("90-80", "low <= high"), ("150", "raise --max-depth"), ("2", "5 m")):
        bad = runner.invoke(app, [*base, "--out", str(tmp_path / "bad"), "--uav-altitude", alt])
        assert bad.exit_code == 2 and words in bad.output, (alt, bad.output)
    bad = runner.invoke(app, ["simulate", "--scenario", "disjoint", "--out", str(tmp_path / "x"), "--uav-altitude",
                              "60"])  # fmt: skip
    assert bad.exit_code == 2 and "airsim-like" in bad.output
    assert not (tmp_path / "bad").exists() and not (tmp_path / "x").exists()


def test_max_depth_is_checked_without_uav_altitude_too(tmp_path):
    """--max-depth 1 used to render all-zero depth, and 50 m left the default UAV (44-54 m) without ground."""
    runner = CliRunner()
    base = ["simulate", "--compact", "--max-frames", "2", "--resolution", "64x32"]
    for scenario, depth, words in (("disjoint", "5", "render at least 10 m"),
                                   ("airsim-like", "1", "render at least 10 m"),
                                   ("airsim-like", "50", "flies at 44-54 m by default")):  # fmt: skip
        res = runner.invoke(app, [*base, "-s", scenario, "-o", str(tmp_path / "bad"), "--max-depth", depth])
        assert res.exit_code == 2 and words in " ".join(res.output.split()), (scenario, depth, res.output)
    assert not (tmp_path / "bad").exists()
    ok = runner.invoke(app, [*base, "-s", "airsim-like", "-o", str(tmp_path / "ok"), "--max-depth", "80"])
    assert ok.exit_code == 0, ok.output


def test_a_world_larger_than_the_memory_is_refused_before_it_is_built(tmp_path, monkeypatch):
    """--world-size 5000 took 5 GB; under a memory limit the ray tracer crashed (signal 11) instead of erring."""
    import importlib

    sim = importlib.import_module("shgm_slam.sim.simulate")  # (the package's `simulate` is the function)
    monkeypatch.setattr(sim, "available_memory_bytes", lambda: 2e9)
    with pytest.raises(ConfigError, match=r"--world-size 5000 m: .* about 5 GB .* choose at most about 2958 m"):
        simulate("airsim-like", tmp_path / "w", world_size_m=5000.0)
    assert not (tmp_path / "w").exists()
    sim.check_world_memory(2000.0)  # ~1 GB: fits
    monkeypatch.setattr(sim, "available_memory_bytes", lambda: None)
    sim.check_world_memory(20000.0)  # unknown memory: not refused
