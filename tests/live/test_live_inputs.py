"""What a robot's driver gives ``LiveRun`` / ``LiveRobot`` wrongly or unusually: labels of another label space, a
reused buffer, a stop between held frames, an error or ``sys.exit`` in the ``with`` block, a closed link."""

from __future__ import annotations

import signal
import socket
import sys
from pathlib import Path

import numpy as np
import pytest

from shgm_slam import open_sequence
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.live import LiveRobot, LiveRun
from shgm_slam.types import Intrinsics

K = Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4)
"""A tiny camera for the stream's own checks: 8 x 4 pixels."""


def give(live: LiveRun | LiveRobot, seq, frames, robot: str = "car1") -> list:
    """Frames ``frames`` of recorded ``seq`` given as a camera would; the poses returned."""
    poses = []
    for i in frames:
        f = seq[i]
        args = (f.image_rgb, f.timestamp_s)
        kwargs = dict(depth_m=f.depth_m, label_ids=f.label_ids)
        if isinstance(live, LiveRun):
            poses += live.add_frame(robot, *args, **kwargs)
        else:
            poses += live.add_frame(*args, **kwargs)
    return poses


def stop_at_call(monkeypatch, cls: type, method: str, call: int) -> None:
    """A Ctrl-C (SIGINT) that arrives while the ``call``-th call of ``cls.method`` runs (a held frame's step); the
    test takes the ``python_ctrl_c`` fixture, so that the signal raises KeyboardInterrupt here."""
    real, calls = getattr(cls, method), [0]

    def step(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] == call:
            signal.raise_signal(signal.SIGINT)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(cls, method, step)


