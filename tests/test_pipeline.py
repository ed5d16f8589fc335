"""End-to-end tests of the multi-robot system (front ends, map server, pose graph, results folder)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.data.interleave import interleave
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.fusion import fuse_frames
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import read_comments, read_kitti_poses, read_tum, write_kitti_poses
from shgm_slam.robot.keyframes import KeyframeSelector
from shgm_slam.runner import open_robots, parse_robot_arg, run_slam


def drifting_odometry(gt_poses: np.ndarray, yaw_deg_per_frame: float, scale: float) -> np.ndarray:
    """Odometry that drifts: every ground-truth step is scaled and turned about the camera's y (vertical) axis."""
    deltas = se3.inverse(gt_poses[:-1]) @ gt_poses[1:]
    deltas[:, :3, 3] *= scale
    deltas = se3.make_pose(se3.rot_y(np.radians(yaw_deg_per_frame)), np.zeros(3)) @ deltas
    out = [np.eye(4)]
    for d in deltas:
        out.append(out[-1] @ d)
    return np.stack(out)


@pytest.fixture(scope="module")
def drifting_run(tiny_scenario: Path, tmp_path_factory: pytest.TempPathFactory):
    """car1 and car2 of the tiny world with drifting odometry read from per-robot pose files."""
    tmp = tmp_path_factory.mktemp("drift")
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    for name, seq in robots.items():
        write_kitti_poses(tmp / f"odo_{name}.txt", drifting_odometry(seq.gt_poses, 0.03, 1.01))
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, tmp / "odo_{robot}.txt"
    cfg.backend.match_every_keyframes = 3  # car2 meets car1 once, briefly: two independent matches to enter
    # ... on one straight street: with stretches tracked every match there is one piece of evidence
    # (backend/stretches.py); this run is about fusion, so matches count by their objects
    cfg.backend.stretch_turn_deg = None
    out = tmp / "out"
    summary = run_slam(robots, cfg, out)
    return summary, robots, out


def test_two_robots_are_fused_and_beat_odometry(drifting_run) -> None:
    summary, _, _ = drifting_run
    reports = {r.name: r for r in summary.robots}
    assert summary.closures_accepted >= 1
    assert reports["car2"].localized
    car1, car2 = reports["car1"], reports["car2"]
    # car2 is placed in car1's frame from graph matches alone (no alignment): within 2 m
    assert car2.ate_fused_m < 2.0, car2
    # the reference robot is not bent by the closures, and fusion does not hurt either robot's shape
    assert car1.ate_fused_m <= car1.ate_odometry_m + 0.05, car1
    for r in (car1, car2):
        assert r.ate_fused_aligned_m <= 1.1 * r.ate_odometry_aligned_m, r
    # one SE(3) fit of both together can only remove error from the shared frame's (the identity is one fit)
    assert 0.0 < summary.ate_joint_m <= max(car1.ate_fused_m, car2.ate_fused_m) + 1e-9
    assert np.isfinite(car1.ate_fused_joint_m) and np.isfinite(car2.ate_fused_joint_m)


def test_the_fused_map_puts_the_objects_both_robots_matched_in_one_place(drifting_run) -> None:
    """``shared_graph_<robot>.json``: each placed robot's graph in the shared frame, every node moved with the keyframe
    it is anchored to. The accepted matches' partner objects then lie together in the fused map about as closely as
    under each match's own alignment (centroid noise and the viewpoint's offset of a centroid: their floor), and
    nowhere near as far apart as in the two robots' own odometry frames."""
    from shgm_slam.io.graph_json import read_graph

    summary, _, out = drifting_run
    assert summary.robots[1].localized
    shared = {name: read_graph(out / f"shared_graph_{name}.json") for name in ("car1", "car2")}
    own = {name: read_graph(out / f"graph_{name}.json") for name in ("car1", "car2")}
    for name in shared:
        np.testing.assert_array_equal(shared[name].node_ids, own[name].node_ids)
        np.testing.assert_array_equal(shared[name].label_ids, own[name].label_ids)
    fused = {name: dict(zip(g.node_ids.tolist(), g.positions_xyz, strict=True)) for name, g in shared.items()}
    odom = {name: dict(zip(g.node_ids.tolist(), g.positions_xyz, strict=True)) for name, g in own.items()}
    gaps, floor, apart = [], [], []
    for m in json.loads((out / "matches.json").read_text()):
        if not m["accepted"] or m["robot_a"] == m["robot_b"]:
            continue
        T = np.array(m["T_a_b"])
        for a, b in m["inliers"]:
            pa, pb = odom[m["robot_a"]][a], odom[m["robot_b"]][b]
            gaps.append(np.linalg.norm(fused[m["robot_a"]][a] - fused[m["robot_b"]][b]))
            floor.append(np.linalg.norm(pa - (T[:3, :3] @ pb + T[:3, 3])))
            apart.append(np.linalg.norm(pa - pb))
    assert len(gaps) >= 10
    assert np.median(gaps) < np.median(floor) + 0.5, (np.median(gaps), np.median(floor))
    assert np.median(gaps) < 0.2 * np.median(apart)


