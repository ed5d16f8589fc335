"""Fixtures of the node tests: the tiny world's two cars, driven through server and robot nodes on the
in-process bus with a fake clock."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend, open_robots
from shgm_slam.server.node import ServerNode
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport


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
    c.backend.match_every_keyframes = 3  # car2 meets car1 once, briefly: two independent matches to enter
    # ... on one straight street: with stretches tracked every match there is one piece of evidence
    # (backend/stretches.py); these tests are about the server's mechanics, so matches count by their objects
    c.backend.stretch_turn_deg = None
    return c


def drive(server: ServerNode, nodes: dict[str, RobotNode], frames: dict[str, range], clock: FakeClock) -> None:
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


def finish(server: ServerNode, nodes: dict[str, RobotNode], clock: FakeClock) -> None:
    for n in nodes.values():
        n.done()
    for _ in range(5):
        clock.t += 0.5
        server.poll()
        for n in nodes.values():
            n.poll()
    assert server.finished


def fresh(robots, cfg, bus, clock, names=("car1", "car2")) -> dict[str, RobotNode]:
    nodes = {r: RobotNode(make_frontend(r, robots[r], cfg), InProcessTransport(bus), clock=clock) for r in names}
    for n in nodes.values():
        n.hello()
    return nodes


@pytest.fixture(scope="module")
def uninterrupted_run(robots, cfg, tmp_path_factory) -> tuple[ServerNode, dict[str, RobotNode]]:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path_factory.mktemp("plain"), expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    drive(server, nodes, {r: range(len(robots[r])) for r in nodes}, clock)
    finish(server, nodes, clock)
    return server, nodes


@pytest.fixture(scope="module")
def uninterrupted(uninterrupted_run) -> ServerNode:
    return uninterrupted_run[0]


def fused(server: ServerNode, robot: str) -> np.ndarray:
    _, T = server.fused_trajectory(robot)
    assert T is not None, f"{robot} not placed"
    return T