def free_endpoint() -> str:
    """A Zenoh endpoint no server listens on (the robot's link opens; nothing answers)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def test_labels_of_another_label_space_are_refused_at_their_frame() -> None:
    """Only a robot's first frames were checked for train ids: a later frame in Cityscapes' full label ids (road 7,
    car 26) was taken without a word, its classes read wrongly. A few stray values (a resized map's edges) pass."""
    stream = FrameStream(K, name="cam")
    image, labels = np.zeros((4, 8, 3), np.uint8), np.full((4, 8), 7, np.uint8)
    stream.append(image, 0.0, label_ids=labels)
    with pytest.raises(DataError, match=r"'cam' frame 1: 50 % of label_ids are 26, no Cityscapes train id.*trainId"):
        stream.append(image, 0.1, label_ids=np.where(np.arange(8) < 4, 7, 26).astype(np.int64)[None].repeat(4, 0))
    assert len(stream) == 1
    big = FrameStream(Intrinsics(100.0, 100.0, 50.0, 50.0, 100, 100), name="big")
    few = np.zeros((100, 100), np.uint8)
    few[0, :100] = 200  # 1 % of the pixels
    few[1, :10] = 255
    big.append(np.zeros((100, 100), np.uint8), 0.0, label_ids=few)
    assert (big[0].label_ids == few).all()


def test_an_image_in_a_reused_buffer_is_copied(tmp_path: Path) -> None:
    """An image in a memory-mapped ring buffer (or an object whose ``__array__`` is a view of one) was held as a view:
    the driver's next frame overwrote the frames held for the warm-up."""
    stream = FrameStream(K, name="cam")
    ring = np.memmap(tmp_path / "ring.bin", dtype=np.uint8, mode="w+", shape=(4, 8, 3))
    ring[:] = 1
    stream.append(ring, 0.0)

    class SdkImage:  # a camera SDK's frame: its array is a view of the driver's buffer
        def __init__(self, buffer: np.ndarray) -> None:
            self.buffer = buffer

        def __array__(self, dtype=None, copy=None) -> np.ndarray:
            return self.buffer

    buffer = np.full((4, 8, 3), 5, np.uint8)
    stream.append(SdkImage(buffer), 0.1)
    ring[:], buffer[:] = 2, 6
    assert stream[0].image_rgb[0, 0, 0] == 1 and stream[1].image_rgb[0, 0, 0] == 5
    with pytest.raises(DataError, match=r"frame 2: the image \(list\) cannot be read as an array"):
        stream.append([[1, 2], [3]], 0.2)  # ragged lists: numpy's ValueError came out
    assert len(stream) == 2
    deep = FrameStream(K, name="deep")
    with pytest.raises(DataError, match=r"'deep' frame 0: depth_m \(list\) cannot be read as an array"):
        deep.append(np.zeros((4, 8), np.uint8), 0.0, depth_m=[[1.0], [1.0, 2.0]])


def test_a_bad_depth_origin_is_a_data_error_before_any_folder(tmp_path: Path) -> None:
    """A ``depth_origin`` that is no ``DepthOrigin`` raised Python's ValueError from inside the enum."""
    with pytest.raises(DataError, match="'car1': depth_origin 'sensor' is none of 'measured', 'predicted'"):
        LiveRun({"car1": K}, tmp_path / "a", depth_origin="sensor")  # type: ignore[arg-type]
    assert not (tmp_path / "a").exists()
    live = LiveRun({"car1": K}, tmp_path / "b")
    with pytest.raises(DataError, match="'car2': depth_origin 'lidar'"):
        live.add_camera("car2", K, depth_origin="lidar")  # type: ignore[arg-type]
    assert list(live.streams) == ["car1"]
    with pytest.raises(DataError, match="depth_origin 'x'"):
        LiveRobot("car1", K, depth_origin="x")  # type: ignore[arg-type]


def test_an_append_stopped_midway_leaves_nothing_behind(monkeypatch) -> None:
    """A Ctrl-C inside ``append`` (after the image was taken, before the frame was counted) left the image in the
    stream's list: the next frame was given that stale image instead of its own."""
    stream = FrameStream(K, name="cam")
    real, calls = FrameStream._label_map, [0]

    def label_map(self, i, where):
        calls[0] += 1
        if calls[0] == 1:
            raise KeyboardInterrupt
        return real(self, i, where)

    monkeypatch.setattr(FrameStream, "_label_map", label_map)
    labels = np.zeros((4, 8), np.uint8)
    with pytest.raises(KeyboardInterrupt):
        stream.append(np.full((4, 8, 3), 1, np.uint8), 0.0, label_ids=labels)
    assert len(stream) == 0
    stream.append(np.full((4, 8, 3), 2, np.uint8), 0.0, label_ids=labels)
    stream.append(np.full((4, 8, 3), 3, np.uint8), 0.1, label_ids=labels)
    assert [stream[i].image_rgb[0, 0, 0] for i in range(2)] == [2, 3]


@pytest.mark.parametrize("what", ["timestamp_s", "T_odom_cam"])
def test_units_refused_at_the_fourth_frame_say_the_camera_must_start_anew(what: str) -> None:
    """Times in nanoseconds (or poses in millimetres) are refused from the fourth frame on, when the first three are
    in already: the message said "divide by 1e9", but every later frame in seconds was then refused as earlier than
    the last; it says to start the camera anew."""
    stream = FrameStream(K, name="cam")
    T = np.eye(4)
    for i in range(4):
        t = i * 100_000_000 if what == "timestamp_s" else 0.1 * i
        T[0, 3] = 1000.0 * i
        give = dict(T_odom_cam=T) if what == "T_odom_cam" else {}
        if i < 3:
            stream.append(np.zeros((4, 8), np.uint8), t, **give)
            continue
        with pytest.raises(DataError, match=r"frame 3: .*; frames 0 to 2 were taken in those units and cannot be "
                                            r"taken back: start this camera anew"):  # fmt: skip
            stream.append(np.zeros((4, 8), np.uint8), t, **give)
    assert len(stream) == 3


def test_a_stop_between_held_frames_leaves_the_rest_to_run_in_order(tiny_scenario: Path, tmp_path: Path,
                                                                   monkeypatch, python_ctrl_c) -> None:  # fmt: skip
    """A Ctrl-C while the call that starts the run ran the held frames dropped the frames after the one it stopped:
    caught and fed on, the robot's later frames ran in their place, and the files paired their poses with the
    earlier frames' times (31 of 47 rows). They stay held and run, in order, at the next frame."""
    from shgm_slam.runner import FleetRun

    seq = open_sequence(tiny_scenario / "car1")
    live = LiveRun({"car1": seq.intrinsics}, tmp_path / "out")
    stop_at_call(monkeypatch, FleetRun, "step", 5)
    given = 0
    with pytest.raises(KeyboardInterrupt):
        for given in range(len(seq)):
            give(live, seq, [given])
    monkeypatch.undo()
    assert live.started and [i for _, i in live._held] == list(range(5, given + 1))
    poses = give(live, seq, range(given + 1, len(seq)))
    assert [p.index for p in poses] == list(range(5, len(seq)))
    summary = live.finish()
    assert summary.robots[0].frames_processed == len(seq)
    odometry = np.loadtxt(summary.out_dir / "car1_odometry_tum.txt")
    np.testing.assert_allclose(odometry[:, 0], seq.timestamps_s, atol=1e-6)


@pytest.mark.parametrize("how", ["sys.exit", "generator closed"])
def test_a_with_block_left_by_sys_exit_finishes_the_run_as_stopped(tiny_scenario: Path, tmp_path: Path,
                                                                    how: str) -> None:  # fmt: skip
    """``sys.exit`` (a SIGTERM handler's) or a generator closed inside the block left a checkpoint neither finished
    nor marked incomplete; they stop the run as a Ctrl-C does: what there is, written."""
    seq = open_sequence(tiny_scenario / "car1")

    def feeding():
        with LiveRun({"car1": seq.intrinsics}, tmp_path / "out") as live:
            for i in range(30):
                yield live, give(live, seq, [i])

    if how == "sys.exit":
        with pytest.raises(SystemExit):
            for live, _ in feeding():
                if live.started:
                    sys.exit(0)
    else:
        frames = feeding()
        live, _ = next(frames)
        while not live.started:
            next(frames)
        frames.close()
    summary = live.finish()
    assert summary.interrupted and summary.robots[0].frames_processed == len(live.streams["car1"])
    assert (tmp_path / "out" / "metrics.json").is_file() and not (tmp_path / "out" / "incomplete.txt").exists()


def test_an_error_in_the_with_block_keeps_every_keyframe_so_far(tiny_scenario: Path, tmp_path: Path) -> None:
    """An error of the caller's code in the block marked the folder incomplete over its last periodic checkpoint
    (every 25 keyframes): the keyframes since were lost, and a live run's frames cannot be fed again."""
    seq = open_sequence(tiny_scenario / "car1")
    poses = []
    with pytest.raises(ValueError, match="driver lost"):
        with LiveRun({"car1": seq.intrinsics}, tmp_path / "out") as live:
            poses = give(live, seq, range(40))
            raise ValueError("driver lost")
    assert "ValueError: driver lost" in (tmp_path / "out" / "incomplete.txt").read_text()
    keyframes = sum(p.keyframe for p in poses)
    assert keyframes > 25
    assert len(np.loadtxt(tmp_path / "out" / "car1_odometry_tum.txt")) == keyframes
    with pytest.raises(ConfigError, match="ended with an error"):
        give(live, seq, [40])


def test_a_live_robot_whose_link_closed_takes_no_more_frames(tmp_path: Path) -> None:
    """After an error left its ``with`` block (or ``finish`` failed) the robot's link was closed, yet frames were
    still taken, and once it ran, the Zenoh layer's "the transport is closed; open a new one" came instead."""
    image, labels = np.zeros((4, 8, 3), np.uint8), np.zeros((4, 8), np.uint8)
    with pytest.raises(ValueError):
        with LiveRobot("car2", K, connect=free_endpoint(), wait_s=0.1) as robot:
            robot.add_frame(image, 0.0, depth_m=np.ones((4, 8), np.float32), label_ids=labels)
            raise ValueError("driver lost")
    for call in (lambda: robot.add_frame(image, 0.1, depth_m=np.ones((4, 8), np.float32), label_ids=labels),
                 robot.finish):  # fmt: skip
        with pytest.raises(ConfigError, match=r"robot 'car2': its link .* closed: .*ValueError: driver lost; start "
                                              r"a new LiveRobot"):  # fmt: skip
            call()
    assert len(robot.stream) == 1

    empty = LiveRobot("car3", K, connect=free_endpoint(), wait_s=0.1)
    with pytest.raises(DataError, match="no frame was given"):
        empty.finish()
    with pytest.raises(ConfigError, match=r"robot 'car3': its link .* closed: finish failed"):
        empty.add_frame(image, 0.0, depth_m=np.ones((4, 8), np.float32), label_ids=labels)
    assert len(empty.stream) == 0


def test_a_live_robot_stopped_in_its_with_block_writes_what_it_ran(tiny_scenario: Path, tmp_path: Path,
                                                                   monkeypatch, python_ctrl_c) -> None:  # fmt: skip
    """A Ctrl-C in a ``LiveRobot``'s block closed its link and wrote nothing to ``out`` (``shgm-slam robot`` writes
    its trajectories and leaves the server holding it, not done); a Ctrl-C between its held
    frames dropped the rest. Here the stop lands in the 5th held frame; the robot is fed on, then stopped."""
    from shgm_slam.robot.node import RobotNode

    seq = open_sequence(tiny_scenario / "car2")
    robot = LiveRobot("car2", seq.intrinsics, connect=free_endpoint(), out=tmp_path / "car2", wait_s=0.1)
    stop_at_call(monkeypatch, RobotNode, "step", 5)
    with pytest.raises(KeyboardInterrupt):
        with robot:
            given = 0
            with pytest.raises(KeyboardInterrupt):
                for given in range(len(seq)):
                    give(robot, seq, [given])
            monkeypatch.undo()
            done_calls: list[str] = []
            monkeypatch.setattr(RobotNode, "done", lambda self: done_calls.append(self.name))
            poses = give(robot, seq, range(given + 1, 30))
            assert [p.index for p in poses] == list(range(5, 30))
            raise KeyboardInterrupt
    summary = robot.finish()
    assert summary.interrupted and summary.frames_processed == 30
    assert done_calls == []  # not done on the server: it keeps the robot, and one of its name resumes it
    times = np.loadtxt(tmp_path / "car2" / "car2_odometry_tum.txt")[:, 0]
    np.testing.assert_allclose(times, seq.timestamps_s[:30], atol=1e-6)


def test_a_pose_the_odometry_only_predicted_says_so(tiny_scenario: Path, tmp_path: Path) -> None:
    """A frame with no valid depth got a pose extrapolated from the last motion, returned like a measured one
    (``skipped`` None, nothing logged): ``measured`` now tells them apart."""
    seq = open_sequence(str(tiny_scenario / "car1"))
    with LiveRun({"car1": seq.intrinsics}, tmp_path / "out") as live:
        poses = give(live, seq, range(25))
        f = seq[25]
        poses += live.add_frame("car1", f.image_rgb, f.timestamp_s, depth_m=np.zeros_like(f.depth_m),
                                label_ids=f.label_ids)  # fmt: skip
        poses += give(live, seq, range(26, 28))
    by_index = {p.index: p for p in poses}
    assert not by_index[25].measured and by_index[25].skipped is None and np.isfinite(by_index[25].T_odom_cam).all()
    assert by_index[24].measured and by_index[27].measured


def test_a_live_robot_that_cannot_start_takes_no_more_frames() -> None:
    """Frames without depth and no depth model: the first frame is refused naming the fix. The robot then held every
    later frame and refused it again, the same error each call, its held frames growing; now it is closed."""
    robot = LiveRobot("car1", K, connect=free_endpoint())
    with pytest.raises(DataError, match=r"no depth.*perception\.depth_model"):
        robot.add_frame(np.zeros((4, 8, 3), np.uint8), 0.0, label_ids=np.zeros((4, 8), np.uint8))
    with pytest.raises(ConfigError, match=r"robot 'car1'.*could not start \(.*no depth.*start a new LiveRobot"):
        robot.add_frame(np.zeros((4, 8, 3), np.uint8), 0.1, label_ids=np.zeros((4, 8), np.uint8))
    assert len(robot.stream) == 1