def test_results_folder_has_every_output(drifting_run) -> None:
    summary, robots, out = drifting_run
    for name, seq in robots.items():
        t, _ = read_tum(out / f"{name}_fused_tum.txt")
        assert len(t) == len(seq)
        assert len(read_kitti_poses(out / f"{name}_fused_kitti.txt")) == len(seq)
        assert (out / f"{name}_odometry_tum.txt").is_file()
        graph = json.loads((out / f"graph_{name}.json").read_text())
        assert graph["format"] == "shgm-graph/1" and graph["nodes"]
    matches = json.loads((out / "matches.json").read_text())
    assert len(matches) == summary.matches_tried
    assert {"robot_a", "robot_b", "T_a_b", "inliers", "accepted", "reason"} <= set(matches[0])
    assert "VERTEX_SE3:QUAT" in (out / "pose_graph.g2o").read_text()
    assert "extraction:" in (out / "config.yaml").read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["closures_accepted"] == summary.closures_accepted
    (pair,) = metrics["pairs"]  # how the matches between car1 and car2 went
    assert pair["robots"] == ["car1", "car2"] and pair["tried"] == summary.matches_tried - sum(
        m["robot_a"] == m["robot_b"] for m in matches)  # fmt: skip
    assert pair["accepted"] == sum(m["accepted"] for m in matches if m["robot_a"] != m["robot_b"]) > 0
    rejected = [m["evidence"] for m in matches if not m["success"] and m["evidence"] is not None]
    if rejected:  # the closest rejection, in nats from the threshold
        best = max(e["llr"] - e["llr_threshold"] for e in rejected if e["llr"] is not None)
        assert pair["closest_margin_nats"] == pytest.approx(best, abs=0.01)
    for r in metrics["robots"]:  # which odometry ran, and why
        assert r["odometry"] == "file" and r["odometry_reason"] == "set in the configuration"
        assert r["planar_turn_share"] is None  # reported for the visual odometry only
        assert r["road_step_share"] is None and r["levelled_share"] is None


def test_fused_car2_is_in_car1_frame(drifting_run) -> None:
    """The recovered inter-robot transform: car2's fused start pose matches its true pose in car1's frame."""
    _, robots, out = drifting_run
    _, fused = read_tum(out / "car2_fused_tum.txt")
    gt1, gt2 = robots["car1"].gt_poses, robots["car2"].gt_poses
    T_true = se3.inverse(gt1[0]) @ gt2
    t_err, r_err = se3.pose_error(fused, T_true)
    assert np.median(t_err) < 3.0
    assert np.median(r_err) < 5.0


def test_disjoint_robots_merge_nothing(tmp_path: Path) -> None:
    from shgm_slam.sim.simulate import simulate

    world = tmp_path / "disjoint"
    simulate("disjoint", world, resolution=(320, 96), fps=4.0, compact=True, max_frames=40)
    robots = open_robots([f"{p.name}={p}" for p in sorted(world.iterdir()) if (p / "times.txt").is_file()])
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    cfg.backend.match_every_keyframes = 5
    summary = run_slam(robots, cfg, tmp_path / "out")
    assert summary.matches_tried > 0
    assert summary.closures_accepted == 0
    assert [r.localized for r in summary.robots] == [True, False]
    names = [r.name for r in summary.robots]
    assert not (tmp_path / "out" / f"{names[1]}_fused_tum.txt").exists()


def test_corrupt_frame_is_skipped_and_results_are_written(tiny_scenario: Path, tmp_path: Path) -> None:
    seq_dir = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq_dir)
    (seq_dir / "depth" / "000010.png").write_bytes(b"not a png")
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    summary = run_slam(open_robots([f"car1={seq_dir}"]), cfg, tmp_path / "out")
    assert summary.robots[0].frames_skipped == 1
    assert "000010.png" in summary.skipped_reasons[0]
    t, _ = read_tum(tmp_path / "out" / "car1_odometry_tum.txt")
    assert len(t) == len(open_sequence(seq_dir)) - 1


def test_interrupted_run_keeps_what_it_has(tiny_scenario: Path, tmp_path: Path) -> None:
    def stop_at_30(done: int, total: int) -> None:
        if done == 30:
            raise KeyboardInterrupt

    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    summary = run_slam(robots, cfg, tmp_path / "out", progress=stop_at_30)
    assert summary.interrupted
    t, _ = read_tum(tmp_path / "out" / "car1_odometry_tum.txt")
    assert 10 <= len(t) < len(robots["car1"])
    assert (tmp_path / "out" / "metrics.json").is_file()
    # the frames never reached are said so, not called skipped (the old warning: "289 of 300 frames skipped")
    for rep in summary.robots:
        assert rep.frames_skipped == 0 and rep.frames_processed + rep.frames_not_reached == rep.frames
        assert rep.frames_not_reached > 0 and any("were not run" in w for w in rep.warnings)
    from shgm_slam.evaluation import evaluate_results

    result = evaluate_results(tmp_path / "out")
    assert result.interrupted and "were not run" in result.robots[0].note


