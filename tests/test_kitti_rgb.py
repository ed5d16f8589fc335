"""The KITTI RGB-only path end to end: real KITTI frames -> demo ONNX depth + labels -> the whole system.

Plumbing, not accuracy: the demo models are trained on the synthetic world only.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shgm_slam.config import ShgmConfig
from shgm_slam.demo import MODELS_DIR
from shgm_slam.runner import open_robots, run_slam


def test_kitti_sequence_split_into_two_robots_runs_rgb_only(shared_data: Path, tmp_path: Path) -> None:
    depth, seg = MODELS_DIR / "demo_depth.onnx", MODELS_DIR / "demo_seg.onnx"
    if not (depth.is_file() and seg.is_file()):
        pytest.skip("demo models are absent (train them with tools/train_demo_models.py)")
    seq = shared_data / "kitti" / "sequences" / "07"
    robots = open_robots([f"a={seq}:0-25", f"b={seq}:25-50"])
    cfg = ShgmConfig()
    cfg.perception.depth_model, cfg.perception.seg_model = depth, seg
    summary = run_slam(robots, cfg, tmp_path / "out")
    reports = {r.name: r for r in summary.robots}
    assert reports["a"].frames_processed == 25 and reports["b"].frames_processed == 25
    assert reports["a"].keyframes >= 2
    # a car on a real road: the visual odometry takes most steps from the road's image motion
    assert reports["a"].road_step_share is not None and reports["a"].road_step_share > 0.5
    assert reports["a"].planar_turn_share is not None
    assert reports["a"].levelled_share is None  # the horizon is in view: its tilt is not held to the ground
    assert any(k.startswith("perception") for k in summary.timings_ms)  # model inference was timed
    # ground truth of KITTI is found, so the odometry is evaluated
    assert reports["a"].path_length_m > 2.0
    assert (tmp_path / "out" / "a_odometry_tum.txt").is_file()
    assert json.loads((tmp_path / "out" / "graph_a.json").read_text())["format"] == "shgm-graph/1"
