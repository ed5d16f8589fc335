"""A placed pair's re-matches over the querying robot's recent window (``queries.RECENT_WINDOW_SUBMAPS``):
closures stay right at their place while the two robots' odometries drift apart; one rigid transform over
both whole graphs does not."""

from __future__ import annotations

import numpy as np
import pytest

import shgm_slam.server.map_server as map_server
import shgm_slam.server.queries as query_plan
from shgm_slam.config import ShgmConfig
from shgm_slam.geometry import se3
from shgm_slam.graph.extraction import ObjectObservations
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.map_server import MapServer

STEP_M = 2.0
LENGTH_M = 560.0
SCALE_B = 1.04  # robot b's odometry reads every step 4 % long (a depth-scale drift)


def _street(seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) objects along a straight street (KITTI camera frame: x right, y down, z forward), (N,) labels:
    poles every 9 m and trees every 7 m (rows that align again under a shift), scattered buildings, signs
    and cars."""
    rng = np.random.default_rng(seed)
    z_pole, z_tree = np.arange(0.0, LENGTH_M + 40, 9.0), np.arange(3.0, LENGTH_M + 40, 7.0)
    z_rest = rng.uniform(0.0, LENGTH_M + 40, 90)
    pos = np.concatenate([
        np.stack([np.full(z_pole.size, -7.0), np.full(z_pole.size, -3.0), z_pole], axis=1),
        np.stack([np.full(z_tree.size, 8.0), np.full(z_tree.size, -2.0), z_tree], axis=1),
        np.stack([rng.choice([-16.0, 17.0], z_rest.size) + rng.normal(0, 2, z_rest.size),
                  rng.normal(-2.0, 0.5, z_rest.size), z_rest], axis=1),
    ])  # fmt: skip
    labels = np.concatenate([np.full(z_pole.size, 5), np.full(z_tree.size, 8), rng.choice([2, 7, 13], z_rest.size)])
    return pos, labels


def _drive(offset_m: float, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, 4, 4) true camera poses straight along z from ``offset_m``, and the odometry's (from the identity),
    whose steps are ``scale`` times too long."""
    n = int(LENGTH_M / STEP_M)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 2, 3] = offset_m + STEP_M * np.arange(n)
    T_odom = np.tile(np.eye(4), (n, 1, 1))
    T_odom[:, 2, 3] = scale * STEP_M * np.arange(n)
    return T, T_odom


def _messages(robot: str, T: np.ndarray, T_odom: np.ndarray, pos: np.ndarray, labels: np.ndarray):
    """Keyframe messages of ``robot`` at true poses ``T`` whose odometry says ``T_odom``: it sees the objects within
    25 m, with 0.3 m of noise, each at the place its odometry puts it."""
    rng = np.random.default_rng(len(robot))
    graph = SemanticGraph(5.0, 10.0)
    for k, (T_k, T_odom_k) in enumerate(zip(T, T_odom, strict=True)):
        seen = np.linalg.norm(pos - T_k[:3, 3], axis=1) < 25.0
        cam = se3.transform_points(se3.inverse(T_k), pos[seen]) + rng.normal(0, 0.3, (seen.sum(), 3))
        obs = ObjectObservations(labels[seen].astype(np.int64), cam, se3.transform_points(T_odom_k, cam),
                                 np.full(seen.sum(), 2000), np.ones((seen.sum(), 3)))  # fmt: skip
        yield KeyframeMessage(robot, k, k, 0.1 * k, T_odom_k, graph.add_keyframe(k, T_odom_k, obs),
                              np.array([0.0, -1.0, 0.0]))  # fmt: skip


