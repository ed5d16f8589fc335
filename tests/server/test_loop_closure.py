"""Intra-robot loop closure end to end: a robot that drives a loop with drifting odometry closes it from
its own semantic graph; a robot that never comes back gets no loop closure.

Worlds: ``kitti-paths`` grown around synthetic drives written as KITTI pose files (a rounded-rectangle
loop driven 1.4 times, and an open S-curve), rendered once per module at 320x96.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import write_kitti_poses
from shgm_slam.runner import open_robots, run_slam
from shgm_slam.sim.trajectories import arc_length, fillet_path, resample_path
from shgm_slam.viz.rerun_logger import NullLogger


class RecordingViz(NullLogger):
    """A viewer that remembers the matches and messages it was asked to show."""

    def __init__(self) -> None:
        self.matches: list[tuple[str, str, bool, int]] = []
        self.texts: list[str] = []

    def log_matches(self, robot_a, robot_b, positions_a, positions_b, accepted, num_inliers=None, score=None):
        assert positions_a.shape == positions_b.shape
        self.matches.append((robot_a, robot_b, accepted, num_inliers))

    def log_text(self, message, level="INFO"):
        self.texts.append(message)


def kitti_poses_along(path_xz: np.ndarray) -> np.ndarray:
    """(N, 4, 4) KITTI-convention camera poses (x right, y down, z forward; ground = x-z plane) along a path."""
    t = np.gradient(path_xz, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    z = np.stack([t[:, 0], np.zeros(len(t)), t[:, 1]], axis=1)
    y = np.tile([0.0, 1.0, 0.0], (len(t), 1))
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = np.cross(y, z), y, z
    T[:, 0, 3], T[:, 2, 3] = path_xz[:, 0], path_xz[:, 1]
    return T


def drifting_odometry(gt_poses: np.ndarray, yaw_deg_per_frame: float, scale: float) -> np.ndarray:
    """Odometry that drifts: every ground-truth step is scaled and turned about the camera's y (vertical) axis."""
    deltas = se3.inverse(gt_poses[:-1]) @ gt_poses[1:]
    deltas[:, :3, 3] *= scale
    deltas = se3.make_pose(se3.rot_y(np.radians(yaw_deg_per_frame)), np.zeros(3)) @ deltas
    out = [np.eye(4)]
    for d in deltas:
        out.append(out[-1] @ d)
    return np.stack(out)


def _render(root: Path, path_xz: np.ndarray, out: Path) -> Path:
    from shgm_slam.sim.simulate import simulate

    (root / "poses").mkdir(parents=True)
    T = kitti_poses_along(resample_path(path_xz, 1.0))
    np.savetxt(root / "poses" / "00.txt", T[:, :3, :].reshape(len(T), 12))
    simulate("kitti-paths", out, resolution=(320, 96), kitti_root=root, kitti_robots=("00",))
    return out / "kitti00"


@pytest.fixture(scope="module")
def loop_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ~260 m rounded rectangle driven 1.4 times (~360 frames, 1 m apart)."""
    tmp = tmp_path_factory.mktemp("loop")
    lap = np.array([[90.0, 0.0], [90.0, 50.0], [0.0, 50.0], [0.0, 0.0]])
    laps = fillet_path(np.vstack([[45.0, 0.0], lap, lap, [90.0, 0.0]]), radius_m=12.0)  # starts mid-edge
    return _render(tmp / "kitti", laps[arc_length(laps) <= 360.0], tmp / "world")


@pytest.fixture(scope="module")
def open_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An S-curve of ~330 m that never comes back."""
    tmp = tmp_path_factory.mktemp("open")
    corners = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 60.0], [200.0, 60.0], [200.0, 0.0], [260.0, 0.0]])
    return _render(tmp / "kitti", fillet_path(corners, radius_m=15.0), tmp / "world")


def _run(seq: Path, out: Path, *, loop_closure: bool = True, viz: NullLogger | None = None):
    robots = open_robots([f"car={seq}"])
    odo = drifting_odometry(robots["car"].gt_poses, 0.05, 1.01)
    write_kitti_poses(out.parent / f"{out.name}_odo.txt", odo)
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, out.parent / f"{out.name}_odo.txt"
    cfg.backend.loop_closure = loop_closure
    summary = run_slam(robots, cfg, out, viz=viz)
    return summary, json.loads((out / "matches.json").read_text())


def _loops(matches: list[dict]) -> list[dict]:
    return [m for m in matches if m["query"] == "loop"]


def test_a_drifting_loop_is_closed(loop_drive: Path, tmp_path: Path) -> None:
    viz = RecordingViz()
    summary, matches = _run(loop_drive, tmp_path / "out", viz=viz)
    (car,) = summary.robots
    loops = _loops(matches)
    accepted = [m for m in loops if m["accepted"]]
    assert accepted, [m["reason"] for m in loops]
    for m in loops:  # logged like inter-robot matches, between two keyframes of the same robot
        assert m["robot_a"] == m["robot_b"] == "car"
    for m in accepted:
        assert m["keyframe_a"] < m["keyframe_b"]
    # shown by the viewer like inter-robot matches
    assert ("car", "car", True, len(accepted[0]["inliers"])) in viz.matches
    assert any(t.startswith("car<->car (loop)") for t in viz.texts)
    # the loop pulls the drifted return back: the fused trajectory is clearly better than the odometry
    assert car.ate_fused_m < 0.6 * car.ate_odometry_m, car
    # its closures measured the odometry's heading drift (5 deg per 100 m, a random walk's rate above the prior)
    # and the results say so
    assert car.measured_drift_deg_per_100m is not None and car.measured_drift_deg_per_100m > 10.0, car
    assert any(t.startswith("car: its loop closures measure an odometry heading drift") for t in viz.texts)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["robots"][0]["measured_drift_deg_per_100m"] == pytest.approx(car.measured_drift_deg_per_100m)


def test_no_loop_closure_without_a_revisit(open_drive: Path, tmp_path: Path) -> None:
    summary, matches = _run(open_drive, tmp_path / "out")
    assert not [m for m in _loops(matches) if m["accepted"]]
    (car,) = summary.robots
    assert car.ate_fused_m <= car.ate_odometry_m + 0.05, car
    assert car.measured_drift_deg_per_100m is None  # no loop, nothing measured: the prior holds


def test_loop_closure_can_be_switched_off(loop_drive: Path, tmp_path: Path) -> None:
    _, matches = _run(loop_drive, tmp_path / "out", loop_closure=False)
    assert not _loops(matches)
