"""The map server node and robot nodes on the in-process bus: resume after a robot or a server restart,
name clashes, malformed input, stale robots. Nothing may be lost and the result must equal an
uninterrupted run."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.agents import segment_agent
from shgm_slam.config import OdometryKind, load_config
from shgm_slam.errors import ConfigError, ProtocolError
from shgm_slam.messages import RobotState
from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend
from shgm_slam.scene_scale import effective_fields
from shgm_slam.server.node import CHECKPOINT_SHARE, CLASH_WINDOW_S, ServerNode
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import hello_key, keyframe_key
from shgm_slam.wire import decode, encode
from tests.server.conftest import FakeClock, drive, finish, fresh, fused


def test_uninterrupted_nodes_place_both_robots(uninterrupted: ServerNode, robots) -> None:
    s = uninterrupted.summary()
    assert s["robots"]["car2"]["placed"] == ["car2"]
    gt = robots["car2"].gt_poses
    gt_shared = np.linalg.inv(robots["car1"].gt_poses[0]) @ gt
    err = np.linalg.norm(fused(uninterrupted, "car2")[:, :3, 3] - gt_shared[:, :3, 3], axis=1)
    assert np.nanmedian(err) < 2.0
    assert s["traffic"]["bytes_per_keyframe"] < 5000


def test_robot_killed_and_restarted_resumes_without_loss(uninterrupted, robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2  # both robots cut at the same frame: the same order as uninterrupted
    drive(server, nodes, {r: range(k) for r in nodes}, clock)
    held = server.map.received("car2")
    assert held > 0
    nodes["car2"].transport.close()  # killed
    clock.t += CLASH_WINDOW_S + 0.5
    restarted = RobotNode(make_frontend("car2", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    restarted.hello()
    server.poll()
    restarted.poll()
    nodes["car2"] = restarted
    drive(server, nodes, {"car2": range(k)}, clock)  # its first half again: the server ignores it all
    assert server.map.received("car2") == held
    drive(server, nodes, {r: range(k, len(robots[r])) for r in nodes}, clock)
    finish(server, nodes, clock)
    assert server.map.received("car2") == uninterrupted.map.received("car2")
    np.testing.assert_allclose(fused(server, "car2"), fused(uninterrupted, "car2"), atol=0.05)


def test_a_done_sent_while_the_restart_is_held_back_is_sent_again(robots, cfg, tmp_path: Path) -> None:
    """A robot restarted within the clash window runs its whole (short) sequence while the server still
    holds its hello back, so the server ignores its keyframes and its done; the robot must send both again
    (the done until the server's status says it holds it) and the server must finish."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    drive(server, nodes, {"car1": range(len(robots["car1"]))}, clock)
    drive(server, nodes, {"car2": range(5)}, clock)
    nodes["car2"].transport.close()  # killed
    restarted = RobotNode(make_frontend("car2", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    nodes["car2"] = restarted
    restarted.hello()
    clock.t += 1.0
    server.poll()
    restarted.poll()  # it has heard the server's status: no new server session will make it send anything
    for i in range(len(robots["car2"])):
        restarted.step(i)
        clock.t += 0.01
        server.poll()
        restarted.poll()
    nodes["car1"].done()
    restarted.done()  # the old session was heard < CLASH_WINDOW_S ago: held, so this done is ignored
    server.poll()
    assert server.robots["car2"].session != restarted.session
    for _ in range(100):
        clock.t += 0.25
        for n in nodes.values():
            n.heartbeat()
        server.poll()
        for n in nodes.values():
            n.poll()
        if server.finished:
            break
    assert server.finished
    assert server.robots["car2"].session == restarted.session
    assert server.map.received("car2") == len(restarted._payloads["car2"])
    assert restarted.resent_done >= 1


def test_server_killed_and_restarted_recovers_from_its_journal(uninterrupted, robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    first = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2
    drive(first, nodes, {r: range(k) for r in nodes}, clock)
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
    drive(second, nodes, {r: range(k, len(robots[r])) for r in nodes}, clock)
    finish(second, nodes, clock)
    assert second.map.received("car2") == uninterrupted.map.received("car2")
    np.testing.assert_allclose(fused(second, "car2"), fused(uninterrupted, "car2"), atol=0.05)


def test_name_clash_is_refused_and_the_newcomer_told(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
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


def test_a_robot_on_other_front_end_settings_is_refused_with_the_fix(robots, cfg, tmp_path: Path) -> None:
    """A robot started with another --config than the server (here: its keyframes twice as far apart) builds
    graphs the server's settings do not describe: refused, the robot told to use the server's file."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    other = cfg.model_copy(deep=True)
    other.keyframes.distance_m = 2 * cfg.keyframes.distance_m
    stray = RobotNode(make_frontend("car2", robots["car2"], other), InProcessTransport(bus), clock=clock)
    stray.hello()
    server.poll()
    with pytest.raises(ProtocolError, match=r"differ from the map server's.*--config"):
        stray.poll()
    assert "car2" not in server.robots and server.reference is None  # never a session, never the reference
    for _ in range(3):  # its heartbeats are refused without a new line each
        stray.hello()
        server.poll()
    assert server.traffic.refused == 1
    # what only the robot process decides (its odometry, its threads) is not compared
    own = cfg.model_copy(deep=True)
    own.odometry.kind, own.odometry.icp_threads = OdometryKind.KISS_ICP, 1
    assert own.front_end_digest("car2") == cfg.front_end_digest("car2")


def test_a_restart_with_other_front_end_settings_is_refused_not_resumed_empty(robots, cfg, tmp_path: Path) -> None:
    """The journal's hellos carry the digest of the settings the robots ran with: a server restarted on the
    folder with another --config used to refuse each replayed hello and resume on an empty map."""
    clock, bus = FakeClock(), InProcessBus()
    first = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    drive(first, nodes, {r: range(3) for r in nodes}, clock)
    first.transport.close()  # killed
    journal = (tmp_path / "journal.bin").read_bytes()
    other = cfg.model_copy(deep=True)
    other.keyframes.distance_m = 2 * cfg.keyframes.distance_m
    with pytest.raises(ConfigError, match=r"other front-end settings.*--config it ran with.*--overwrite"):
        ServerNode(other, InProcessTransport(InProcessBus()), tmp_path, expect=2, clock=clock)
    assert (tmp_path / "journal.bin").read_bytes() == journal  # kept for a restart with the right --config
    second = ServerNode(cfg, InProcessTransport(InProcessBus()), tmp_path, expect=2, clock=clock)
    assert set(second.robots) == {"car1", "car2"}


def test_the_servers_config_records_each_robots_derived_values(uninterrupted: ServerNode, robots) -> None:
    """config.yaml of a server's folder reproduces every robot's front end, as `run`'s does."""
    loaded = load_config(uninterrupted.writer.root / "config.yaml")
    assert set(loaded.robots) == set(robots)
    for name in robots:
        front = make_frontend(name, robots[name], uninterrupted.cfg)
        derived = effective_fields(front.cfg)
        mine = loaded.for_robot(name)
        for stage, values in derived.items():
            for field, value in values.items():
                assert getattr(getattr(mine, stage), field) == value, (name, stage, field)


def test_malformed_and_misaddressed_messages_are_refused_not_fatal(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    server.poll()
    t = InProcessTransport(bus)
    t.publish(keyframe_key("car1"), b"\x00garbage")
    t.publish(keyframe_key("car1"), b"")
    t.publish(hello_key("car2"), encode(nodes["car1"]._hello_message()))  # car1's hello on car2's key
    server.poll()
    assert server.traffic.refused == 3
    drive(server, nodes, {"car1": range(10)}, clock)
    assert server.map.received("car1") > 0


def test_silent_robot_goes_stale_and_comes_back(robots, cfg, tmp_path: Path) -> None:
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock, stale_after_s=5.0)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    drive(server, nodes, {"car1": range(5)}, clock)
    clock.t += 6.0
    server.poll()
    assert server.robots["car1"].state is RobotState.STALE
    drive(server, nodes, {"car1": range(5, 10)}, clock)
    assert server.robots["car1"].state is RobotState.ACTIVE


def test_results_are_rewritten_every_few_keyframes_unless_a_rewrite_costs_too_much(robots, cfg, tmp_path: Path,
                                                                                  monkeypatch) -> None:
    def run(write_s: float) -> int:
        clock, bus = FakeClock(), InProcessBus()
        server = ServerNode(cfg, InProcessTransport(bus), tmp_path / f"w{write_s}", expect=2, clock=clock,
                            write_every_keyframes=5)  # fmt: skip
        original = ServerNode.write_results

        def slow(self):
            original(self)
            self.timings_ms["write"][-1] += write_s * 1e3  # as if the rewrite had taken write_s longer

        monkeypatch.setattr(ServerNode, "write_results", slow)
        drive(server, fresh(robots, cfg, bus, clock), {r: range(40) for r in ("car1", "car2")}, clock)
        monkeypatch.setattr(ServerNode, "write_results", original)
        return len(server.timings_ms["write"])

    t0 = time.perf_counter()
    cheap = run(0.0)
    elapsed = time.perf_counter() - t0
    assert cheap >= 2
    # a rewrite "taking" far longer than the whole drive leaves room for no second one
    assert run(10 * elapsed / CHECKPOINT_SHARE) == 1


def _car2_stopped_early(robots, cfg, out: Path, min_closures_to_anchor: int):
    """Server and robot nodes after car1's whole drive and car2's first 30 frames, matched every 10 keyframes
    (the default: car2's matches in 30 frames all find the same objects)."""
    cfg = cfg.model_copy(deep=True)
    cfg.backend.match_every_keyframes = 10
    cfg.backend.min_closures_to_anchor = min_closures_to_anchor
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), out, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    drive(server, nodes, {"car1": range(len(robots["car1"])), "car2": range(30)}, clock)
    finish(server, nodes, clock)
    return server, nodes


def test_a_robot_waiting_for_independent_matches_hears_so_in_the_status(robots, cfg, tmp_path: Path) -> None:
    """car2 stopped early with the default anchoring: its matches all found the same objects, so it is not
    placed; server.json says why and the robot process learns it is waiting (the status)."""
    server, nodes = _car2_stopped_early(robots, cfg, tmp_path, min_closures_to_anchor=2)
    assert not server.map.is_placed("car2") and server.map.waiting_note("car2") is not None
    s = server.summary()
    assert s["robots"]["car2"]["placed"] == [] and s["robots"]["car2"]["waiting"] == [server.map.waiting_note("car2")]
    assert s["robots"]["car1"]["measured_drift_deg_per_100m"] == {}  # no loop closed: the prior holds
    assert nodes["car2"].waiting_agents == ("car2",) and nodes["car1"].waiting_agents == ()


def test_a_provisional_placement_reaches_status_server_json_and_the_robot(robots, cfg, tmp_path: Path) -> None:
    """car2 stopped early, placed from one piece of evidence (a server told to trust single matches): the
    status, server.json, the server's fused file and the robot process all say it is provisional."""
    from shgm_slam.io.trajectories import read_comments

    server, nodes = _car2_stopped_early(robots, cfg, tmp_path, min_closures_to_anchor=1)
    assert server.map.placement("car2").provisional
    s = server.summary()
    assert s["robots"]["car2"]["placed"] == ["car2"] and s["robots"]["car2"]["provisional"] == ["car2"]
    assert s["robots"]["car1"]["provisional"] == []
    assert nodes["car2"].provisional_agents == ("car2",) and nodes["car1"].provisional_agents == ()
    assert read_comments(tmp_path / "car2_fused_tum.txt")[0].startswith("provisional: car2 is placed provisionally")
    assert server.provisional_note("car1") is None


def _segment_keyframes(robots, cfg, clock, bus, name: str, agents: int) -> tuple[RobotNode, list[bytes]]:
    """A node of robot ``name`` on ``bus`` that has said hello and sent its first keyframe, and keyframe 0 of
    ``agents`` trajectory segments of it (that real keyframe relabelled per segment)."""
    node = RobotNode(make_frontend(name, robots["car1"], cfg), InProcessTransport(bus), clock=clock)
    node.hello()
    i = 0
    while not node._payloads:
        node.step(i)
        i += 1
    first = decode(node._payloads[name][0])
    return node, [encode(replace(first, robot=segment_agent(name, k))) for k in range(agents)]


def test_segments_beyond_a_robots_share_are_dropped_and_the_robot_told(robots, cfg, tmp_path: Path) -> None:
    """A robot whose odometry keeps failing starts segment after segment; each robot may hold only its share of
    the pose graph's agents (26 robots expected: 2 each). The third segment's keyframes are dropped (logged once,
    in server.json), not an exception that stops the server; the status tells the robot its share, so its front
    end stops at its last allowed segment and it neither re-sends nor waits for the dropped one."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=26, clock=clock, order_keyframes=False)
    node, payloads = _segment_keyframes(robots, cfg, clock, bus, "car1", 4)
    sender = InProcessTransport(bus)
    for p in payloads[1:]:
        sender.publish(keyframe_key("car1"), p)
    server.poll()
    assert server.map.agents == ["car1", "car1#1"]
    assert set(server.dropped_segments) == {"car1#2", "car1#3"}
    assert "share of 2 trajectory segments" in server.dropped_segments["car1#2"]
    refused = server.traffic.refused
    sender.publish(keyframe_key("car1"), payloads[2])  # sent again: dropped again, not refused again
    server.poll()
    assert server.traffic.refused == refused
    server._broadcast_status()
    node._payloads["car1#2"] = [payloads[2]]  # as if its front end had made that segment before the status came
    node.poll()
    assert node.front.max_segments == 2
    assert not node._allowed("car1#2") and node._allowed("car1#1")
    summary = server.summary()
    assert summary["segments_allowed"] == 2
    assert set(summary["robots"]["car1"]["dropped_segments"]) == {"car1#2", "car1#3"}


def test_a_robot_expected_later_shrinks_every_robots_share_at_once(robots, cfg, tmp_path: Path) -> None:
    """A camera added to a live run: the map server waits for one more robot and tells the running ones their
    smaller share of the pose graph before their next keyframe; it never waits for fewer than before."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=13, clock=clock, order_keyframes=False)
    node, _ = _segment_keyframes(robots, cfg, clock, bus, "car1", 1)
    server.poll()
    server._broadcast_status()
    node.poll()
    assert node.front.max_segments == 4
    server.expect_robots(26)
    node.poll()
    assert server.expect == 26 and node.front.max_segments == 2
    server.expect_robots(2)
    assert server.expect == 26 and server.segments_allowed() == 2


def test_a_robot_that_finds_the_pose_graph_full_is_refused(robots, cfg, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr("shgm_slam.server.node.MAX_AGENTS", 3)  # the pose graph's 52 agents, reached sooner
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock, order_keyframes=False)
    _, first = _segment_keyframes(robots, cfg, clock, bus, "car1", 3)
    sender = InProcessTransport(bus)
    for p in first[1:]:
        sender.publish(keyframe_key("car1"), p)
    server.poll()
    assert len(server.map.agents) == 3
    late, _ = _segment_keyframes(robots, cfg, clock, bus, "car2", 1)
    server.poll()
    with pytest.raises(ProtocolError, match="at most 3 agents"):
        late.poll()
    assert "car2" in server.dropped_segments and len(server.map.agents) == 3
