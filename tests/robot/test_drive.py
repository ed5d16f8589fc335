"""One robot process's loop: ``--realtime`` paces frames by their timestamps, also while messages arrive."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.messages import CorrectionMessage
from shgm_slam.robot.drive import drive_robot
from shgm_slam.runner import open_robots
from shgm_slam.transport.factory import NodeRole, make_transport
from shgm_slam.transport.keys import correction_key
from shgm_slam.wire import encode


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_realtime_paces_frames_by_their_timestamps_while_messages_arrive(tiny_scenario: Path) -> None:
    (name, seq), = open_robots([f"car1={tiny_scenario / 'car1'}:0-9"]).items()
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    span_s = float(seq.timestamps_s[-1] - seq.timestamps_s[0])  # 2 s at the tiny world's 4 Hz
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    stop = threading.Event()
    with make_transport(NodeRole.SERVER, endpoint) as server:
        ack = encode(CorrectionMessage(name, "", {}))  # an acknowledgement of nothing, every 20 ms

        def chatter() -> None:
            while not stop.wait(0.02):
                server.publish(correction_key(name), ack)

        thread = threading.Thread(target=chatter, daemon=True)
        thread.start()
        try:
            t0 = time.perf_counter()
            s = drive_robot(name, seq, cfg, connect=endpoint, realtime=True, wait_s=0.0)
            took = time.perf_counter() - t0
        finally:
            stop.set()
            thread.join()
    assert s.frames_processed == len(seq)
    assert took >= span_s, (took, span_s)


def test_a_stopped_robot_does_not_tell_the_server_it_is_done(tiny_scenario: Path, monkeypatch) -> None:
    """A Ctrl-C sent the server the robot's "done": a server with --expect then finished without the rest of its
    keyframes (7 of 49), exit 0 and not interrupted, while the robot said "start the same command again to go on".
    Not done, the server keeps the robot (stale) and the same command resumes it."""
    from shgm_slam.robot.node import RobotNode

    (name, seq), = open_robots([f"car1={tiny_scenario / 'car1'}:0-9"]).items()
    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    done_calls: list[str] = []
    monkeypatch.setattr(RobotNode, "done", lambda self: done_calls.append(self.name))

    def stop_at_frame_4(done: int, total: int) -> None:
        if done == 4:
            raise KeyboardInterrupt

    s = drive_robot(name, seq, cfg, connect=f"tcp/127.0.0.1:{_free_port()}", wait_s=0.0, progress=stop_at_frame_4)
    assert s.interrupted and s.frames_processed == 4 and done_calls == []
    s = drive_robot(name, seq, cfg, connect=f"tcp/127.0.0.1:{_free_port()}", wait_s=0.0)
    assert not s.interrupted and done_calls == ["car1"]
