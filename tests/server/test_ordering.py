"""The map server's keyframe order: one global time order over all robots, whatever the arrival order."""

from __future__ import annotations

import math
from itertools import permutations
from pathlib import Path

import numpy as np

from shgm_slam.graph.semantic_graph import GraphUpdate
from shgm_slam.messages import CorrectionMessage, KeyframeMessage
from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend
from shgm_slam.server.node import ServerNode
from shgm_slam.server.ordering import KeyframeOrder
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import correction_key
from shgm_slam.wire import encode
from tests.server.conftest import FakeClock, fresh, fused


def _kf(agent: str, index: int, t: float) -> KeyframeMessage:
    empty = GraphUpdate(index, np.eye(4), (), ())
    return KeyframeMessage(agent, index, index, t, np.eye(4), empty)


def _stream(robot: str, times: list[float], start_s: float = 0.0) -> list[KeyframeMessage]:
    return [_kf(robot, i, start_s + t) for i, t in enumerate(times)]


def test_any_arrival_order_is_released_in_time_order_reference_first_on_ties() -> None:
    streams = {"car1": _stream("car1", [0.0, 1.0, 2.0]), "uav": _stream("uav", [0.5, 1.0], start_s=100.0),
               "car2": _stream("car2", [0.0, 1.5])}  # fmt: skip
    rank = {"car1": 0, "car2": 1, "uav": 1}
    start = {"car1": 0.0, "car2": 0.0, "uav": 100.0}
    expected = [("car1", 0), ("car2", 0), ("uav", 0), ("car1", 1), ("uav", 1), ("car2", 1), ("car1", 2)]
    for arrival in permutations(streams):  # whole streams one after another, in every robot order
        order, released = KeyframeOrder(), []
        progress: dict[str, float | None] = dict.fromkeys(streams)
        for robot in arrival:
            for m in streams[robot]:
                order.offer(m, b"", start[robot], rank[robot])
                progress[robot] = m.timestamp_s - start[robot]
                released += order.release(progress)
            progress[robot] = math.inf  # done
            released += order.release(progress)
        assert [(h.msg.robot, h.msg.kf_index) for h in released] == expected
        assert len(order) == 0


def test_a_robot_that_may_still_send_an_earlier_keyframe_holds_the_others_back() -> None:
    order = KeyframeOrder()
    for m in _stream("car1", [0.0, 1.0, 2.0]):
        order.offer(m, b"", 0.0, 0)
    assert order.held("car1") == 3
    assert order.release({"car1": 2.0, "car2": None}) == []  # car2 has not started
    assert [h.msg.kf_index for h in order.release({"car1": 2.0, "car2": 1.2})] == [0, 1]
    assert order.held("car1") == 1
    assert [h.msg.kf_index for h in order.release({"car1": 2.0, "car2": math.inf})] == [2]


def test_a_restarted_robots_queue_is_dropped() -> None:
    order = KeyframeOrder()
    for m in _stream("car2", [0.0, 1.0]) + _stream("car2#1", [2.0]):
        order.offer(m, b"", 0.0, 1)
    assert order.agents() == ["car2", "car2#1"]
    assert order.drop("car2") == 3
    assert len(order) == 0 and order.held("car2") == 0 and order.agents() == []


def _run(robots, cfg, tmp_path: Path, schedule: list[tuple[str, int]]) -> ServerNode:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, reference="car1", clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    for robot, i in schedule:
        nodes[robot].step(i)
        clock.t += 0.01
        server.poll()
        nodes[robot].poll()
    for n in nodes.values():
        n.done()
    for _ in range(5):
        clock.t += 0.5
        server.poll()
    assert server.finished
    return server


