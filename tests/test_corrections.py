"""Corrections that send only what changed: a robot's view follows the server's poses to within the
tolerance, exactly after a zero-tolerance correction, and a missed correction is noticed."""

from __future__ import annotations

import numpy as np

from shgm_slam.corrections import FusedView, rigid_motion
from shgm_slam.geometry.se3 import make_pose, rotation_angle, so3_exp
from shgm_slam.messages import AgentCorrection, CorrectionMessage
from shgm_slam.wire import decode, encode

TOL_M, TOL_RAD = 0.05, 0.005


def trajectory(rng: np.random.Generator, k: int) -> np.ndarray:
    return np.stack([make_pose(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 30, 3)) for _ in range(k)])


def jiggle(rng: np.random.Generator, T: np.ndarray, sigma: float) -> np.ndarray:
    n = len(T)
    return T @ np.stack([make_pose(so3_exp(rng.normal(0, sigma / 10, 3)), rng.normal(0, sigma, 3)) for _ in range(n)])


def send(server_view: FusedView, current: dict, seq_full: bool, tol=(TOL_M, TOL_RAD)) -> CorrectionMessage:
    """What the map server does: the changes, numbered, applied to its own copy, through the wire codec."""
    full = seq_full or server_view.seq == 0
    changes = server_view.changes(current, *tol, full=full)
    seq = server_view.seq + 1 if changes or full else 0
    msg = CorrectionMessage("car1", "s", {}, seq, full, changes)
    assert server_view.apply(msg)
    return decode(encode(msg))


def test_deltas_keep_the_robot_within_tolerance_and_exact_at_the_end() -> None:
    rng = np.random.default_rng(0)
    server, robot = FusedView(), FusedView()
    T = {"car1": trajectory(rng, 5), "car1#1": trajectory(rng, 2)}
    sizes = []
    for step in range(40):
        T = {a: np.concatenate([jiggle(rng, P, 0.02 if step % 10 else 1.0), trajectory(rng, 2)]) for a, P in T.items()}
        current = {a: (P[-1], P) for a, P in T.items()}
        msg = send(server, current, False)
        assert robot.apply(msg)
        sizes.append(sum(len(c.kf_indices) for c in msg.agents.values()))
        for a, P in T.items():
            held = robot.T_shared_kf[a]
            assert held.shape == P.shape
            assert np.linalg.norm(held[:, :3, 3] - P[:, :3, 3], axis=1).max() <= TOL_M
            assert rotation_angle(np.swapaxes(held, 1, 2)[:, :3, :3] @ P[:, :3, :3]).max() <= TOL_RAD + 1e-7
    assert np.mean(sizes) < 0.3 * sum(len(P) for P in T.values())  # mostly the new keyframes and a few moved
    assert robot.apply(send(server, {a: (P[-1], P) for a, P in T.items()}, False, tol=(0.0, 0.0)))
    for a, P in T.items():
        np.testing.assert_array_equal(robot.T_shared_kf[a], P)
        np.testing.assert_array_equal(robot.T_shared_odom[a], P[-1])


def test_a_missed_correction_is_noticed_and_a_full_one_repairs_it() -> None:
    rng = np.random.default_rng(1)
    server, robot = FusedView(), FusedView()
    P = trajectory(rng, 4)
    assert robot.apply(send(server, {"car1": (P[0], P)}, False))
    P = np.concatenate([jiggle(rng, P, 1.0), trajectory(rng, 1)])
    send(server, {"car1": (P[0], P)}, False)  # lost on the way
    P = np.concatenate([P, trajectory(rng, 1)])
    late = send(server, {"car1": (P[0], P)}, False)
    assert not robot.apply(late) and robot.seq == 1  # a gap: nothing applied
    full = send(server, {"car1": (P[0], P)}, True)
    assert full.full and robot.apply(full)
    np.testing.assert_array_equal(robot.T_shared_kf["car1"], P)
    assert robot.apply(late)  # an old one after the full: ignored, not a gap
    np.testing.assert_array_equal(robot.T_shared_kf["car1"], P)


