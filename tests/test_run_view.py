"""What run sends the viewer: changed stretches only, and together they draw the whole map."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.run_report import fused_poses
from shgm_slam.run_view import TRAJECTORY_CHUNK_FRAMES, RunView
from shgm_slam.runner import open_robots, run_slam
from shgm_slam.shared_frame import shared_frame_ground_truth
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


class FinalViz(ChunkViz):
    """``ChunkViz`` that also keeps the odometry stretches, the graph nodes' positions and every match drawn."""

    def __init__(self) -> None:
        super().__init__()
        self.odometry: dict[tuple[str, int], np.ndarray] = {}
        self.node_xyz: dict[tuple[str, int], dict[int, np.ndarray]] = {}
        self.matches: list[tuple] = []  # (robot_a, robot_b, positions_a, positions_b, accepted, each one's map then)
        self.server = None  # the run's map server, once it exists
        self.frame: dict[str, int] = {}  # robot -> the frame its time was last set to
        self.drawn: dict[tuple[str, int], np.ndarray] = {}  # (robot, frame) -> the camera position drawn
        self.errors: dict[tuple[str, int], float] = {}  # (robot, frame) -> the error series' value
        self.final_error: dict[str, float] = {}  # robot -> the error series' value at the end (``RunView.finish``)
        self.finishing = False  # ``RunView.finish`` runs

    def set_time(self, robot, frame_index, timestamp_s):
        self.frame[robot] = frame_index

    def log_frame(self, robot, T_shared_cam, image_rgb, depth_m, label_ids, points_shared=None, point_labels=None):
        self.drawn[(robot, self.frame[robot])] = np.asarray(T_shared_cam)[:3, 3].copy()

    def log_error(self, robot, error_m):
        if self.finishing:
            self.final_error[robot] = error_m
        else:
            self.errors[(robot, self.frame[robot])] = error_m

    def log_trajectories(self, robot, odometry_xyz, fused_xyz, chunk=0):
        super().log_trajectories(robot, odometry_xyz, fused_xyz, chunk)
        self.odometry[(robot, chunk)] = odometry_xyz

    def log_graph(self, robot, graph, chunk=0, drawn=None):
        super().log_graph(robot, graph, chunk, drawn)
        rows = np.arange(len(graph)) if drawn is None else np.flatnonzero(drawn)
        self.node_xyz[(robot, chunk)] = dict(zip(graph.node_ids[rows].tolist(), graph.positions_xyz[rows], strict=True))

    def clear_map(self, robot):
        super().clear_map(robot)
        for store in (self.odometry, self.node_xyz):
            for key in [k for k in store if k[0] == robot]:
                del store[key]

    def log_matches(self, robot_a, robot_b, positions_a, positions_b, accepted, num_inliers=None, score=None):
        maps = {r: self.server.graph(r) if self.server.shared_graph(r) is None else self.server.shared_graph(r)
                for r in (robot_a, robot_b)}  # fmt: skip
        self.matches.append((robot_a, robot_b, positions_a, positions_b, accepted, maps))


@pytest.fixture(scope="module")
def odometry_run(tiny_scenario: Path, tmp_path_factory):
    """A run of car1 and car2 with their own (drifting) odometry, drawn by a ``FinalViz``: (viz, view, server,
    fronts) as the run ended."""
    captured = {}
    original_finish = RunView.finish

    original_keyframe = RunView.keyframe

    def spy_keyframe(self, server, front, res):
        viz.server = server
        original_keyframe(self, server, front, res)

    def spy_finish(self, server, fronts):
        fronts = list(fronts)
        captured.update(view=self, server=server, fronts={f.name: f for f in fronts})
        viz.finishing = True
        original_finish(self, server, fronts)

    viz = FinalViz()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(RunView, "finish", spy_finish)
        mp.setattr(RunView, "keyframe", spy_keyframe)
        robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
        run_slam(robots, ShgmConfig(), tmp_path_factory.mktemp("odometry_run"), viz=viz)
    return viz, captured["view"], captured["server"], captured["fronts"]


