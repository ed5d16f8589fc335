"""The map server node and robot nodes on the in-process bus: resume after a robot or a server restart,
name clashes, malformed input, stale robots. Nothing may be lost and the result must equal an
uninterrupted run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.errors import ProtocolError
from shgm_slam.messages import RobotState
from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend, open_robots
from shgm_slam.server.node import CLASH_WINDOW_S, ServerNode
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import hello_key, keyframe_key
from shgm_slam.wire import encode


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(scope="module")
def robots(tiny_scenario: Path):
    return open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}"])


@pytest.fixture(scope="module")
def cfg() -> ShgmConfig:
    c = ShgmConfig()
    c.odometry.kind = OdometryKind.GT
    c.backend.match_every_keyframes = 5
    return c


def _drive(server: ServerNode, nodes: dict[str, RobotNode], frames: dict[str, range], clock: FakeClock) -> None:
    """Step the robots' frames round-robin, the server polled after every frame."""
    its = {r: iter(f) for r, f in frames.items()}
    while its:
        for r in list(its):
            i = next(its[r], None)
            if i is None:
                del its[r]
                continue
            nodes[r].step(i)
            clock.t += 0.05
            server.poll()
            nodes[r].poll()


def _finish(server: ServerNode, nodes: dict[str, RobotNode], clock: FakeClock) -> None:
    for n in nodes.values():
        n.done()
    for _ in range(5):
        clock.t += 0.5
        server.poll()
        for n in nodes.values():
            n.poll()
    assert server.finished


def _fresh(robots, cfg, bus, clock, names=("car1", "car2")) -> dict[str, RobotNode]:
    nodes = {r: RobotNode(make_frontend(r, robots[r], cfg), InProcessTransport(bus), clock=clock) for r in names}
    for n in nodes.values():
        n.hello()
    return nodes


@pytest.fixture(scope="module")
def uninterrupted(robots, cfg, tmp_path_factory):
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path_factory.mktemp("plain"), expect=2, clock=clock)
    nodes = _fresh(robots, cfg, bus, clock)
    _drive(server, nodes, {r: range(len(robots[r])) for r in nodes}, clock)
    _finish(server, nodes, clock)
    return server


def _fused(server: ServerNode, robot: str) -> np.ndarray:
    _, T = server.fused_trajectory(robot)
    assert T is not None, f"{robot} not placed"
    return T


def test_uninterrupted_nodes_place_both_robots(uninterrupted: ServerNode, robots) -> None:
    s = uninterrupted.summary()
    assert s["robots"]["car2"]["placed"] == ["car2"]
    gt = robots["car2"].gt_poses
    gt_shared = np.linalg.inv(robots["car1"].gt_poses[0]) @ gt
    err = np.linalg.norm(_fused(uninterrupted, "car2")[:, :3, 3] - gt_shared[:, :3, 3], axis=1)
    assert np.nanmedian(err) < 2.0
    assert s["traffic"]["bytes_per_keyframe"] < 5000


def test_robot_killed_and_restarted_resumes_without_loss(uninterrupted, robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = _fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2  # both robots cut at the same frame: the same order as uninterrupted
    _drive(server, nodes, {r: range(k) for r in nodes}, clock)
    held = server.map.received("car2")
    assert held > 0
    nodes["car2"].transport.close()  # killed
    clock.t += CLASH_WINDOW_S + 0.5
    restarted = RobotNode(make_frontend("car2", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    restarted.hello()
    server.poll()
    restarted.poll()
    nodes["car2"] = restarted
    _drive(server, nodes, {"car2": range(k)}, clock)  # its first half again: the server ignores it all
    assert server.map.received("car2") == held
    _drive(server, nodes, {r: range(k, len(robots[r])) for r in nodes}, clock)
    _finish(server, nodes, clock)
    assert server.map.received("car2") == uninterrupted.map.received("car2")
    np.testing.assert_allclose(_fused(server, "car2"), _fused(uninterrupted, "car2"), atol=0.05)


def test_server_killed_and_restarted_recovers_from_its_journal(uninterrupted, robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    first = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = _fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2
    _drive(first, nodes, {r: range(k) for r in nodes}, clock)
    held = {a: first.map.received(a) for a in first.map.agents}
    matches = len(first.map.matches)
    first.transport.close()  # killed: nothing but its journal survives
    clock.t += 1.0
    second = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    assert second.recovered_messages > 0
    assert {a: second.map.received(a) for a in second.map.agents} == held
    assert len(second.map.matches) == matches
    second.poll()  # status with the new session: robots say hello again and re-send what is missing
    for n in nodes.values():
        n.poll()
    _drive(second, nodes, {r: range(k, len(robots[r])) for r in nodes}, clock)
    _finish(second, nodes, clock)
    assert second.map.received("car2") == uninterrupted.map.received("car2")
    np.testing.assert_allclose(_fused(second, "car2"), _fused(uninterrupted, "car2"), atol=0.05)


def test_name_clash_is_refused_and_the_newcomer_told(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    nodes = _fresh(robots, cfg, bus, clock, names=("car1",))
    server.poll()
    impostor = RobotNode(make_frontend("car1", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    clock.t += 0.2
    impostor.hello()
    server.poll()
    impostor.poll()  # held, not yet refused: it could be a restart
    clock.t += 0.3
    nodes["car1"].hello()  # the first process is alive: a clash
    server.poll()
    with pytest.raises(ProtocolError, match="in use by another running robot"):
        impostor.poll()
    nodes["car1"].poll()  # the original is unaffected
    assert server.robots["car1"].session == nodes["car1"].session
    assert server.traffic.refused == 1


def test_malformed_and_misaddressed_messages_are_refused_not_fatal(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    nodes = _fresh(robots, cfg, bus, clock, names=("car1",))
    server.poll()
    t = InProcessTransport(bus)
    t.publish(keyframe_key("car1"), b"\x00garbage")
    t.publish(keyframe_key("car1"), b"")
    t.publish(hello_key("car2"), encode(nodes["car1"]._hello_message()))  # car1's hello on car2's key
    server.poll()
    assert server.traffic.refused == 3
    _drive(server, nodes, {"car1": range(10)}, clock)
    assert server.map.received("car1") > 0


def test_silent_robot_goes_stale_and_comes_back(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock, stale_after_s=5.0)
    nodes = _fresh(robots, cfg, bus, clock, names=("car1",))
    _drive(server, nodes, {"car1": range(5)}, clock)
    clock.t += 6.0
    server.poll()
    assert server.robots["car1"].state is RobotState.STALE
    _drive(server, nodes, {"car1": range(5, 10)}, clock)
    assert server.robots["car1"].state is RobotState.ACTIVE