def test_a_second_stop_while_writing_marks_the_folder_incomplete(tiny_scenario: Path, tmp_path: Path, monkeypatch):
    """A second Ctrl-C while the results were written left a folder without metrics.json and no marker."""
    from shgm_slam.errors import DataError
    from shgm_slam.evaluation import evaluate_results
    from shgm_slam.io.export import ResultsWriter

    real = ResultsWriter.write_json

    def stopped_at_metrics(self, name, data, **kwargs):
        if name == "metrics.json":
            raise KeyboardInterrupt
        return real(self, name, data, **kwargs)

    monkeypatch.setattr(ResultsWriter, "write_json", stopped_at_metrics)
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}:0-20", f"car2={tiny_scenario / 'car2'}:0-20"])
    with pytest.raises(KeyboardInterrupt):
        run_slam(robots, cfg, tmp_path / "out")
    assert "stopped while its results were being written" in (tmp_path / "out" / "incomplete.txt").read_text()
    with pytest.raises(DataError, match="holds no results"):
        evaluate_results(tmp_path / "out")


def test_results_are_checkpointed_during_the_run(tiny_scenario: Path, tmp_path: Path) -> None:
    """Every ``write_every_keyframes`` keyframes the results folder is rewritten, long before the end."""
    out = tmp_path / "out"
    seen: list[int] = []

    def watch(done: int, total: int) -> None:
        if (out / "server.json").is_file() and not seen:
            seen.append(done)

    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    total = sum(len(s) for s in robots.values())
    run_slam(robots, cfg, out, progress=watch, write_every_keyframes=10)
    assert seen and seen[0] < total / 2, seen  # the first checkpoint came early
    for name in ("car1_odometry_tum.txt", "graph_car1.json", "matches.json", "pose_graph.g2o"):
        assert (out / name).is_file()


def test_a_full_disk_mid_run_keeps_the_last_complete_checkpoint(tiny_scenario: Path, tmp_path: Path, monkeypatch):
    """The second checkpoint fails half way (disk full): the run stops with a DataError and the folder holds
    the first checkpoint, whole (its files agree with each other) and without temporaries."""
    import errno

    from shgm_slam.io import export
    from shgm_slam.server.node import ServerNode

    out = tmp_path / "out"
    real_write = ServerNode.write_results
    calls = []

    def write_results(self):
        calls.append(1)
        if len(calls) == 2:  # the graphs come after the trajectories: the checkpoint is half written
            def full(*_args, **_kwargs):
                raise OSError(errno.ENOSPC, "No space left on device")

            monkeypatch.setattr(export, "write_graph", full)
        return real_write(self)

    monkeypatch.setattr(ServerNode, "write_results", write_results)
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    with pytest.raises(DataError, match="No space left on device"):
        run_slam(robots, cfg, out, write_every_keyframes=10)
    assert len(calls) == 2
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporaries
    server = json.loads((out / "server.json").read_text())
    assert server["matches_tried"] == len(json.loads((out / "matches.json").read_text()))
    t, _ = read_tum(out / "car1_odometry_tum.txt")  # keyframe-rate checkpoint of the first write
    assert len(t) == server["robots"]["car1"]["keyframes"]


def test_a_run_that_fails_mid_way_marks_its_folder_incomplete(tiny_scenario: Path, tmp_path: Path, monkeypatch):
    """An error after the first checkpoint: the folder says so (incomplete.txt), eval refuses it, and the next
    run into it needs --overwrite, which clears the marker too."""
    from shgm_slam.errors import BackendError
    from shgm_slam.evaluation import evaluate_results
    from shgm_slam.io.export import make_results_dir
    from shgm_slam.server.node import ServerNode

    out = tmp_path / "out"
    real_write = ServerNode.write_results
    calls = []

    def write_results(self):
        calls.append(1)
        if len(calls) == 2:
            raise BackendError("the pose graph failed")
        return real_write(self)

    monkeypatch.setattr(ServerNode, "write_results", write_results)
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    with pytest.raises(BackendError, match="the pose graph failed"):
        run_slam(robots, cfg, out, write_every_keyframes=10)
    assert (out / "car1_odometry_tum.txt").is_file() and not (out / "metrics.json").exists()
    assert "BackendError: the pose graph failed" in (out / "incomplete.txt").read_text()
    with pytest.raises(DataError, match="holds no results: its run ended with an error"):
        evaluate_results(out)
    with pytest.raises(DataError, match="earlier run's results"):
        make_results_dir(out)
    make_results_dir(out, overwrite=True)
    assert not (out / "incomplete.txt").exists()


