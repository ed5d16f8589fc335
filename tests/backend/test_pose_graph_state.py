"""Pose graph snapshots: a graph restored from ``state()`` answers and votes like the original."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.errors import BackendError
from shgm_slam.geometry.se3 import make_pose, rot_y
from tests.backend.test_pose_graph import noisy_odometry, route, true_closures, wrong_closure

N = 40


@pytest.fixture(scope="module")
def events():
    """Keyframes of a and b (and c, added at run time), true and wrong a-b closures, a loop closure of a."""
    rng = np.random.default_rng(3)
    gt_a = route(N, np.eye(4))
    gt_b = gt_a[::-1] @ make_pose(rot_y(np.pi), [3.0, 0.0, 0.0])
    gt_c = gt_a @ make_pose(rot_y(0.1), [-3.0, 0.0, 1.0])
    odo = {"a": noisy_odometry(gt_a, rng), "b": noisy_odometry(gt_b, rng), "c": noisy_odometry(gt_c, rng)}
    closures = [("a", i, "b", j, T) for i, j, T in true_closures(gt_a, gt_b, rng, every=4)]
    closures += [("a", i, "b", j, T) for i, j, T in (wrong_closure(rng, N, N) for _ in range(4))]
    closures += [("c", i, "a", j, T) for j, i, T in true_closures(gt_a, gt_c, rng, every=5)]
    out = []
    for k in range(N):
        out += [("kf", r, k, odo[r][k]) for r in ("a", "b", "c")]
        out += [("closure", c) for c in closures if max(c[1], c[3]) == k]
    return out, odo


def play(pg: MultiRobotPoseGraph, events) -> list:
    decisions = []
    for ev in events:
        if ev[0] == "kf":
            _, robot, k, T = ev
            if robot not in pg.keys.names:
                pg.add_robot(robot)
            pg.add_keyframe(robot, k, T)
        else:
            a, i, b, j, T = ev[1]
            decisions.append(pg.add_inter_robot_closure(a, i, b, j, T, num_inliers=6 + i % 5, match_id=i))
    return decisions


def restored(pg: MultiRobotPoseGraph, odo, k: int) -> MultiRobotPoseGraph:
    fresh = MultiRobotPoseGraph(["a", "b"])
    fresh.restore_state(pg.state(), {r: odo[r][:k] for r in pg.keys.names})
    return fresh


def test_restored_graph_continues_exactly_like_the_original(events) -> None:
    evs, odo = events
    whole = MultiRobotPoseGraph(["a", "b"])
    d_whole = play(whole, evs)
    cut = next(i for i, ev in enumerate(evs) if ev[0] == "kf" and ev[2] == N // 2)
    first = MultiRobotPoseGraph(["a", "b"])
    d_first = play(first, evs[:cut])
    k = N // 2
    again = restored(first, odo, k)
    for r, T in first.estimate().items():
        # the original is iSAM2 partly relinearized (beyond 1 mrad or 0.1 m: a robot just anchored, here c,
        # may be ~0.1 m from convergence), the restored one a batch solve from it
        np.testing.assert_allclose(again.estimate()[r], T, atol=0.15)
    d_again = play(again, evs[cut:])
    assert [(d.accepted, d.reason) for d in d_first + d_again] == [(d.accepted, d.reason) for d in d_whole]
    assert [(c.status, c.reason, c.in_graph) for c in again.closures()] == [
        (c.status, c.reason, c.in_graph) for c in whole.closures()
    ]
    assert again.stats().anchored_robots == whole.stats().anchored_robots == ("a", "b", "c")
    for r, T in whole.estimate().items():
        np.testing.assert_allclose(again.estimate()[r][:, :3, 3], T[:, :3, 3], atol=5e-3)


def test_state_of_an_empty_graph_restores() -> None:
    pg = MultiRobotPoseGraph(["a", "b"])
    again = MultiRobotPoseGraph(["a", "b"])
    again.restore_state(pg.state(), {"a": np.zeros((0, 4, 4)), "b": np.zeros((0, 4, 4))})
    again.add_keyframe("a", 0, np.eye(4))
    assert again.is_anchored("a") and not again.is_anchored("b")


def test_inconsistent_state_or_a_used_graph_is_refused(events) -> None:
    evs, odo = events
    pg = MultiRobotPoseGraph(["a", "b"])
    play(pg, evs)
    state = pg.state()
    short = {r: odo[r][: N // 2] for r in ("a", "b", "c")}  # closures refer to keyframes that are missing
    with pytest.raises(BackendError, match="keyframes that do not exist"):
        MultiRobotPoseGraph(["a", "b"]).restore_state(state, short)
    with pytest.raises(BackendError, match="does not fit"):
        MultiRobotPoseGraph(["b", "a"]).restore_state(state, odo)
    bad = replace(state, T_shared_kf={**state.T_shared_kf, "b": state.T_shared_kf["b"][:-1]})
    with pytest.raises(BackendError, match="estimate"):
        MultiRobotPoseGraph(["a", "b"]).restore_state(bad, odo)
    with pytest.raises(BackendError, match="fresh"):
        pg.restore_state(state, odo)
    bad = replace(state, up_odom={**state.up_odom, "a": np.zeros((2, 3))})
    with pytest.raises(BackendError, match="normals"):
        MultiRobotPoseGraph(["a", "b"]).restore_state(bad, odo)


def test_attitude_factors_come_back_with_the_ground_normals(events) -> None:
    """Keyframes that measured their ground normal keep their attitude factors through a snapshot."""
    evs, odo = events
    pg = MultiRobotPoseGraph(["a", "b"], attitude_warmup=5)
    rng = np.random.default_rng(5)
    for ev in evs:
        if ev[0] == "kf":
            _, robot, k, T = ev
            if robot not in pg.keys.names:
                pg.add_robot(robot)
            up_cam = np.array([0.0, -1.0, 0.0]) + rng.normal(0.0, 0.01, 3)  # camera y points down
            up = T[:3, :3] @ (up_cam / np.linalg.norm(up_cam)) if k % 3 else None  # some keyframes none
            pg.add_keyframe(robot, k, T, up)
        else:
            a, i, b, j, T = ev[1]
            pg.add_inter_robot_closure(a, i, b, j, T, num_inliers=6 + i % 5, match_id=i)
    state = pg.state()
    assert np.isnan(state.up_odom["a"][0]).all() and np.isfinite(state.up_odom["a"][1]).all()
    again = MultiRobotPoseGraph(["a", "b"], attitude_warmup=5)
    again.restore_state(state, odo)
    assert pg.stats().attitude_factors > 0
    assert again.stats().attitude_factors == pg.stats().attitude_factors
    for r, T in pg.estimate().items():  # iSAM2 (relinearization threshold 0.1) against a batch solve from it
        np.testing.assert_allclose(again.estimate()[r][:, :3, 3], T[:, :3, 3], atol=0.3)


def test_restored_graph_keeps_the_objects_behind_each_closure() -> None:
    """Restored with the closures' supports, a match that re-finds objects of an earlier one still does not
    count as independent (nor anchor b); restored without them it would."""
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    odo = {r: np.stack([make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]) for k in range(4)]) for r in ("a", "b")}
    for k in range(4):
        pg.add_keyframe("a", k, odo["a"][k])
        pg.add_keyframe("b", k, odo["b"][k])
    pg.add_inter_robot_closure("a", 0, "b", 0, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    support = {0: {("a", 1), ("b", 1)}}
    for given, anchored in ((support, False), (None, True)):
        again = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
        again.restore_state(pg.state(), odo, given)
        again.add_inter_robot_closure("a", 2, "b", 2, np.eye(4), match_id=2, support={("a", 1), ("b", 2)})
        assert again.is_anchored("b") is anchored