def test_the_map_server_result_does_not_depend_on_how_fast_each_robot_ran(robots, cfg, tmp_path: Path) -> None:
    """car1's whole sequence first, then car2's, against the two stepped frame by frame in time: the server
    sees the same keyframes in the same order, so it finds the same closures and the same poses."""
    n1, n2 = len(robots["car1"]), len(robots["car2"])
    by_time = [(r, i) for i in range(max(n1, n2)) for r in ("car1", "car2") if i < len(robots[r])]
    one_after_other = [("car1", i) for i in range(n1)] + [("car2", i) for i in range(n2)]
    a = _run(robots, cfg, tmp_path / "a", by_time)
    b = _run(robots, cfg, tmp_path / "b", one_after_other)
    assert [(m.robot_a, m.robot_b, m.accepted) for m in a.map.matches] == [
        (m.robot_a, m.robot_b, m.accepted) for m in b.map.matches
    ]
    np.testing.assert_allclose(fused(a, "car2"), fused(b, "car2"), atol=1e-6)


def test_a_robot_reports_progress_only_up_to_what_the_server_acknowledged(robots, cfg) -> None:
    bus = InProcessBus()
    node = RobotNode(make_frontend("car1", robots["car1"], cfg), InProcessTransport(bus))
    assert node.progress_s() is None  # no frame yet
    for i in range(12):
        node.step(i)
    t = np.asarray(robots["car1"].timestamps_s) - robots["car1"].timestamps_s[0]
    times = node._kf_times_s["car1"]
    assert len(times) >= 3
    assert node.progress_s() is None  # no server has answered: nothing is known to have arrived
    server = InProcessTransport(bus)
    server.publish(correction_key("car1"), encode(CorrectionMessage("car1", node.session, {"car1": 2})))
    node.poll()
    assert times[1] < node.progress_s() < times[2]  # keyframe 2 on is not acknowledged
    n = len(times)
    server.publish(correction_key("car1"), encode(CorrectionMessage("car1", node.session, {"car1": n})))
    node.poll()
    assert node.progress_s() == t[11]  # everything acknowledged: the last frame processed


def _journal_keyframes(path: Path) -> list[tuple[str, int]]:
    from shgm_slam.server.journal import Journal
    from shgm_slam.wire import decode

    out = []
    for payload in Journal(path).replay():
        m = decode(payload)
        if isinstance(m, KeyframeMessage):
            out.append((m.robot, m.kf_index))
    return out


def test_the_order_holds_across_a_server_killed_while_a_finished_robot_waited(robots, cfg, tmp_path: Path) -> None:
    """car1 runs its whole sequence and says it is done while car2 is half-way: the server queues car1's
    later keyframes (car2 may still send earlier ones) and dies. The restarted server must wait for car1's
    re-sent keyframes instead of taking car2's first: the journal ends up in the uninterrupted order."""
    n1, n2 = len(robots["car1"]), len(robots["car2"])

    def run(out: Path, kill: bool) -> list[tuple[str, int]]:
        clock, bus = FakeClock(), InProcessBus()
        server = ServerNode(cfg, InProcessTransport(bus), out, expect=2, reference="car1", clock=clock)
        nodes = fresh(robots, cfg, bus, clock)
        half = n2 // 2
        for i in range(n1):  # car1 all the way, car2 half-way, in step
            for r in ("car1", "car2") if i < half else ("car1",):
                nodes[r].step(i)
                clock.t += 0.01
                server.poll()
                nodes[r].poll()
        nodes["car1"].done()
        clock.t += 0.01
        server.poll()
        if kill:
            assert len(server._order) > 0  # car1's keyframes past car2's progress wait their turn
            server.transport.close()
            clock.t += 1.0
            server = ServerNode(cfg, InProcessTransport(bus), out, expect=2, reference="car1", clock=clock)
        for i in range(half, n2):
            nodes["car2"].step(i)
            clock.t += 0.05
            server.poll()
            for n in nodes.values():
                n.heartbeat()
                n.poll()
        nodes["car2"].done()
        for _ in range(200):
            clock.t += 0.25
            server.poll()
            for n in nodes.values():
                n.heartbeat()
                n.poll()
            if server.finished:
                break
        assert server.finished
        return _journal_keyframes(out / "journal.bin")

    plain = run(tmp_path / "plain", kill=False)
    killed = run(tmp_path / "killed", kill=True)
    assert killed == plain