def test_more_robots_than_the_pose_graph_holds_are_refused_before_anything_is_written(tiny_scenario, tmp_path):
    from typer.testing import CliRunner

    from shgm_slam.cli import app

    args = [a for i in range(53) for a in ("--robot", f"r{i}={tiny_scenario / 'car1'}:0-3")]
    res = CliRunner().invoke(app, ["run", *args, "--rerun", "off", "--out", str(tmp_path / "out")])
    assert res.exit_code == 2, res.output
    assert "53 robots: the pose graph holds at most 52 agents" in " ".join(res.output.split())
    assert not (tmp_path / "out").exists()


def test_a_robot_whose_odometry_fails_on_every_frame_stops_and_the_run_goes_on(tiny_scenario, tmp_path) -> None:
    """car2's odometry jumps 30 m every frame: it stops after its share of the pose graph's agents (26 of 52
    for two robots) instead of ending the run when they run out; car1's results are written as usual."""
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    odo = np.tile(np.eye(4), (len(robots["car2"]), 1, 1))
    odo[:, 0, 3] = 30.0 * np.arange(len(odo))
    write_kitti_poses(tmp_path / "odo_car2.txt", odo)
    cfg = ShgmConfig.model_validate({"robots": {"car2": {"odometry": {
        "kind": "file", "poses_file": str(tmp_path / "odo_car2.txt")}}}})  # fmt: skip
    cfg.odometry.kind = OdometryKind.GT
    summary = run_slam(robots, cfg, tmp_path / "out")
    car1, car2 = summary.robots
    assert car1.localized and car1.odometry_failures == 0
    assert car2.segments == 26 and car2.odometry_failures == 26 and not car2.localized
    assert car2.frames_dropped == len(robots["car2"]) - 26
    stop = [w for w in car2.warnings if w.startswith("stopped at frame 26")]
    assert stop and "share of the pose graph's 52 agents in a run of 2 robots" in stop[0]
    still = [w for w in car2.warnings if "did not move" in w]  # true of its one-frame segments, not of the rest
    assert still and "in 25 of 25 consecutive frames" in still[0]
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["robots"][1]["warnings"] == car2.warnings
    assert (tmp_path / "out" / "car1_fused_tum.txt").is_file()


def test_results_inside_a_robots_sequence_folder_are_refused(tiny_scenario: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from shgm_slam.cli import app
    from shgm_slam.runner import check_out_outside_sequences

    seq = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq)
    before = sorted(p.relative_to(seq) for p in seq.rglob("*"))
    for out in (seq, seq / "image_2", seq / "new" / "deeper"):
        res = CliRunner().invoke(app, ["run", "--robot", f"car1={seq}:0-5", "--rerun", "off", "--out", str(out)])
        assert res.exit_code == 2, res.output
        assert "is in the sequence folder of robot 'car1'" in " ".join(res.output.split())  # (wrapped lines)
    assert sorted(p.relative_to(seq) for p in seq.rglob("*")) == before  # nothing written into it
    check_out_outside_sequences(tmp_path / "out", open_robots([f"car1={seq}:0-5"]))  # beside it is fine
    check_out_outside_sequences(tmp_path / "car10", open_robots([f"car1={seq}"]))  # a name that only starts the same
    with pytest.raises(ConfigError, match="is in the sequence folder of robot 'car1'"):  # a view of it too
        check_out_outside_sequences(seq / "out", open_robots([f"car1={seq}:2-5"]))


def test_bad_robot_arguments_give_clear_errors(tiny_scenario: Path, tmp_path: Path) -> None:
    assert parse_robot_arg("car1=/data/seq:0-10") == ("car1", "/data/seq:0-10")
    with pytest.raises(ConfigError, match="NAME=PATH"):
        parse_robot_arg("/data/seq")
    with pytest.raises(ConfigError, match="twice"):
        open_robots([f"a={tiny_scenario / 'car1'}", f"a={tiny_scenario / 'car2'}"])
    with pytest.raises(ConfigError, match="no robots"):
        open_robots([])
    with pytest.raises(DataError):
        open_robots([f"a={tiny_scenario / 'car1'}:5-5"])
    with pytest.raises(DataError):
        open_robots([f"a={tmp_path / 'missing'}"])


def test_pose_file_with_wrong_count_is_a_clear_error(tiny_scenario: Path, tmp_path: Path) -> None:
    seq = open_sequence(tiny_scenario / "car1")
    write_kitti_poses(tmp_path / "short.txt", seq.gt_poses[:5])
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, tmp_path / "short.txt"
    with pytest.raises(DataError, match=r"short\.txt"):
        run_slam({"car1": seq}, cfg, tmp_path / "out")


def test_keyframe_selector_distance_and_angle() -> None:
    sel = KeyframeSelector(distance_m=2.0, angle_deg=15.0)
    assert sel.is_keyframe(np.eye(4))
    assert not sel.is_keyframe(se3.make_pose(np.eye(3), [0, 0, 1.5]))
    assert sel.is_keyframe(se3.make_pose(np.eye(3), [0, 0, 2.5]))
    assert sel.is_keyframe(se3.make_pose(se3.rot_y(np.radians(20)), [0, 0, 2.5]))


