"""Configuration: semantic checks that refuse settings which would make a run silently do nothing."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from shgm_slam.config import OdometryKind, ShgmConfig, load_config
from shgm_slam.errors import ConfigError
from shgm_slam.runner import open_robots, run_slam


@pytest.mark.parametrize(
    ("yaml_text", "culprit"),
    [
        ("extraction: {labels: []}", "labels is empty"),
        ("extraction: {labels: [2, 255]}", "train ids"),
        ("extraction: {min_depth_m: 40, max_depth_m: 30}", "must be below max_depth_m"),
        ("robots: {uav: {extraction: {labels: []}}}", "labels is empty"),
        ("extraction: {labels: [0, 99]}", "train ids 0-18"),  # no such Cityscapes class: no node ever
        ("keyframes: {distance_m: .inf}", r"keyframes\.distance_m: Input should be a finite number"),  # 1 keyframe
        ("matching: {max_rmse_m: .nan}", "finite number"),
        ("keyframes: {distance_m: true}", "distance_m: true is not a number"),  # read as 1 m before
        ("descriptor: {seed: -1}", r"descriptor\.seed: Input should be greater than or equal to 0"),
        ("matching: {seed: -1}", r"matching\.seed"),
        ("keyframes: {distance_m: 3}\nkeyframes: {distance_m: 4}", r"line 2, column 1: key 'keyframes' given twice"),
        ("keyframes:\n  distance_m: [3\n", r"not valid YAML: line \d+, column \d+: expected ',' or ']'"),
        ("matching: {topk: 3}", r"matching\.topk: Extra inputs are not permitted; did you mean top_k\?"),
        ("robots: {uav: {graph: {merge_radius_m: 3}}}", "known here: extraction, odometry, keyframes, perception"),
        ("odometry: {kind: kiss_icp}", r"odometry\.kind: .*, got 'kiss_icp'; did you mean 'kiss-icp'\?"),
    ],
)
def test_settings_that_make_a_run_do_nothing_are_refused(tmp_path: Path, yaml_text: str, culprit: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(yaml_text + "\n")
    with pytest.raises(ConfigError, match=culprit):
        load_config(path)


def test_derived_max_depth_still_allows_any_min_depth(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("extraction: {min_depth_m: 40}\n")  # max_depth_m derived from the data later
    assert load_config(path).extraction.min_depth_m == 40


def test_overrides_for_a_robot_not_in_the_run_are_refused(tiny_scenario: Path, tmp_path: Path) -> None:
    cfg = ShgmConfig.model_validate({"robots": {"uva": {"extraction": {"max_depth_m": 100}}}})
    with pytest.raises(ConfigError, match="uva"):
        run_slam(open_robots([f"car1={tiny_scenario / 'car1'}"]), cfg, tmp_path / "out")


def test_gt_odometry_without_ground_truth_is_refused_before_the_run(tiny_scenario: Path, tmp_path: Path) -> None:
    seq = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq)
    (seq / "poses.txt").unlink()
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    with pytest.raises(ConfigError, match="needs ground-truth poses"):
        run_slam(open_robots([f"car1={seq}"]), cfg, tmp_path / "out")
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_odometry_drift_follows_where_the_depth_comes_from() -> None:
    from types import SimpleNamespace

    from shgm_slam.config import MATCHES_TO_ANCHOR, MEASURED_DEPTH_DRIFT, PREDICTED_DEPTH_DRIFT, BackendConfig
    from shgm_slam.runner import fleet_backend

    b = BackendConfig()
    measured, predicted = b.for_depth(predicted_depth=False), b.for_depth(predicted_depth=True)
    assert (measured.odometry_drift_rot_rad_per_m, measured.odometry_drift_trans_per_m) == MEASURED_DEPTH_DRIFT
    assert (predicted.odometry_drift_rot_rad_per_m, predicted.odometry_drift_trans_per_m) == PREDICTED_DEPTH_DRIFT
    assert PREDICTED_DEPTH_DRIFT[1] > MEASURED_DEPTH_DRIFT[1]
    user = BackendConfig(odometry_drift_trans_per_m=0.02).for_depth(predicted_depth=True)  # the user's value wins
    assert user.odometry_drift_trans_per_m == 0.02 and user.odometry_drift_rot_rad_per_m == PREDICTED_DEPTH_DRIFT[0]
    # anchoring does not depend on the depth source; the user's value stays
    assert measured.min_closures_to_anchor == predicted.min_closures_to_anchor == MATCHES_TO_ANCHOR
    assert BackendConfig(min_closures_to_anchor=1).for_depth(predicted_depth=True).min_closures_to_anchor == 1

    cfg = ShgmConfig()
    rgb = cfg.model_copy(deep=True)
    rgb.perception.depth_model = Path("d.onnx")
    # one robot on a depth model (or on files a depth model wrote: the front end says which)
    fronts = {"a": SimpleNamespace(cfg=cfg, depth_predicted=False), "b": SimpleNamespace(cfg=rgb, depth_predicted=True)}
    assert fleet_backend(cfg, fronts).backend.odometry_drift_trans_per_m == PREDICTED_DEPTH_DRIFT[1]
    assert fleet_backend(cfg, {"a": fronts["a"]}).backend.odometry_drift_trans_per_m == MEASURED_DEPTH_DRIFT[1]
    # written resolved into config.yaml and read back unchanged
    again = ShgmConfig.model_validate(yaml.safe_load(fleet_backend(cfg, fronts).to_yaml()))
    assert again.backend.odometry_drift_rot_rad_per_m == PREDICTED_DEPTH_DRIFT[0]


def test_a_zero_up_axis_is_refused(tmp_path):
    path = tmp_path / "up.yaml"
    path.write_text("matching:\n  up_axis: [0, 0, 0]\n")
    with pytest.raises(ConfigError, match="up_axis must be a finite non-zero vector"):
        load_config(path)


def test_a_bad_robot_override_names_its_place_once(tmp_path: Path) -> None:
    """A robot's override is checked by a whole-config validator, whose location is empty: the message read
    "config file c.yaml: : Value error, robots.car1...". It names the robot's field once, after the file."""
    path = tmp_path / "c.yaml"
    path.write_text("robots:\n  car1:\n    odometry:\n      voxel_size_m: -3\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: Value error, robots\.car1\.odometry\.voxel_size_m: Input") as info:
        load_config(path)
    assert ": :" not in str(info.value)


