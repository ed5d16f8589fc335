"""No option or config value can ask for absurd memory or time: upper bounds with clear messages (exit 2)."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.config import load_config
from shgm_slam.errors import ConfigError

runner = CliRunner()


@pytest.mark.parametrize(
    "args",
    [
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--fps", "10000"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--max-frames", "100000000"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--resolution", "100000x100000"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--world-size", "1e9"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--depth-noise", "50"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--seed", "-1"],
        ["check-model", "{tmp}/m.onnx", "--runs", "100000000"],
        ["check-model", "{tmp}/m.onnx", "--threads", "100000"],
        ["perceive", "{tmp}/s", "-o", "{tmp}/p", "--batch-size", "1000000"],
        ["bench", "simulate", "-o", "{tmp}/b.json", "--long-frames", "100000000"],
        ["bench", "heldout", "-o", "{tmp}/h", "--jobs", "1000"],
        ["bench", "table3", "-o", "{tmp}/t", "--runs", "1000000000"],
        ["server", "--out", "{tmp}/srv", "--expect", "1000"],
        ["demo", "--seed", "99999999999"],
    ],
)
def test_absurd_options_are_refused_with_exit_2(tmp_path, args):
    res = runner.invoke(app, [a.replace("{tmp}", str(tmp_path)) for a in args])
    assert res.exit_code == 2, res.output
    assert "Invalid value" in res.output or "out of range" in res.output, res.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("value", ["nan", "-inf", "Infinity"])
@pytest.mark.parametrize(
    "args",
    [
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--depth-noise"],
        ["simulate", "-s", "airsim-like", "-o", "{tmp}/x", "--world-size"],
        ["bench", "heldout", "-o", "{tmp}/x", "--label-noise"],
        ["server", "--out", "{tmp}/x", "--stale-after"],
    ],
)
def test_non_finite_bounded_floats_are_named_as_such(tmp_path, args, value):
    # a range check alone said NaN was "not less than or equal to" the upper bound
    res = runner.invoke(app, [a.replace("{tmp}", str(tmp_path)) for a in args] + [value])
    assert res.exit_code == 2, res.output
    assert "not a finite number" in res.output, res.output
    assert "less than or equal" not in res.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "yaml_text",
    [
        "odometry: {voxel_size_m: 0.0001}",
        "matching: {ransac_iterations: 100000000000}",
        "descriptor: {num_walks: 100000000}",
        "odometry: {max_icp_iterations: 100000000}",
        "perception: {threads: 100000}",  # onnxruntime started 100000 threads: the run hung
    ],
)
def test_absurd_config_values_are_config_errors(tmp_path, yaml_text):
    path = tmp_path / "c.yaml"
    path.write_text(yaml_text + "\n")
    with pytest.raises(ConfigError, match="than or equal to"):
        load_config(path)


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--noise-m", "3-1", "start is above its end; write 1-3"),
        ("--noise-m", "nan-2", "must be finite"),
        ("--miss", "a-b", "write a range of numbers"),
        ("--miss", "0.1-0.2-0.3", "write a range of numbers"),
        ("--share-m", "", "write a range of numbers"),
    ],
)
def test_malformed_number_ranges_are_refused_before_anything_runs(tmp_path, option, value, says):
    res = runner.invoke(app, ["bench", "sparse", "-o", str(tmp_path / "x"), option, value])
    assert res.exit_code == 2, res.output
    assert "Invalid value" in res.output and says in " ".join(res.output.replace("│", " ").split()), res.output
    assert not (tmp_path / "x").exists()


def test_a_number_range_is_one_argument_and_reads_exponents():
    from shgm_slam.cli.options import NumberRange, number_range

    assert number_range("0.5-2") == NumberRange(0.5, 2.0)
    assert number_range("2") == NumberRange(2.0, 2.0)  # one number: the range of that number alone
    assert number_range("1e-3-0.5") == NumberRange(0.001, 0.5)  # the exponent's minus is not the range's
    assert number_range(" 3 - 4 ").as_tuple() == (3.0, 4.0)


def test_map_conditions_out_of_bounds_are_refused_with_the_bounds(tmp_path):
    res = runner.invoke(app, ["bench", "sparse", "-o", str(tmp_path / "x"), "--miss", "0.2-0.99"])
    assert res.exit_code == 2, res.output
    assert "miss_range 0.2-0.99" in res.output and "within 0..0.95" in res.output, res.output
    assert not (tmp_path / "x").exists()