def test_unplaced_agents_are_dropped_and_acknowledgements_change_nothing() -> None:
    rng = np.random.default_rng(2)
    server, robot = FusedView(), FusedView()
    P = trajectory(rng, 3)
    assert robot.apply(send(server, {"car1": (P[0], P), "car1#1": (P[1], P)}, False))
    assert robot.apply(send(server, {"car1": (P[0], P), "car1#1": None}, False))
    assert set(robot.T_shared_kf) == {"car1"} and set(robot.T_shared_odom) == {"car1"}
    assert robot.apply(CorrectionMessage("car1", "s", {"car1": 3})) and robot.seq == server.seq
    nothing = server.changes({"car1": (P[0], P)}, TOL_M, TOL_RAD, full=False)
    assert nothing == {}


def test_a_delta_that_leaves_a_keyframe_without_a_pose_is_refused() -> None:
    rng = np.random.default_rng(3)
    server, robot = FusedView(), FusedView()
    P = trajectory(rng, 3)
    assert robot.apply(send(server, {"car1": (P[0], P)}, False))
    bigger = np.concatenate([P, trajectory(rng, 2)])
    msg = send(server, {"car1": (P[0], bigger)}, False)
    c = msg.agents["car1"]
    holey = type(c)(c.T_shared_odom, c.num_keyframes, c.kf_indices[1:], c.T_shared_kf[1:])  # keyframe 3 missing
    assert not robot.apply(CorrectionMessage("car1", "s", {}, msg.seq, False, {"car1": holey}))
    assert robot.seq == 1 and len(robot.T_shared_kf["car1"]) == 3


def test_a_keyframe_count_no_pose_covers_is_refused_without_allocating_it() -> None:
    """A correction (from any publisher on the robot's key) claiming 2^31 - 1 keyframes: before, the robot
    allocated a (2^31 - 1, 4, 4) array and died of a MemoryError; now it is refused (the robot asks for a full one)."""
    P = trajectory(np.random.default_rng(4), 2)
    bomb = AgentCorrection(P[0], 2**31 - 1, np.arange(2), P)
    robot = FusedView()
    assert not robot.apply(decode(encode(CorrectionMessage("car1", "s", {}, 1, True, {"car1": bomb}))))
    assert robot.seq == 0 and not robot.T_shared_kf


def test_a_rigid_move_is_sent_as_one_motion_and_what_it_leaves() -> None:
    rng = np.random.default_rng(4)
    server, robot = FusedView(), FusedView()
    P = trajectory(rng, 30)
    assert robot.apply(send(server, {"car1": (P[-1], P)}, False))
    move = make_pose(so3_exp(np.array([0.0, 0.3, 0.0])), np.array([12.0, -1.0, 40.0]))
    moved = move @ P
    moved[5] = jiggle(rng, moved[5:6], 1.0)[0]  # and one keyframe bent on its own
    msg = send(server, {"car1": (moved[-1], moved)}, False)
    c = msg.agents["car1"]
    assert c.T_move is not None and c.kf_indices.tolist() == [5]
    assert robot.apply(msg)
    err = np.linalg.norm(robot.T_shared_kf["car1"][:, :3, 3] - moved[:, :3, 3], axis=1)
    assert err.max() <= TOL_M


def test_rigid_motion_recovers_a_motion_of_a_straight_path() -> None:
    held = np.stack([make_pose(np.eye(3), np.array([0.0, 0.0, 2.0 * k])) for k in range(10)])  # collinear
    T = make_pose(so3_exp(np.array([0.4, 0.1, -0.2])), np.array([1.0, 2.0, 3.0]))
    found, left = rigid_motion(held, T @ held, TOL_M, TOL_RAD)
    np.testing.assert_allclose(found, T, atol=1e-12)
    assert not left.any()
