"""Front ends in worker processes: the orchestrator's mirror holds exactly the front end's state, a run with
worker processes writes the very same results as one process, and a worker that dies costs only its robot's
remaining frames."""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from shgm_slam.arrays import thinning_stride
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.errors import ConfigError
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import read_tum, write_kitti_poses
from shgm_slam.robot.remote import FrontendMirror, _Marks, assign_workers, default_jobs, frame_delta
from shgm_slam.runner import make_frontend, open_robots, run_slam
from tests.robot.jumps import jumping_odometry


def _blanked_and_corrupt(tiny_scenario: Path, tmp_path: Path) -> Path:
    """car1 with frames 20-23 without depth (a coasting failure: segment 0 is cut back to frame 20 and a
    second segment starts at 24) and frame 35's depth unreadable (a skipped frame)."""
    seq_dir = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq_dir)
    for i in range(20, 24):
        path = seq_dir / "depth" / f"{i:06d}.png"
        cv2.imwrite(str(path), np.zeros_like(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))
    (seq_dir / "depth" / "000035.png").write_bytes(b"not a png")
    return seq_dir


def _assert_same_state(mirror: FrontendMirror, front) -> None:
    np.testing.assert_array_equal(mirror.T_odom_cam, front.T_odom_cam)  # NaN rows equal too
    np.testing.assert_array_equal(mirror.frame_kf, front.frame_kf)
    np.testing.assert_array_equal(mirror.frame_segment, front.frame_segment)
    assert len(mirror.segments) == len(front.segments)
    for m, s in zip(mirror.segments, front.segments, strict=True):
        assert (m.index, m.agent, m.first_frame, m.kf_frames, m.num_nodes, m.end_failure) == (
            s.index, s.agent, s.first_frame, s.kf_frames, len(s.graph), s.end_failure)  # fmt: skip
        np.testing.assert_array_equal(np.reshape(m.kf_poses, (-1, 4, 4)), np.reshape(s.kf_poses, (-1, 4, 4)))
    assert mirror.failures == front.failures and mirror.depth_scales == front.depth_scales
    assert (mirror.measured_frames, mirror.planar_turns, mirror.road_steps, mirror.image_steps,
            mirror.image_windows, mirror.references, mirror.levelled_references) == (
        front.measured_frames, front.planar_turns, front.road_steps, front.image_steps, front.image_windows,
        front.references, front.levelled_references)  # fmt: skip
    assert mirror.num_keyframes == front.num_keyframes and mirror.segment.agent == front.segment.agent


def _assert_viewer_share(sent, res, viewer_points: int) -> None:
    """What crosses to the orchestrator: the image always; for a viewer the labels of every frame and the
    depth and the cloud of keyframes, the cloud thinned to the rows the viewer draws of the full one."""
    assert sent.frame.image_rgb is res.frame.image_rgb and sent.frame.depth_m is None
    if viewer_points == 0 or res.message is None:
        assert sent.depth_m is None and sent.points_cam.shape == (0, 3) and sent.point_labels is None
    if viewer_points == 0:
        assert sent.label_ids is None
        return
    assert sent.label_ids is res.label_ids
    if res.message is not None:
        step = thinning_stride(len(res.points_cam), viewer_points)
        assert sent.depth_m is res.depth_m and 0 < len(sent.points_cam) <= viewer_points < len(res.points_cam)
        np.testing.assert_array_equal(sent.points_cam, res.points_cam[::step])
        np.testing.assert_array_equal(sent.point_labels, res.point_labels[::step])
        assert thinning_stride(len(sent.points_cam), viewer_points) == 1  # the viewer draws every row sent


def test_mirror_holds_the_front_ends_state_after_every_frame(tiny_scenario: Path, tmp_path: Path) -> None:
    """Through a divergence (the segment cut back to its onset, a new segment) and a skipped frame."""
    from shgm_slam.errors import DataError

    seq = open_sequence(str(_blanked_and_corrupt(tiny_scenario, tmp_path)))
    cfg = ShgmConfig()
    front = make_frontend("car1", seq, cfg)
    mirror = FrontendMirror(make_frontend("car1", seq, cfg))
    skipped = 0
    for i in range(len(seq)):
        before = _Marks.of(front)
        try:
            res = front.process(i)
        except DataError:
            skipped += 1
            continue
        viewer_points = 0 if i % 2 else 300
        delta = frame_delta(front, before, res, i, viewer_points=viewer_points)
        _assert_viewer_share(delta.result, res, viewer_points)
        got = mirror.apply(delta)
        assert got.message == res.message and got.agent == res.agent and got.failure == res.failure
        _assert_same_state(mirror, front)
    assert skipped == 1 and len(front.failures) == 1 and len(front.segments) == 2  # the test saw what it meant to
    assert (mirror.frame_segment[20:24] == -1).all() and mirror.segments[1].first_frame == 24