def test_an_integer_of_thousands_of_digits_or_deep_nesting_is_said_in_our_words(tmp_path):
    huge = tmp_path / "huge.yaml"
    huge.write_text("graph:\n  connectivity_m: " + "9" * 5000 + "\n")
    with pytest.raises(ConfigError, match="holds an integer of 5000 digits") as info:
        load_config(huge)
    assert "set_int_max_str_digits" not in str(info.value)  # Python's advice is not ours to give
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match="its nesting is too deep"):
        load_config(deep)


def test_true_and_false_still_set_switches(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("matching: {gravity_aligned: true, polish: false}\n"
                    "odometry: {image_rotation: false, shuffle_points: true}\n")  # fmt: skip
    cfg = load_config(path)
    assert cfg.matching.gravity_aligned and not cfg.matching.polish
    assert not cfg.odometry.image_rotation and cfg.odometry.shuffle_points


def test_a_folder_given_as_the_config_is_named_so(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder; give a YAML file"):
        load_config(tmp_path)


def test_the_front_end_digest_follows_what_shapes_a_robots_graph() -> None:
    """Equal configs agree; a front-end setting, fleet-wide or in this robot's overrides, changes it; another
    robot's overrides, the back end and what a robot process sets for itself do not."""
    base = ShgmConfig()
    d = base.front_end_digest("uav")
    assert d == ShgmConfig().front_end_digest("uav") and len(d) == 16
    assert ShgmConfig.model_validate({"graph": {"merge_radius_m": 4}}).front_end_digest("uav") != d
    assert ShgmConfig.model_validate({"robots": {"uav": {"extraction": {"max_depth_m": 90}}}}).front_end_digest(
        "uav") != d  # fmt: skip
    assert ShgmConfig.model_validate({"robots": {"car1": {"extraction": {"max_depth_m": 90}}}}).front_end_digest(
        "uav") == d  # fmt: skip
    assert ShgmConfig.model_validate({"matching": {"top_k": 5}}).front_end_digest("uav") == d
    assert ShgmConfig.model_validate({"odometry": {"kind": "gt", "icp_threads": 1}}).front_end_digest("uav") == d


def test_robot_values_merge_into_overrides_and_reload(tmp_path: Path) -> None:
    cfg = ShgmConfig.model_validate({"robots": {"uav": {"extraction": {"min_depth_m": 2.0}}}})
    merged = cfg.with_robot_values(
        {"uav": {"extraction": {"max_depth_m": 90.0}}, "car1": {"odometry": {"voxel_size_m": 1.5}}}
    )
    path = tmp_path / "c.yaml"
    path.write_text(merged.to_yaml())
    loaded = load_config(path)
    assert loaded.for_robot("uav").extraction.max_depth_m == 90.0
    assert loaded.for_robot("uav").extraction.min_depth_m == 2.0  # its own override kept
    assert loaded.for_robot("car1").odometry.voxel_size_m == 1.5
    assert loaded.for_robot("car2").model_dump(exclude={"robots"}) == ShgmConfig().model_dump(exclude={"robots"})


def test_a_written_config_names_the_same_files_from_any_working_folder(tmp_path: Path, monkeypatch) -> None:
    """A results folder's config.yaml kept the run's relative model and poses paths: given back with --config from
    another folder, the run was refused ("model file models/demo_depth.onnx does not exist")."""
    monkeypatch.chdir(tmp_path)
    cfg = ShgmConfig.model_validate({
        "perception": {"depth_model": "models/d.onnx", "seg_model": "models/s.onnx"},
        "odometry": {"kind": "file", "poses_file": "poses/{robot}.txt"},
        "robots": {"uav": {"perception": {"depth_model": "models/uav.onnx"}}},
    })  # fmt: skip
    path = tmp_path / "config.yaml"
    path.write_text(cfg.with_robot_values({"uav": {"odometry": {"voxel_size_m": 2.0}}}).to_yaml())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    loaded = load_config(path)
    assert loaded.perception.depth_model == tmp_path / "models" / "d.onnx"
    assert loaded.perception.seg_model == tmp_path / "models" / "s.onnx"
    assert loaded.odometry.poses_file == tmp_path / "poses" / "{robot}.txt"  # {robot} still replaced per robot
    assert loaded.for_robot("uav").perception.depth_model == tmp_path / "models" / "uav.onnx"
    assert loaded.for_robot("uav").odometry.voxel_size_m == 2.0
