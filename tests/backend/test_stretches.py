"""Straight stretches of a trajectory (``backend/stretches.py``) and what they do to independent evidence."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.backend.stretches import HEADING_BASE_M, StretchTracker, stretch_token
from shgm_slam.geometry.se3 import make_pose, rot_y


def stretch_ids(positions_xyz: np.ndarray, turn_deg: float = 30.0) -> np.ndarray:
    """Feed a trajectory's keyframe positions (K, 3) one by one; (K,) stretch ids."""
    steps = np.linalg.norm(np.diff(positions_xyz, axis=0), axis=1)
    path_m = np.concatenate([[0.0], np.cumsum(steps)])
    tracker = StretchTracker(np.radians(turn_deg))
    for k in range(len(positions_xyz)):
        tracker.append(positions_xyz[: k + 1], path_m[: k + 1])
    return np.array(tracker.ids)


def corner(n_leg: int, step_m: float = 2.0, turn_deg: float = 90.0) -> np.ndarray:
    """An L: ``n_leg`` keyframes along +z, then ``n_leg`` along z turned by ``turn_deg`` about y."""
    first = np.stack([np.zeros(n_leg), np.zeros(n_leg), step_m * np.arange(n_leg)], axis=1)
    direction = rot_y(np.radians(turn_deg)) @ np.array([0.0, 0.0, 1.0])
    second = first[-1] + step_m * np.arange(1, n_leg + 1)[:, None] * direction
    return np.vstack([first, second])


def test_a_straight_drive_with_jitter_is_one_stretch():
    rng = np.random.default_rng(3)
    n = 200
    xyz = np.stack([rng.normal(0, 0.2, n), rng.normal(0, 0.05, n), 2.0 * np.arange(n)], axis=1)
    assert set(stretch_ids(xyz).tolist()) == {0}


def test_a_corner_starts_new_stretches_and_each_leg_is_one():
    ids = stretch_ids(corner(50))
    assert np.all(np.diff(ids) >= 0)  # ids never go back
    first_leg, second_leg = ids[:50], ids[50 + int(HEADING_BASE_M / 2.0) + 1:]  # past the turn's base
    assert set(first_leg.tolist()) == {0}
    assert second_leg.min() > 0 and len(set(second_leg.tolist())) == 1
    assert set(stretch_ids(corner(50, turn_deg=20.0)).tolist()) == {0}  # a bend below the turn: same street


def test_standing_still_and_reversing_keep_the_stretch():
    still = np.zeros((20, 3))
    assert set(stretch_ids(still).tolist()) == {0}
    back_and_forth = np.stack([np.zeros(60), np.zeros(60), np.abs(np.arange(60) - 30) * 0.5], axis=1)
    assert stretch_ids(back_and_forth)[:20].max() == 0


def test_the_tracker_refuses_positions_that_skip_keyframes():
    with pytest.raises(ValueError, match="holds 0 keyframes"):
        StretchTracker(0.5).append(np.zeros((2, 3)), np.zeros(2))


def _pose_graph_on_corner(turn_deg: float | None) -> MultiRobotPoseGraph:
    """Robots a and b drive the same L (50 keyframes per leg, 2 m apart)."""
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2, stretch_turn_deg=turn_deg)
    for k, p in enumerate(corner(50)):
        pg.add_keyframe("a", k, make_pose(np.eye(3), p))
        pg.add_keyframe("b", k, make_pose(np.eye(3), p))
    return pg


