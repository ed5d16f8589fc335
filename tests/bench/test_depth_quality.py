"""The depth-quality study: levels, corrupted sequences, odometry alone, and the whole pipeline on a
tiny world (one level pair, short sequences)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.bench import depth_quality as dq
from shgm_slam.bench.heldout import world_folder
from shgm_slam.cli import app
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.errors import ConfigError
from shgm_slam.io.json_text import to_json_text
from shgm_slam.sim.depth_errors import abs_rel


def test_levels_parse_and_refuse_nonsense():
    assert dq.parse_level("true") is dq.TRUE_DEPTH
    assert dq.parse_level("model") is dq.DEMO_MODEL
    assert dq.parse_level(" 0.05 ").abs_rel == 0.05
    for bad in ("abc", "0", "1.5", "-0.1"):
        with pytest.raises(ConfigError, match="depth level"):
            dq.parse_level(bad)


def test_network_like_depth_hits_its_level_and_changes_nothing_else(tiny_scenario):
    base = open_sequence(tiny_scenario / "car1")
    seq, errors = dq.network_like(base, 0.08, seed=4)
    assert errors.amplitude > 0
    measured = np.mean([abs_rel(base[i].depth_m, seq[i].depth_m) for i in range(1, len(base), 3)])
    assert measured == pytest.approx(0.08, rel=0.3)
    a, b = seq[7], base[7]
    np.testing.assert_array_equal(a.image_rgb, b.image_rgb)
    np.testing.assert_array_equal(a.label_ids, b.label_ids)
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    np.testing.assert_array_equal(seq[7].depth_m, seq[7].depth_m)  # the same frame, the same depth
    assert not np.array_equal(a.depth_m, b.depth_m)
    assert len(seq) == len(base) and seq.has_depth and seq.gt_poses is base.gt_poses


def test_odometry_alone_on_true_depth_barely_drifts(tiny_scenario):
    seq = open_sequence(tiny_scenario / "car1")
    track, poses = dq.run_odometry(seq, ShgmConfig(), OdometryKind.KISS_ICP, true_depth=seq)
    assert poses.shape == (len(seq), 4, 4)
    assert track.abs_rel == 0.0 and track.frames == len(seq)
    assert track.drift_percent < 3.0 and track.ate_aligned_m < 1.0


def test_study_pipeline_on_a_tiny_world(tiny_scenario, tmp_path):
    cache = tmp_path / "cache"
    folder = world_folder(cache, "airsim-like", 0, (320, 96))
    folder.parent.mkdir(parents=True)
    folder.symlink_to(tiny_scenario, target_is_directory=True)  # the held-out cache layout, already rendered
    options = dq.DepthQualityOptions(
        scenarios=("airsim-like",), seeds=(0,), levels=(dq.TRUE_DEPTH, dq.parse_level("0.1")),
        odometry_kinds=(OdometryKind.KISS_ICP,), system_kinds=(OdometryKind.HYBRID,), max_frames=25, cache=cache,
    )  # fmt: skip
    out = tmp_path / "study"
    results = dq.run_depth_quality_benchmark(out, options)
    assert (out / "depth_quality.png").stat().st_size > 1000
    md = (out / "depth_quality.md").read_text()
    assert "| true |" in md and "| 0.10 |" in md
    assert "the first 25 frames of every robot" in md  # the caption says the runs were cut
    true, noisy = results["summary"]
    assert true["abs_rel_measured"] == 0.0 and noisy["abs_rel_measured"] == pytest.approx(0.1, rel=0.35)
    assert true["odometry"]["kiss-icp"]["all"]["robots"] == 3
    assert true["system"]["hybrid"]["overlapping"] == 2  # car2 and the UAV; car1 is the reference
    again = dq.run_depth_quality_benchmark(out, options)  # resumes: everything comes from the cache
    assert to_json_text(again["rows"]) == to_json_text(results["rows"])  # NaN-aware: both as strict JSON


def test_cli_refuses_bad_levels_and_kinds(tmp_path):
    runner = CliRunner()
    for args in (["--level", "abc"], ["--odometry", "gt"], ["--system", "visual,nonsense"], ["--seeds", "9-3"]):
        res = runner.invoke(app, ["bench", "depth-quality", "-o", str(tmp_path / "o"), *args])
        assert res.exit_code == 2, res.output


def test_resume_cache_is_strict_json_and_reads_nan_back(tmp_path):
    """The study's resume cache holds numbers that were not measurable (a robot not placed): written as null
    (strict JSON), read back as NaN; computed once."""
    calls = []

    def compute():
        calls.append(1)
        return {"outcome": "not placed", "placed": False, "placement_error_m": float("nan"), "rows": [1.5, np.nan]}

    path = tmp_path / "cache" / "verdicts.json"
    first = dq._cached(path, compute)
    json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c} in the cache"))
    again = dq._cached(path, compute)
    assert len(calls) == 1
    assert np.isnan(again["placement_error_m"]) and np.isnan(again["rows"][1]) and again["rows"][0] == 1.5
    assert again["outcome"] == first["outcome"] and again["placed"] is False