def test_fuse_frames_rides_on_keyframe_corrections() -> None:
    T_odom = np.stack([se3.make_pose(np.eye(3), [0, 0, i]) for i in range(6)])
    frame_kf = np.array([0, 0, 0, 1, 1, 1])
    T_odom_kf = T_odom[[0, 3]]
    correction = se3.make_pose(se3.rot_y(0.3), [5.0, 0, 0])
    fused = fuse_frames(T_odom, frame_kf, T_odom_kf, correction @ T_odom_kf)
    np.testing.assert_allclose(fused, correction @ T_odom, atol=1e-12)


def test_interleave_orders_robots_by_time() -> None:
    class Seq:
        def __init__(self, t):
            self.timestamps_s = np.asarray(t, dtype=float)

        def __len__(self):
            return len(self.timestamps_s)

    order = list(interleave({"a": Seq([100.0, 100.2, 100.4]), "b": Seq([0.0, 0.1, 0.3])}))
    assert order == [("a", 0), ("b", 0), ("b", 1), ("a", 1), ("b", 2), ("a", 2)]
    # equal times: the first robot (the reference), then the others by name, as the map server orders them
    ties = list(interleave({"m": Seq([0.0, 1.0]), "z": Seq([5.0, 6.0]), "a": Seq([0.0, 1.0])}))
    assert ties == [("m", 0), ("a", 0), ("z", 0), ("m", 1), ("a", 1), ("z", 1)]


def test_saved_recording_holds_the_run(tiny_scenario: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    from shgm_slam.viz.rerun_logger import RerunMode, make_viz

    robots = open_robots([f"car1={tiny_scenario / 'car1'}:0-20", f"car2={tiny_scenario / 'car2'}:0-20"])
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    rrd = tmp_path / "run.rrd"
    viz = make_viz(RerunMode.SAVE, robots=list(robots), save_path=rrd)
    run_slam(robots, cfg, tmp_path / "out", viz=viz)
    chunks = RrdReader(str(rrd)).stream().to_chunks()
    paths = {c.entity_path for c in chunks}
    for robot in robots:
        for suffix in ("cam", "cam/rgb", "cam/depth", "cam/seg"):
            assert any(p.startswith(f"/world/{robot}") and p.endswith(suffix) for p in paths), (robot, suffix)
        assert any(p.startswith(f"/timings/{robot}") for p in paths)
        assert any("graph" in p and robot in p for p in paths)
        assert any("traj" in p and robot in p for p in paths)
    columns = {f for c in chunks if c.entity_path.endswith("cam/rgb") for f in c.to_record_batch().schema.names}
    assert "frame" in columns


# --------------------------------------------------------------------------------------------------
# Early stop: a robot placed from a single piece of evidence is provisional in every output
# --------------------------------------------------------------------------------------------------


class RecordingViz:
    """A viewer that records every call (the log panel's lines in ``texts``)."""

    enabled = True
    max_cloud_points = 20_000

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple]] = []

    @property
    def texts(self) -> list[tuple[str, str]]:
        return [(args[0], str(args[1]) if len(args) > 1 else "INFO") for name, args in self.calls if name == "log_text"]

    def __getattr__(self, name):
        return lambda *args, **kwargs: self.calls.append((name, args))


@pytest.fixture(scope="module")
def early_stop(tiny_scenario: Path, tmp_path_factory: pytest.TempPathFactory):
    """car2 stopped after 30 frames: every match it got found the same objects of car1 (ground-truth
    odometry, so the run is deterministic); and the full run, where later matches confirm it. The map
    server trusts single matches here (``min_closures_to_anchor: 1``; the default waits for two), the
    setting whose early stop the provisional flag guards."""
    trusting = ShgmConfig()
    trusting.odometry.kind = OdometryKind.GT
    trusting.backend.min_closures_to_anchor = 1
    trusting.backend.stretch_turn_deg = None  # the cars meet on one straight street: confirmed by objects alone
    default = ShgmConfig()
    default.odometry.kind = OdometryKind.GT
    runs = {}
    for name, car2, cfg in (("early", ":0-30", trusting), ("full", "", trusting), ("early_default", ":0-30", default)):
        out = tmp_path_factory.mktemp(name)
        viz = RecordingViz()
        robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}{car2}"])
        runs[name] = (run_slam(robots, cfg, out, viz=viz), out, viz)
    return runs