def _outputs(folder: Path) -> dict[str, bytes | dict]:
    out: dict[str, bytes | dict] = {p.name: p.read_bytes() for p in folder.iterdir() if p.suffix in (".txt", ".g2o")}
    metrics = json.loads((folder / "metrics.json").read_text())
    for k in ("timings_ms", "wall_s", "per_keyframe_ms"):
        metrics.pop(k)
    out["metrics.json"] = metrics
    return out


def test_worker_processes_write_the_same_results_as_one_process(tiny_scenario: Path, tmp_path: Path) -> None:
    """Three robots, one of which diverges (its odometry teleports 30 m at frame 25) and one with a blank
    stretch and an unreadable frame: every results file is byte for byte the same."""
    blank = _blanked_and_corrupt(tiny_scenario, tmp_path)
    specs = [f"car1={blank}", f"car2={tiny_scenario / 'car2'}", f"uav={tiny_scenario / 'uav'}"]
    car2 = open_robots(specs)["car2"]
    odo = se3.inverse(car2.gt_poses[0]) @ car2.gt_poses
    odo[25:, 0, 3] += 30.0
    write_kitti_poses(tmp_path / "odo_car2.txt", odo)
    cfg = ShgmConfig.model_validate({"robots": {"car2": {"odometry": {
        "kind": "file", "poses_file": str(tmp_path / "odo_car2.txt")}}}})  # fmt: skip
    cfg.backend.match_every_keyframes = 3
    one = run_slam(open_robots(specs), cfg, tmp_path / "one")
    many = run_slam(open_robots(specs), cfg, tmp_path / "many", jobs=2)
    assert [r.segments for r in one.robots] == [2, 2, 1] and one.robots[0].frames_skipped == 1
    assert one.closures_accepted > 0
    assert _outputs(tmp_path / "one") == _outputs(tmp_path / "many")
    assert [vars(r) for r in many.robots] == [vars(r) for r in one.robots]


class DiesAt:
    """A sequence whose worker process dies (``os._exit``, as an out-of-memory kill would end it) or raises a
    plain bug when it loads frame ``at``; in the orchestrator's own process it reads normally."""

    def __init__(self, inner, at: int, how: str) -> None:
        self.inner, self.at, self.how = inner, at, how

    def __len__(self) -> int:
        return len(self.inner)

    def __getattr__(self, attr: str):
        if attr == "inner":
            raise AttributeError(attr)
        return getattr(self.inner, attr)

    def __getitem__(self, i: int):
        if i == self.at and multiprocessing.parent_process() is not None:
            if self.how == "die":
                os._exit(9)
            raise ZeroDivisionError("a bug in the front end")
        return self.inner[i]


def test_default_jobs_is_one_worker_per_robot_up_to_the_cores(monkeypatch) -> None:
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    assert [default_jobs(n) for n in (1, 2, 3, 8)] == [1, 2, 2, 2]
    assert default_jobs(3, 1) == 1 and default_jobs(3, 5) == 5  # as given (never more workers than robots: below)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert default_jobs(4) == 1


def test_robots_are_spread_over_the_workers_longest_first() -> None:
    assert assign_workers({"a": 10, "b": 50, "c": 30, "d": 20}, 2) == [["a", "b"], ["c", "d"]]
    assert assign_workers({"a": 10, "b": 50}, 8) == [["a"], ["b"]]  # never more workers than robots
    assert assign_workers({"a": 10, "b": 50, "c": 5}, 1) == [["a", "b", "c"]]
    groups = assign_workers({f"r{i}": 100 + i for i in range(8)}, 3)
    assert sorted(r for g in groups for r in g) == [f"r{i}" for i in range(8)] and len(groups) == 3
    assert max(map(len, groups)) - min(map(len, groups)) <= 1


def test_a_dead_worker_costs_its_robots_remaining_frames_only(tiny_scenario: Path, tmp_path: Path) -> None:
    """A worker killed at car2's frame 30 (car2 alone in it), then a bug in car2's front end at frame 30 while
    it shares its worker with another robot: car2's remaining frames are skipped with the reason, what it did
    before is kept, and the robots beside it go on to the end."""
    specs = [f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}", f"uav={tiny_scenario / 'uav'}"]
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    cases = (("die", 2, "worker process died (exit code 9"), ("bug", 3, "ZeroDivisionError: a bug"))
    for how, robots_in, said in cases:
        robots = dict(list(open_robots(specs).items())[:robots_in])
        robots["car2"] = DiesAt(robots["car2"], 30, how)
        if how == "bug":
            groups = assign_workers({r: len(q) for r, q in robots.items()}, 2)
            assert any("car2" in g and len(g) == 2 for g in groups)  # it shares its worker
        out = tmp_path / how
        summary = run_slam(robots, cfg, out, jobs=2)
        reports = {r.name: r for r in summary.robots}
        car2 = reports.pop("car2")
        # a bug is reported after every frame before it; a killed worker loses the frames still on their way
        done = car2.frames_processed
        assert done == 30 if how == "bug" else 0 < done <= 30
        assert all(r.frames_skipped == 0 and r.frames_processed == r.frames for r in reports.values())
        assert car2.frames_skipped == len(robots["car2"]) - done
        assert said in summary.skipped_reasons[0] and f"car2 frame {done}:" in summary.skipped_reasons[0]
        t, _ = read_tum(out / "car2_odometry_tum.txt")
        assert len(t) == done  # what it did before it died is kept
        assert json.loads((out / "metrics.json").read_text())["robots"][1]["frames_processed"] == done
        # said as a fault of its own, not as skipped data: the command exits 1, a benchmark refuses the run
        assert summary.front_ends_lost == [car2.front_end_lost] and said in car2.front_end_lost
        assert car2.front_end_lost.startswith(f"at frame {done}: car2:")
        assert all(r.front_end_lost is None for r in reports.values())