def test_the_viewer_ends_on_the_fused_map_and_the_reference_odometry(odometry_run) -> None:
    """The graph was drawn moved by the latest keyframe's correction as one rigid body, not each node with its
    keyframe's as the fused map (``shared_graph_<robot>.json``): decimetres off after 100 m of drift. The
    reference robot's odometry line, in the shared frame = its odometry frame, was moved the same way, off its
    odometry file."""
    viz, _, server, fronts = odometry_run
    for name, front in fronts.items():
        agent = front.segment.agent
        drawn = {i: xyz for k, part in viz.node_xyz.items() if k[0] == name for i, xyz in part.items()}
        shared = server.shared_graph(agent)
        expected = server.graph(agent) if shared is None else shared
        assert sorted(drawn) == sorted(expected.node_ids.tolist())
        xyz = np.stack([drawn[i] for i in expected.node_ids.tolist()])
        assert np.abs(xyz - expected.positions_xyz).max() < 1e-4, name
    reference = fronts[server.reference]
    odometry = np.concatenate([viz.odometry[k] for k in sorted(k for k in viz.odometry if k[0] == reference.name)])
    posed = np.flatnonzero(reference.frame_segment == reference.segment.index)
    truth = reference.T_odom_cam[posed, :3, 3]  # <robot>_odometry_tum.txt
    d = np.linalg.norm(truth[:, None, :] - odometry[None, :, :], axis=2).min(axis=1)
    assert d.max() < 1e-4, d.max()


def test_matches_are_drawn_on_the_map(odometry_run) -> None:
    """Matches of robots not placed were never drawn (the airsim-like world's first 200 frames: 11 accepted, none
    in the viewer), and those of placed robots were moved by the latest correction as one rigid body: each end of
    a match's line is a node of that robot's map as the server held it then (the fused map, ``shared_graph``,
    when placed; else its graph in its own odometry frame)."""
    viz, _, server, _ = odometry_run
    assert len(viz.matches) == sum(m.success for m in server.matches)
    assert any(m[4] for m in viz.matches)
    for a, b, pa, pb, _, maps in viz.matches:
        for agent, ends in ((a, pa), (b, pb)):
            d = np.linalg.norm(ends[:, None, :] - maps[agent].positions_xyz[None, :, :], axis=2).min(axis=1)
            assert d.max() < 1e-4, (agent, d.max())


def test_a_robot_that_lost_its_place_keeps_no_fused_line(odometry_run, monkeypatch) -> None:
    """A robot placed during the run and not at its end kept the fused line of its former estimate."""
    recorded, recorded_view, server, fronts = odometry_run
    placed = [f.name for f in fronts.values() if recorded_view._robots[f.name].placed]
    assert placed and any(k[0] in placed for k in recorded.fused)
    viz = FinalViz()  # a copy of what was drawn, so the shared run's recording stays as the run left it
    viz.fused, viz.nodes = dict(recorded.fused), dict(recorded.nodes)
    view = RunView(viz)
    view._robots = copy.deepcopy(recorded_view._robots)
    monkeypatch.setattr(server, "is_placed", lambda agent: False)
    view.finish(server, fronts.values())
    assert not [k for k in viz.fused if k[0] in placed]


def test_the_error_series_is_each_placed_robots_distance_from_its_ground_truth(odometry_run, tiny_scenario) -> None:
    """The viewer's metrics panel stayed empty: nothing logged to it. Every frame of a robot drawn in the shared
    frame now gives its distance from the ground truth there; frames of a robot not placed yet give none."""
    viz, _, _, fronts = odometry_run
    truth = shared_frame_ground_truth(open_robots([f"{r}={tiny_scenario / r}" for r in fronts]))
    assert viz.errors
    for (robot, frame), error in viz.errors.items():
        assert error == pytest.approx(np.linalg.norm(viz.drawn[(robot, frame)] - truth[robot][frame, :3, 3]))
    reference = next(iter(fronts))
    assert viz.errors[(reference, 0)] < 1e-6  # its first camera frame is the shared frame
    for name in fronts:
        frames = sorted(f for r, f in viz.drawn if r == name)
        measured = [f for f in frames if (name, f) in viz.errors]
        if name == reference:
            assert measured == frames
            continue
        # the others from the frame they were first drawn in the shared frame on (placed), or not at all
        assert measured == frames[len(frames) - len(measured):]
    assert not viz.final_error  # the series is the live estimate's (``finish`` adds no value at the timeline's end)