def test_early_stop_with_the_default_leaves_the_robot_out_and_says_why(early_stop) -> None:
    """Its matches all found the same objects: one piece of evidence, so with the default (two independent
    matches) car2 is not placed; the summary, metrics.json and server.json say why."""
    summary, out, _ = early_stop["early_default"]
    car1, car2 = summary.robots
    assert not car2.localized and not car2.provisional and car1.localized
    assert summary.closures_accepted >= 1  # matches were accepted: a plain "never met" would be wrong
    why = [w for w in car2.warnings if w.startswith("car2 is not placed in the shared frame")]
    assert len(why) == 1 and "with car1 are one piece of evidence (here: matches that found the same objects" in why[0]
    assert "min_closures_to_anchor" in why[0]
    assert json.loads((out / "metrics.json").read_text())["robots"][1]["warnings"] == car2.warnings
    server = json.loads((out / "server.json").read_text())
    assert server["robots"]["car2"]["placed"] == [] and server["robots"]["car2"]["waiting"] == why
    # the last look on the objects its matches did not use found no second match, and says why
    look, *partner = summary.last_looks  # car1's look too when car2's lay on its earlier queries' stretches
    assert look.startswith("car2: a last look with car1") and "did not confirm it: " in look
    assert all(p.startswith("car2: car1's last look at it") and "did not confirm it: " in p for p in partner)
    assert len(partner) <= 1
    assert json.loads((out / "metrics.json").read_text())["last_looks"] == summary.last_looks == server["last_looks"]
    assert server["robots"]["car1"]["waiting"] == []
    assert not (out / "car2_fused_tum.txt").exists()


