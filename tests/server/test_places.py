"""Candidate places: keyframes that could share objects with a query, and a map server that matches only
those (loop queries of a drive that never returns cost nothing; a revisit is matched against its surroundings)."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.consistency import ConsistencyThresholds
from shgm_slam.config import ShgmConfig
from shgm_slam.geometry import se3
from shgm_slam.graph.extraction import ObjectObservations
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.places import free_path_m, near_keyframes, tolerance_m


def test_free_path_is_the_distance_to_the_nearest_tied_keyframe():
    path = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    np.testing.assert_allclose(free_path_m(path, np.array([1, 4])), [10, 0, 10, 10, 0, 10])
    np.testing.assert_allclose(free_path_m(path, np.array([5])), [50, 40, 30, 20, 10, 0])
    assert np.isinf(free_path_m(path, np.zeros(0, dtype=np.int64))).all()


def test_near_keyframes_uses_reach_plus_tolerance():
    th = ConsistencyThresholds(trans_m=5.0, trans_per_m=0.05)
    assert tolerance_m(100.0, th) == pytest.approx(10.0)
    query = np.array([[0.0, 0.0, 0.0]])
    cand = np.array([[0.0, 0.0, 29.0], [0.0, 0.0, 31.0], [0.0, 0.0, 100.0]])
    near = near_keyframes(query, cand, np.full((1, 3), 10.0), reach_m=20.0)
    np.testing.assert_array_equal(near, [True, False, False])
    near = near_keyframes(query, cand, np.array([[10.0, 10.0, np.inf]]), reach_m=20.0)  # unknown drift: always near
    np.testing.assert_array_equal(near, [True, False, True])
    assert near_keyframes(np.zeros((0, 3)), cand, 1.0, 1.0).tolist() == [False] * 3


def _out_and_back(step_m: float = 2.0, out_m: float = 700.0) -> np.ndarray:
    """(K, 4, 4) KITTI camera poses (y down, z forward): straight out along z, a U-turn, straight back."""
    n = int(out_m / step_m)
    T = np.tile(np.eye(4), (2 * n, 1, 1))
    T[:n, 2, 3] = step_m * np.arange(n)
    T[n:, :3, :3] = se3.rot_y(np.pi)  # facing back
    T[n:, 0, 3] = 8.0  # the other lane
    T[n:, 2, 3] = step_m * np.arange(n)[::-1]
    return T


def _landmarks(length_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    z = np.arange(0.0, length_m, 4.0)
    side = rng.choice([-12.0, 20.0], size=z.size) + rng.normal(0, 2, z.size)
    pos = np.stack([side, rng.normal(-2.0, 1.0, z.size), z + rng.normal(0, 1, z.size)], axis=1)
    return pos, rng.choice([2, 5, 7, 8, 13], size=z.size)


def _drifting(T: np.ndarray, yaw_deg_per_step: float) -> np.ndarray:
    """Odometry of the drive ``T`` (K, 4, 4) that turns ``yaw_deg_per_step`` too far every step."""
    steps = se3.make_pose(se3.rot_y(np.radians(yaw_deg_per_step)), np.zeros(3)) @ (se3.inverse(T[:-1]) @ T[1:])
    out = [T[0]]
    for step in steps:
        out.append(out[-1] @ step)
    return np.stack(out)


def _messages(T: np.ndarray, T_odom: np.ndarray, pos: np.ndarray, labels: np.ndarray, range_m: float = 25.0):
    """Keyframe messages of a robot at true poses ``T`` whose odometry says ``T_odom``, seeing ``pos``."""
    graph = SemanticGraph(5.0, 10.0)
    for k, (T_k, T_odom_k) in enumerate(zip(T, T_odom, strict=True)):
        seen = np.linalg.norm(pos - T_k[:3, 3], axis=1) < range_m
        cam = se3.transform_points(se3.inverse(T_k), pos[seen])
        obs = ObjectObservations(labels[seen].astype(np.int64), cam, pos[seen], np.full(seen.sum(), 2000),
                                 np.ones((seen.sum(), 3)))  # fmt: skip
        update = graph.add_keyframe(k, T_odom_k, obs)
        up = T_odom_k[:3, :3] @ (T_k[:3, :3].T @ np.array([0.0, -1.0, 0.0]))
        yield KeyframeMessage("car", k, k, 0.1 * k, T_odom_k, update, up)


def test_loop_queries_match_only_the_older_graph_near_the_submap():
    T = _out_and_back()
    pos, labels = _landmarks(720.0)
    server = MapServer(["car"], ShgmConfig())
    n_out = len(T) // 2
    loops_out, loops_back = [], []
    for msg in _messages(T, _drifting(T, 0.02), pos, labels):
        for rec in server.receive(msg):
            if rec.query == "loop":
                (loops_out if msg.kf_index < n_out else loops_back).append((rec, len(server.graph("car"))))
    assert not loops_out  # driving away: no older keyframe could share an object
    assert loops_back  # coming back: the outbound lane is near
    late = loops_back[len(loops_back) // 2 :]
    # the older graph holds the whole outbound lane; only its stretch near the submap is matched
    assert max(rec.nodes_a for rec, _ in late) < 0.25 * min(size for _, size in late)
    assert any(rec.accepted for rec, _ in loops_back), [rec.reason for rec, _ in loops_back]


def test_object_range_follows_the_graph_as_it_grows():
    """The object range (95th percentile of node-to-anchor distance) is remembered per graph version: every
    answer equals the whole graph's, asked once or many times, before and after further keyframes."""
    T = _out_and_back(out_m=120.0)
    pos, labels = _landmarks(130.0)
    server = MapServer(["car"], ShgmConfig())
    assert server.object_range_m("car") is None
    answers = []
    for msg in _messages(T, T, pos, labels):
        server.receive(msg)
        origins = server.keyframe_poses("car")[server.graph_anchors("car"), :3, 3]
        expected = np.percentile(np.linalg.norm(server.graph("car").positions_xyz - origins, axis=1), 95)
        assert server.object_range_m("car") == pytest.approx(expected) == server.object_range_m("car")
        answers.append(expected)
    assert len(set(np.round(answers, 6))) > 3  # it did change as the graph grew