def test_object_disjoint_matches_on_one_straight_street_count_once_and_a_match_round_the_corner_confirms():
    """An aliased street keeps aliasing with new objects as both robots drive on: two matches on disjoint
    objects of the same straight stretches are one piece of evidence; one after the corner is a second."""
    pg = _pose_graph_on_corner(30.0)
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    pg.add_inter_robot_closure("a", 30, "b", 30, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    assert pg.evidence_between("a", "b") == 1 and not pg.is_anchored("b")
    pg.add_inter_robot_closure("a", 80, "b", 80, np.eye(4), match_id=3, support={("a", 3), ("b", 3)})
    assert pg.evidence_between("a", "b") == 2 and pg.is_anchored("b")
    tokens = pg.stretches()
    assert tokens[0] == tokens[1] != tokens[2]


def test_what_tied_two_matches_together_is_named():
    """``shared_support`` returns what two or more matches rest on in common: the stretch pair of two
    object-disjoint matches on one street, the objects of two matches that found the same ones; the map server
    names the kinds in its waiting line."""
    from shgm_slam.backend.confirmation import Sharing
    from shgm_slam.server.evidence import MARGINAL_OBJECT, sharing

    pg = _pose_graph_on_corner(30.0)
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    assert pg.shared_support("a", "b") == frozenset()  # one match: nothing shared
    pg.add_inter_robot_closure("a", 30, "b", 30, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    shared = pg.shared_support("b", "a")
    assert shared == {pg.stretches()[0]} and sharing(shared) == (Sharing.STRETCHES,)
    objects = _pose_graph_on_corner(None)
    objects.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    objects.add_inter_robot_closure("a", 80, "b", 80, np.eye(4), match_id=2, support={("a", 1), ("b", 7)})
    assert objects.shared_support("a", "b") == {("a", 1)} and sharing({("a", 1)}) == (Sharing.OBJECTS,)
    marginal = {("a", f"{MARGINAL_OBJECT}:b"), ("a", 1), pg.stretches()[0]}
    assert sharing(frozenset(marginal)) == (Sharing.OBJECTS, Sharing.STRETCHES, Sharing.CHANCE)


def test_without_stretches_objects_alone_decide():
    pg = _pose_graph_on_corner(None)
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    pg.add_inter_robot_closure("a", 30, "b", 30, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    assert pg.is_anchored("b") and pg.stretches() == {}


def test_a_restored_graph_recomputes_the_stretches_behind_its_closures():
    """Restored with the closures' objects only, the graph still knows which straight stretches each closure
    lies on: a second object-disjoint match on the same stretches does not anchor b."""
    pg = _pose_graph_on_corner(30.0)
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    odo = {r: np.stack([make_pose(np.eye(3), p) for p in corner(50)]) for r in ("a", "b")}
    again = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2, stretch_turn_deg=30.0)
    again.restore_state(pg.state(), odo, {0: {("a", 1), ("b", 1)}})
    assert again.stretches() == pg.stretches()
    again.add_inter_robot_closure("a", 30, "b", 30, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    assert not again.is_anchored("b")
    again.add_inter_robot_closure("a", 80, "b", 80, np.eye(4), match_id=3, support={("a", 3), ("b", 3)})
    assert again.is_anchored("b")


def test_a_match_on_the_same_stretches_does_not_confirm_a_place():
    """With single matches trusted (min_closures_to_anchor=1) b is placed at once and stays provisional while
    the second match lies on the same straight stretches; a match round the corner confirms it."""
    from shgm_slam.backend.confirmation import Placement, placements

    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=1, stretch_turn_deg=30.0)
    for k, p in enumerate(corner(50)):
        pg.add_keyframe("a", k, make_pose(np.eye(3), p))
        pg.add_keyframe("b", k, make_pose(np.eye(3), p))
    support = {}
    for cid, (k, match) in enumerate(((10, 1), (30, 2), (80, 3))):
        pg.add_inter_robot_closure("a", k, "b", k, np.eye(4), match_id=match, support={("a", cid), ("b", cid)})
        support[cid] = {"a": frozenset({cid}), "b": frozenset({cid})}
        got = placements(["a", "b"], "a", ["a", "b"], pg.closures(), support, pg.stretches())["b"].placement
        assert got is (Placement.CONFIRMED if k == 80 else Placement.PROVISIONAL)
        assert placements(["a", "b"], "a", ["a", "b"], pg.closures(), support)["b"].placement is (
            Placement.PROVISIONAL if k == 10 else Placement.CONFIRMED
        )  # objects alone: the second match confirms


def test_matches_on_one_street_pair_count_once_whichever_robot_queried():
    """An aliased street aliases whoever queries (report world airsim-like 569: car2's submap query and car1's
    found one alias along one long straight street, on disjoint objects, and placed car2 310 m off): a match the
    partner's query found on the same two stretches shares the pseudo-object; one round the corner does not."""
    pg = _pose_graph_on_corner(30.0)
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    pg.add_inter_robot_closure("b", 30, "a", 30, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    tokens = pg.stretches()
    assert tokens[0] == tokens[1] == ("stretch", "a", 0, "b", 0)
    assert pg.closures()[0].querier == "b" and pg.closures()[1].querier == "a"
    assert not pg.is_anchored("b")  # one piece of evidence
    pg.add_inter_robot_closure("b", 80, "a", 80, np.eye(4), match_id=3, support={("a", 3), ("b", 3)})
    assert pg.stretches()[2] != tokens[0] and pg.is_anchored("b")


def test_the_stretch_token_does_not_depend_on_the_order_of_the_robots():
    token = ("stretch", "car1", 5, "car2", 3)
    assert stretch_token("car2", 3, "car1", 5) == stretch_token("car1", 5, "car2", 3) == token
    assert stretch_token("car1", 3, "car2", 5) != stretch_token("car1", 5, "car2", 3)


def test_stretch_pair_is_the_queriers_stretch_then_the_partners():
    pg = _pose_graph_on_corner(30.0)
    pg.add_inter_robot_closure("a", 80, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    pg.add_inter_robot_closure("b", 80, "a", 10, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    stretch_80 = pg.stretches()[0][2]  # a's stretch (the robots in name order)
    assert stretch_80 > 0
    assert pg.stretch_pair(0) == (0, stretch_80)  # b's query: b's keyframe 10 on stretch 0, a's 80 later
    assert pg.stretch_pair(1) == (0, stretch_80)  # a's query: the same, seen from a
    pg.add_loop_closure("a", 2, 90, np.eye(4), match_id=3)
    assert pg.stretch_pair(2) is None
    assert _pose_graph_on_corner(None).stretches() == {}
