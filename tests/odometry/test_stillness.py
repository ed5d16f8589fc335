"""Odometry that did not move while the images did is reported (log, summary, metrics.json), never "fused"."""

from __future__ import annotations

import json

import numpy as np

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.odometry.stillness import ImageChange, odometry_motion, stillness_warning
from shgm_slam.runner import open_robots, run_slam


def _images(n, moving):
    rng = np.random.default_rng(0)
    still = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) if moving else still for _ in range(n)]


def test_image_change_counts_changed_pairs():
    moving, still = ImageChange(), ImageChange()
    for a, b in zip(_images(6, True), _images(6, False), strict=True):
        moving.add(a)
        still.add(b)
    moving.add(None)
    assert (moving.pairs, moving.changed) == (5, 5)
    assert (still.pairs, still.changed) == (5, 0)


def test_odometry_motion_sums_steps_within_segments():
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = [0, 1, 2, 0, 1]
    T[2] = np.nan
    seg = np.array([0, 0, 0, 1, 1])
    path, rot = odometry_motion(T, seg)
    assert np.isclose(path, 2.0) and np.isclose(rot, 0.0)  # 0->1 and 3->4; the jump between segments is not a step


def test_still_odometry_with_moving_images_warns_only_then():
    moving = ImageChange()
    for image in _images(10, True):
        moving.add(image)
    assert "did not move" in stillness_warning(0.0, 0.0, moving)
    assert "check the depth" in stillness_warning(0.0, 0.0, moving)
    assert "check the T_odom_cam given" in stillness_warning(0.0, 0.0, moving, given=True)
    assert stillness_warning(5.0, 0.0, moving) is None
    still = ImageChange()
    for image in _images(10, False):
        still.add(image)
    assert stillness_warning(0.0, 0.0, still) is None


def test_run_reports_still_odometry_and_no_nodes(tiny_scenario, tmp_path):
    robots = open_robots([f"car={tiny_scenario / 'car1'}:0-16"])
    poses = tmp_path / "still.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 16)
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, poses
    cfg.extraction.labels = (16,)  # trains: none in the world, so no graph nodes
    summary = run_slam(robots, cfg, tmp_path / "out")
    (rep,) = summary.robots
    assert not rep.localized
    assert any("did not move" in w for w in rep.warnings) and any("no graph nodes" in w for w in rep.warnings)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["robots"][0]["localized"] is False
    assert any("did not move" in w for w in metrics["robots"][0]["warnings"])