def test_early_stop_leaves_a_provisional_robot_and_every_output_says_so(early_stop) -> None:
    from typer.testing import CliRunner

    from shgm_slam.cli import app
    from shgm_slam.evaluation import evaluate_results

    summary, out, viz = early_stop["early"]
    car1, car2 = summary.robots
    assert car2.localized and car2.provisional and not car1.provisional
    assert any(w.startswith("car2 is placed provisionally") for w in car2.warnings)
    metrics = json.loads((out / "metrics.json").read_text())
    assert [r["provisional"] for r in metrics["robots"]] == [False, True]
    assert any("provisionally" in w for w in metrics["robots"][1]["warnings"])
    server = json.loads((out / "server.json").read_text())
    assert server["robots"]["car2"]["provisional"] == ["car2"] and server["robots"]["car1"]["provisional"] == []
    assert [(a["agent"], a["confirmed"]) for a in server["anchorings"]] == [("car2", False)]
    # written, but never silently certain: the TUM file says so in a comment line; the KITTI file stays
    # plain 12-number rows (KITTI tools do not skip comments), metrics.json and server.json say it instead
    assert read_comments(out / "car2_fused_tum.txt")[0].startswith("provisional: car2 is placed provisionally")
    assert read_comments(out / "car2_fused_kitti.txt") == []
    assert read_comments(out / "car1_fused_tum.txt") == []
    warned = [t for t, level in viz.texts if level == "WARN" and t.startswith("car2 is placed provisionally")]
    assert warned, viz.texts  # the viewer's log panel, when it happened
    evaluation = {r.name: r for r in evaluate_results(out).robots}
    assert evaluation["car2"].provisional and "provisional" in evaluation["car2"].note
    assert not evaluation["car1"].provisional
    res = CliRunner().invoke(app, ["eval", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert [r["provisional"] for r in json.loads(res.output)["robots"]] == [False, True]


def test_a_later_independent_match_confirms_the_robot(early_stop) -> None:
    summary, out, viz = early_stop["full"]
    assert [r.provisional for r in summary.robots] == [False, False] and summary.robots[1].localized
    server = json.loads((out / "server.json").read_text())
    assert server["robots"]["car2"]["provisional"] == []
    # car2 entered the shared frame through a closure of car1's, and its place was confirmed on it
    anchoring = [a for a in server["anchorings"] if a["agent"] == "car2"]
    assert anchoring and anchoring[-1]["confirmed"] and not anchoring[-1]["withdrawn"]
    assert {anchoring[-1]["robot_a"], anchoring[-1]["robot_b"]} == {"car1", "car2"}
    said = [(t.split(" is ")[1].split()[0], level) for t, level in viz.texts if t.startswith("car2 is ")]
    # confirmed, said once; provisional first (once) when the round that placed it had a single match, not
    # when two independent matches came in the same round
    assert said in ([("placed", "WARN"), ("confirmed", "INFO")], [("confirmed", "INFO")]), said
    assert read_comments(out / "car2_fused_tum.txt") == []


# --------------------------------------------------------------------------------------------------
# Odometry failures: detected, cut at the onset, recovered as a new trajectory segment
# --------------------------------------------------------------------------------------------------


def test_healthy_kiss_icp_raises_no_false_alarm(tiny_scenario: Path) -> None:
    """Cars through intersections, the UAV at altitude: no divergence reported with the defaults."""
    from shgm_slam.runner import make_frontend

    for name in ("car1", "car2", "uav"):
        seq = open_sequence(str(tiny_scenario / name))
        front = make_frontend(name, seq, ShgmConfig())
        for i in range(len(seq)):
            front.process(i)
        assert front.failures == [], (name, [f.describe() for f in front.failures])
        assert len(front.segments) == 1 and (front.frame_segment == 0).all()


def test_blank_stretch_starts_a_new_segment_after_it(tiny_scenario: Path, tmp_path: Path) -> None:
    """Frames 20-23 have no depth (1 s at 4 Hz): KISS-ICP can only predict; the failure is dated to frame 20,
    the predicted frames belong to no segment, and segment 1 starts at the first measured frame."""
    import cv2

    from shgm_slam.odometry.health import FailureReason
    from shgm_slam.runner import make_frontend

    seq_dir = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq_dir)
    for i in range(20, 24):
        path = seq_dir / "depth" / f"{i:06d}.png"
        cv2.imwrite(str(path), np.zeros_like(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))
    seq = open_sequence(str(seq_dir))
    front = make_frontend("car1", seq, ShgmConfig())
    results = [front.process(i) for i in range(len(seq))]
    assert len(front.failures) == 1, [f.describe() for f in front.failures]
    failure = front.failures[0]
    assert failure.reason is FailureReason.COASTING and failure.onset_frame == 20
    assert [r.failure is not None for r in results].index(True) == failure.detected_frame
    assert (front.frame_segment[:20] == 0).all() and (front.frame_segment[20:24] == -1).all()
    assert np.isnan(front.T_odom_cam[20:24]).all()
    seg = front.segments[1]
    assert seg.agent == "car1#1" and seg.first_frame == 24 and (front.frame_segment[24:] == 1).all()
    np.testing.assert_allclose(front.T_odom_cam[24], np.eye(4), atol=1e-9)  # a new odometry frame
    assert max(front.segments[0].kf_frames) < 20 and min(seg.kf_frames) >= 24
    assert {r.agent for r in results[24:] if r.message is not None} == {"car1#1"}


def test_injected_jump_is_detected_and_the_new_segment_is_placed_again(tiny_scenario: Path, tmp_path: Path) -> None:
    """car2's odometry teleports 30 m sideways at frame 25: the failure is reported, segment car2#1 starts
    there in its own frame, and graph matching places both segments in the shared frame again (each from
    single matches here: a 25-frame segment of the tiny world never gets two independent ones)."""
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    for name, seq in robots.items():
        odo = se3.inverse(seq.gt_poses[0]) @ seq.gt_poses
        if name == "car2":
            odo[25:, 0, 3] += 30.0
        write_kitti_poses(tmp_path / f"odo_{name}.txt", odo)
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, tmp_path / "odo_{robot}.txt"
    cfg.backend.match_every_keyframes = 3
    cfg.backend.min_closures_to_anchor = 1
    summary = run_slam(robots, cfg, tmp_path / "out")
    car1, car2 = summary.robots
    assert car1.odometry_failures == 0 and car1.segments == 1
    assert car2.odometry_failures == 1 and car2.segments == 2
    assert car2.failure_reasons[0].startswith("speed at frame 25"), car2.failure_reasons
    assert car2.segments_placed == 2 and car2.localized and car2.placed_fraction == 1.0
    assert car2.ate_fused_m < 2.5, car2  # both segments in the right place: no trace of the 30 m jump
    assert car2.ate_odometry_m < 1e-6  # per segment, the odometry is exact
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["robots"][1]["failure_reasons"] == car2.failure_reasons
    assert (tmp_path / "out" / "graph_car2#1.json").is_file()
    # the odometry file restarts at the identity where the new segment starts
    t_odo, odo_file = read_tum(tmp_path / "out" / "car2_odometry_tum.txt")
    t = np.asarray(robots["car2"].timestamps_s)
    np.testing.assert_allclose(odo_file[np.flatnonzero(np.isclose(t_odo, t[25]))[0]], np.eye(4), atol=1e-6)


def test_an_odometry_that_stalls_at_speed_is_cut_where_it_stalled(tiny_scenario: Path, tmp_path: Path) -> None:
    """car1's odometry reads standing still for five frames mid-drive (as a road whose stripes line up at no
    motion does) and then drives on: no single step breaks a motion limit, but the speed continuity check
    dates the failure to the first stalled frame and the stall belongs to no segment."""
    from shgm_slam.odometry.health import FailureReason
    from shgm_slam.runner import make_frontend

    seq = open_sequence(str(tiny_scenario / "car1"))
    gt = se3.inverse(seq.gt_poses[0]) @ seq.gt_poses
    speeds = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) / np.diff(seq.timestamps_s)
    start = 28
    assert speeds[start - 1 : start + 5].min() > 3.0, "the car must be moving where the stall is injected"
    odo = gt.copy()
    for i in range(start, start + 5):  # frames start..start+4 stay where start-1 was
        odo[i] = odo[start - 1]
    odo[start + 5 :] = odo[start - 1] @ se3.inverse(gt[start + 4]) @ gt[start + 5 :]  # and then drive on
    write_kitti_poses(tmp_path / "odo.txt", odo)
    cfg = ShgmConfig()
    cfg.odometry.kind, cfg.odometry.poses_file = OdometryKind.FILE, tmp_path / "odo.txt"
    front = make_frontend("car1", seq, cfg)
    for i in range(len(seq)):
        front.process(i)
    assert [f.reason for f in front.failures] == [FailureReason.SPEED_CHANGE], [f.describe() for f in front.failures]
    assert front.failures[0].onset_frame == start
    assert (front.frame_segment[:start] == 0).all() and (front.frame_segment[start:] != 0).all()
    assert front.segments[1].first_frame >= front.failures[0].detected_frame  # re-initialised from there


