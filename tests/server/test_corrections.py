"""Corrections between server and robot nodes: robots end with exactly the server's fused trajectory,
corrections carry only what moved, and a lost correction is repaired by a full one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shgm_slam.messages import CorrectionMessage
from shgm_slam.server.node import ServerNode
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.wire import decode
from tests.server.conftest import FakeClock, drive, finish, fresh


def test_robots_end_with_exactly_the_servers_fused_trajectory(uninterrupted_run) -> None:
    server, nodes = uninterrupted_run
    for name, node in nodes.items():
        _, T = server.fused_trajectory(name)
        assert T is not None
        np.testing.assert_array_equal(node.fused(), T)  # bit for bit, NaN where not placed


def test_corrections_carry_only_what_moved(uninterrupted_run) -> None:
    server, nodes = uninterrupted_run
    t = server.traffic
    kf = server.map.received("car1") + server.map.received("car2")
    # sending every placed keyframe's pose in each correction would cost ~100 B per keyframe each time;
    # here all corrections together cost little more than one pose per keyframe and a few full resends
    assert t.sent_by_kind["correction"] < 8 * 100 * kf, t.sent_by_kind
    assert sum(n.bytes_received["correction"] for n in nodes.values()) == t.sent_by_kind["correction"]


def test_a_lost_correction_is_repaired_by_a_full_one(robots, cfg, tmp_path: Path) -> None:
    cfg = cfg.model_copy(deep=True)
    cfg.backend.min_closures_to_anchor = 1  # car2 placed early: corrections flow while it still drives
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2
    drive(server, nodes, {r: range(k) for r in nodes}, clock)
    lost: list[int] = []
    i = k
    while i < min(len(s) for s in robots.values()) and not nodes["car2"]._resync:
        for node in nodes.values():
            node.step(i)
        clock.t += 0.3
        server.poll()
        for key, payload in nodes["car2"]._inbox.drain():  # car2's first delta after the cut is lost
            msg = decode(payload)
            if not lost and isinstance(msg, CorrectionMessage) and msg.seq > 0 and not msg.full:
                lost.append(msg.seq)
                continue
            nodes["car2"]._inbox.put(key, payload)
        for node in nodes.values():
            node.poll()
        i += 1
    assert lost and nodes["car2"]._resync  # noticed at the next correction
    drive(server, nodes, {r: range(i, len(robots[r])) for r in nodes}, clock)
    finish(server, nodes, clock)
    assert not nodes["car2"]._resync
    for name, node in nodes.items():
        np.testing.assert_array_equal(node.fused(), server.fused_trajectory(name)[1])