def _run(window_submaps: int, monkeypatch: pytest.MonkeyPatch) -> tuple[MapServer, list, dict, int]:
    """The convoy driven through a map server: (server, match records, true poses, b's keyframe when placed)."""
    monkeypatch.setattr(query_plan, "RECENT_WINDOW_SUBMAPS", window_submaps)
    pos, labels = _street()
    T_a, odo_a = _drive(10.0, 1.0)
    T_b, odo_b = _drive(0.0, SCALE_B)
    cfg = ShgmConfig()
    cfg.backend.stretch_turn_deg = None  # one straight street: counted by stretches, b would never be confirmed
    server = MapServer(["a", "b"], cfg)
    records, placed_at = [], None
    for msg_a, msg_b in zip(_messages("a", T_a, odo_a, pos, labels), _messages("b", T_b, odo_b, pos, labels),
                            strict=True):  # fmt: skip
        for msg in (msg_a, msg_b):
            records += server.receive(msg)
        if placed_at is None and server.is_placed("b"):
            placed_at = msg_b.kf_index
    assert placed_at is not None and placed_at < 100, "the pair must be placed early for this test to mean anything"
    return server, records, {"a": T_a, "b": T_b}, placed_at


def test_recent_window_keeps_later_closures_right_under_scale_drift(monkeypatch):
    server, records, truth, placed_at = _run(map_server.RECENT_WINDOW_SUBMAPS, monkeypatch)
    queries = [r.query for r in records]
    assert map_server.WINDOW_QUERY in queries and "whole" not in queries[len(queries) // 2 :]
    assert any(r.accepted for r in records if r.query == map_server.WINDOW_QUERY)
    errors = []
    for c in server._pose_graph.closures():
        if c.robot_a != c.robot_b and c.status.value == "accepted" and max(c.kf_a, c.kf_b) > placed_at + 60:
            T_true = se3.inverse(truth[c.robot_a][c.kf_a]) @ truth[c.robot_b][c.kf_b]
            errors.append(float(np.linalg.norm(c.T_a_b[:3, 3] - T_true[:3, 3])))
    assert len(errors) >= 5
    assert np.percentile(errors, 90) < 3.0, np.round(np.sort(errors), 1)


def test_recent_window_cost_does_not_grow_with_the_maps(monkeypatch):
    """A placed pair's re-match holds the querying robot's recent window and the partner's nodes near it: the
    same size at the end of the drive as early on, a small part of graphs that keep growing."""
    server, records, _, _ = _run(map_server.RECENT_WINDOW_SUBMAPS, monkeypatch)
    window = [r for r in records if r.query == map_server.WINDOW_QUERY]
    early, late = window[: len(window) // 3], window[-len(window) // 3 :]
    whole_a, whole_b = len(server.graph("a")), len(server.graph("b"))
    assert max(r.nodes_b for r in late) < 0.35 * whole_b and max(r.nodes_a for r in late) < 0.35 * whole_a
    assert np.mean([r.nodes_a + r.nodes_b for r in late]) < 1.3 * np.mean([r.nodes_a + r.nodes_b for r in early])


def test_unclosed_windows_are_older_than_the_recent_window_hold_no_closure_and_come_in_turn(monkeypatch):
    cfg = ShgmConfig()
    w = map_server.RECENT_WINDOW_SUBMAPS * cfg.backend.submap_keyframes
    server = MapServer(["a", "b"], cfg)
    closed = np.array([5, 2 * w + 3])  # windows 0 and 2 are tied by closures
    monkeypatch.setattr(server._pose_graph, "closure_keyframes", lambda robot: closed)
    server._T_odom_kf["b"] = [np.eye(4)] * (5 * w + 7)  # windows 0..3 lie wholly before the recent one
    seen = set()
    every = cfg.backend.match_every_keyframes
    for n_kf in range(5 * w + 7, 6 * w - 10, every):  # the open windows stay 1 and 3 (0 and 2 are closed)
        server._T_odom_kf["b"] = [np.eye(4)] * n_kf
        kfs = server._unclosed_window("b")
        assert kfs is not None and kfs.size == w and kfs[-1] < n_kf - w
        assert not np.isin(closed, kfs).any()
        seen.add(int(kfs[0]))
    assert seen == {w, 3 * w}  # each open window in turn
    server._T_odom_kf["b"] = [np.eye(4)] * (2 * w - 1)
    assert server._unclosed_window("b") is None  # nothing older than the recent window yet