def test_every_step_reports_its_cost(tiny_scenario: Path, tmp_path: Path) -> None:
    stats = []
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    cfg.backend.match_every_keyframes = 5
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    summary = run_slam(robots, cfg, tmp_path / "out", on_frame=stats.append)
    assert len(stats) == sum(r.frames_processed for r in summary.robots)
    for r in summary.robots:
        assert sum(s.keyframe for s in stats if s.robot == r.name) == r.keyframes
    assert sum(len(s.matches) for s in stats) <= summary.matches_tried  # the final matching is no step
    assert any(s.matches for s in stats)
    for s in stats:
        parts = (s.front_end_ms, s.load_ms, s.match_ms, s.backend_ms, s.server_ms)
        assert min(parts) >= 0.0
        assert s.match_ms + s.backend_ms + s.write_ms + s.correction_ms <= s.server_ms + 1e-6
        assert s.step_cpu_ms >= 0.0
        assert s.front_end_ms + s.load_ms + s.server_ms <= s.step_ms + 1e-6


def test_a_noisy_depth_sensor_is_measured_and_kiss_icp_sized_to_it(tiny_scenario: Path, tmp_path: Path) -> None:
    """5 % depth noise: the robot's report, metrics.json and config.yaml carry the noise its KISS-ICP voxel and
    spacing filter were sized to; noise-free renders read 0 and keep the car's 1 m voxel."""
    from shgm_slam.sim.corruption import CorruptionLevels
    from shgm_slam.sim.simulate import simulate

    noisy = tmp_path / "noisy"
    simulate("airsim-like", noisy, resolution=(320, 96), fps=4.0, compact=True, max_frames=12,
             corruption=CorruptionLevels.from_levels(depth_noise=0.05))  # fmt: skip
    clean = open_robots([f"car1={tiny_scenario / 'car1'}:0-12"])
    robots = open_robots([f"car1={noisy / 'car1'}"])
    cfg = ShgmConfig()
    summary = run_slam(robots, cfg, tmp_path / "out")
    (report,) = summary.robots
    assert 0.035 < report.depth_noise_rel < 0.075
    assert report.voxel_size_m > 1.0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["robots"][0]["depth_noise_rel"] == report.depth_noise_rel
    assert f"depth_noise_rel: {report.depth_noise_rel}" in (tmp_path / "out" / "config.yaml").read_text()
    assert "image_step_blend: true" in (tmp_path / "out" / "config.yaml").read_text()  # ICP blended with the tracks
    assert "blended with the one the image tracks give" in metrics["robots"][0]["odometry_reason"]
    (clean_report,) = run_slam(clean, cfg, tmp_path / "clean").robots
    assert clean_report.depth_noise_rel == 0.0 and clean_report.voxel_size_m == 1.0
    assert "image_step_blend: false" in (tmp_path / "clean" / "config.yaml").read_text()
    clean_metrics = json.loads((tmp_path / "clean" / "metrics.json").read_text())
    assert "blended" not in clean_metrics["robots"][0]["odometry_reason"]


def test_the_log_panel_gives_each_accepted_match_its_predicted_precision(early_stop) -> None:
    """An accepted match's line in the viewer's log says how well it is known (``MatchResult.centroid_sigma_m``);
    a rejected one claims none."""
    _, _, viz = early_stop["full"]
    lines = [text for text, _ in viz.texts if "<->" in text and " inliers" in text]
    accepted = [t for t in lines if ", accepted:" in t]
    assert accepted and all(re.search(r"inliers \(±\d+\.\d m predicted at the centre of car\d's nodes\)", t)
                            for t in accepted)  # fmt: skip
    assert all("predicted" not in t for t in lines if ", rejected:" in t)


def test_a_stop_while_the_run_starts_says_so(tiny_scenario: Path, tmp_path: Path, monkeypatch) -> None:
    """A Ctrl-C while the run set itself up (the ground truth and config.yaml written) was marked "stopped again
    while its results were being written", a second stop that never was."""
    from shgm_slam.runner import FleetRun

    def stopped(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(FleetRun, "_write_config", stopped)
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    robots = open_robots([f"car1={tiny_scenario / 'car1'}:0-20"])
    with pytest.raises(KeyboardInterrupt):
        run_slam(robots, cfg, tmp_path / "out")
    assert "stopped while the run was starting" in (tmp_path / "out" / "incomplete.txt").read_text()
