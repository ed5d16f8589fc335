"""What run sends the viewer: changed stretches only, and together they draw the whole map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.run_report import fused_poses
from shgm_slam.run_view import TRAJECTORY_CHUNK_FRAMES, RunView
from shgm_slam.runner import open_robots, run_slam
from shgm_slam.viz.rerun_logger import NullLogger


class ChunkViz(NullLogger):
    """Keeps the latest stretch of every trajectory and graph chunk, and counts what was sent per call."""

    enabled = True

    def __init__(self) -> None:
        self.fused: dict[tuple[str, int], np.ndarray] = {}
        self.nodes: dict[tuple[str, int], np.ndarray] = {}
        self.sent = 0  # trajectory positions sent so far

    def log_trajectories(self, robot, odometry_xyz, fused_xyz, chunk=0):
        if fused_xyz is not None:
            self.fused[(robot, chunk)] = fused_xyz
        self.sent += len(odometry_xyz)

    def log_graph(self, robot, graph, chunk=0, drawn=None):
        self.nodes[(robot, chunk)] = graph.node_ids[drawn] if drawn is not None else graph.node_ids

    def clear_map(self, robot):
        for store in (self.fused, self.nodes):
            for key in [k for k in store if k[0] == robot]:
                del store[key]


def test_stretches_draw_the_whole_trajectory_and_graph(tiny_scenario: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr("shgm_slam.run_view.TRAJECTORY_CHUNK_FRAMES", 40)
    monkeypatch.setattr("shgm_slam.run_view.GRAPH_CHUNK_KEYFRAMES", 10)
    captured = {}
    original = RunView.keyframe

    def spy(self, server, front, res):
        captured["server"], captured.setdefault("fronts", {})[front.name] = server, front
        before, corrections = viz.sent, server.corrections
        original(self, server, front, res)
        per_keyframe.append((viz.sent - before, corrections != captured.get("corrections", corrections)))
        placed_in_run.update(a for a in server.agents if server.is_placed(a))
        captured["corrections"] = corrections

    per_keyframe: list[tuple[int, bool]] = []
    placed_in_run: set[str] = set()
    original_finish = RunView.finish

    def spy_finish(self, server, fronts):
        captured["before_finish"] = dict(viz.fused)  # what the keyframes drew
        original_finish(self, server, fronts)

    monkeypatch.setattr(RunView, "keyframe", spy)
    monkeypatch.setattr(RunView, "finish", spy_finish)
    viz = ChunkViz()
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    run_slam(robots, cfg, tmp_path / "out", viz=viz)
    server = captured["server"]
    for name, front in captured["fronts"].items():
        fused = fused_poses(front, server)
        if fused is None:
            continue
        last_kf_frame = front.segments[-1].kf_frames[-1]
        truth = fused[: last_kf_frame + 1, :3, 3]
        truth = truth[np.isfinite(truth).all(axis=1)]
        kept = captured["before_finish"]
        stretches = [kept[k] for k in sorted(k for k in kept if k[0] == name)]
        # a robot placed only by the final matching has nothing drawn before the end
        assert bool(stretches) == (name in placed_in_run), name
        if stretches:
            # during the run every fused position is drawn (chunks overlap by one frame), each close to the final
            # estimate (the stretches are those of the last correction; the keyframes after it and the final
            # convergence move a robot by centimetres to decimetres) ...
            drawn = np.concatenate(stretches)
            d = np.linalg.norm(truth[:, None, :] - drawn[None, :, :], axis=2).min(axis=1)
            assert d.max() < 0.5, (name, d.max())
        # ... and the run ends by drawing exactly the final estimate
        final = np.concatenate([viz.fused[k] for k in sorted(k for k in viz.fused if k[0] == name)])
        d = np.linalg.norm(truth[:, None, :] - final[None, :, :], axis=2).min(axis=1)
        assert d.max() < 1e-6, (name, d.max())
        nodes = np.concatenate([viz.nodes[k] for k in viz.nodes if k[0] == name])
        assert sorted(nodes.tolist()) == sorted(server.graph(front.segments[-1].agent).node_ids.tolist())
    # between corrections a keyframe sends at most the two latest stretches, however long the trajectory
    quiet = [n for n, corrected in per_keyframe if not corrected]
    assert quiet and max(quiet) <= 2 * (40 + 1)


def test_default_stretch_is_a_few_hundred_frames():
    assert 50 <= TRAJECTORY_CHUNK_FRAMES <= 1000