def test_a_sequence_that_cannot_go_to_a_worker_is_a_clear_error(tiny_scenario: Path, tmp_path: Path) -> None:
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])
    robots["car2"] = DiesAt(robots["car2"], -1, "never")
    robots["car2"].hook = lambda: None  # a lambda cannot be pickled
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    with pytest.raises(ConfigError, match=r"car2.*cannot be handed to a worker process.*--jobs 1"):
        run_slam(robots, cfg, tmp_path / "out", jobs=2)


def _report_sigint_state(conn) -> None:
    """A worker's first act: are SIGINT and SIGHUP ignored (a Ctrl-C or a hangup during its imports cannot have
    killed it)?"""
    import signal

    from shgm_slam.robot.remote import WORKER_IGNORED_SIGNALS

    conn.send(all(signal.getsignal(s) is signal.SIG_IGN for s in WORKER_IGNORED_SIGNALS))
    conn.close()


@pytest.mark.skipif(not hasattr(__import__("signal"), "pthread_sigmask"), reason="POSIX signal masks")
def test_a_worker_starts_with_ctrl_c_ignored_and_the_orchestrator_keeps_it() -> None:
    """A Ctrl-C on the process group killed workers still importing, with tracebacks and robots reported failed."""
    import signal

    from shgm_slam.robot.remote import _start_without_sigint

    # a terminal's process: Ctrl-C raises KeyboardInterrupt here (pytest-xdist's workers ignore it themselves)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_report_sigint_state, args=(child,))
        _start_without_sigint(proc)
        child.close()
        assert parent.recv() is True
        proc.join(timeout=60)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # this process still gets Ctrl-C
    finally:
        signal.signal(signal.SIGINT, previous)
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    assert signal.SIGHUP not in signal.pthread_sigmask(signal.SIG_BLOCK, [])


class _Unmeasured:
    """Wraps an odometry source: the frames in ``frames`` are reported as predicted (not measured)."""

    def __init__(self, inner, frames: set[int]) -> None:
        self.inner, self.frames = inner, frames

    def update(self, frame, *args, **kwargs):
        est = self.inner.update(frame, *args, **kwargs)
        return replace(est, ok=False) if frame.index in self.frames else est

    def reset(self, motion=None) -> None:
        self.inner.reset(motion)


def test_a_restarted_segment_moves_its_origin_until_it_measures_a_step(tiny_scenario: Path, tmp_path: Path) -> None:
    """car1's odometry jumps 30 m at frame 25 and frames 26-27 are not measured (PnP failing inside a sharp
    turn): the new segment's origin moves to frame 28, frames 25-27 belong to no segment, its first keyframe is
    the first frame after a measured step; the mirror follows the rows moved back."""
    seq, cfg, gt = jumping_odometry(tiny_scenario / "car1", tmp_path, 25)
    front = make_frontend("car1", seq, cfg)
    front.odometry = _Unmeasured(front.odometry, {26, 27, 33})
    mirror = FrontendMirror(make_frontend("car1", seq, cfg))
    for i in range(36):
        before = _Marks.of(front)
        res = front.process(i)
        mirror.apply(frame_delta(front, before, res, i, viewer_points=0))
        _assert_same_state(mirror, front)
    assert [f.onset_frame for f in front.failures] == [25] and len(front.segments) == 2
    seg = front.segments[1]
    assert seg.first_frame == 28 and seg.kf_frames[0] == 29
    assert (front.frame_segment[25:28] == -1).all() and np.isnan(front.T_odom_cam[25:28]).all()
    assert (front.frame_segment[28:36] == 1).all()
    np.testing.assert_allclose(front.T_odom_cam[28], np.eye(4), atol=1e-6)
    np.testing.assert_allclose(front.T_odom_cam[32], se3.inverse(gt[28]) @ gt[32], atol=1e-6)
    assert front.frame_segment[33] == 1  # a steady segment coasts over an unmeasured frame, as before
