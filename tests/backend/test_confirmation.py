"""Provisional vs confirmed placement: one match never confirms itself, a second one on other objects does."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.confirmation import (
    AgentPlacement,
    Placement,
    Sharing,
    confirms,
    describe,
    describe_waiting,
    placements,
)
from shgm_slam.backend.pose_graph import ClosureStatus, MultiRobotPoseGraph
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y
from tests.backend.test_pose_graph import noisy_odometry, route

N = 40  # keyframes per robot


@pytest.fixture(scope="module")
def world():
    """Robots a, b, c drive one street; b and c start 4 and 8 m beside a (their frames unknown to a)."""
    rng = np.random.default_rng(3)
    gt = {"a": route(N, np.eye(4))}
    gt["b"] = gt["a"] @ make_pose(np.eye(3), [4.0, 0.0, 0.0])
    gt["c"] = gt["a"] @ make_pose(np.eye(3), [8.0, 0.0, 0.0])
    return {"gt": gt, "odo": {r: noisy_odometry(g, rng) for r, g in gt.items()}}


def graph(world, robots=("a", "b")) -> MultiRobotPoseGraph:
    pg = MultiRobotPoseGraph(list(robots))
    for r in robots:
        for k in range(N):
            pg.add_keyframe(r, k, world["odo"][r][k])
    return pg


class Fleet:
    """A pose graph plus the objects behind each closure, as the map server records them."""

    def __init__(self, world, robots=("a", "b")) -> None:
        self.world, self.pg, self.support = world, graph(world, robots), {}

    def closure(self, ra, ka, rb, kb, match, objects, *, wrong=False):
        gt = self.world["gt"]
        T = inverse(gt[ra][ka]) @ gt[rb][kb]
        if wrong:  # aliasing: 30 m off and turned
            T = T @ make_pose(rot_y(0.5), [30.0, 0.0, 5.0])
        d = self.pg.add_inter_robot_closure(ra, ka, rb, kb, T, num_inliers=8, match_id=match)
        self.support[d.closure_id] = {ra: frozenset(objects), rb: frozenset(o + 1000 for o in objects)}
        return d

    def placement(self, agent: str) -> AgentPlacement:
        pg = self.pg
        names = pg.keys.names
        anchored = [a for a in names if pg.is_anchored(a)]
        return placements(names, names[0], anchored, pg.closures(), self.support)[agent]


def test_reference_and_unplaced(world) -> None:
    f = Fleet(world)
    assert f.placement("a").placement is Placement.REFERENCE
    assert f.placement("b").placement is Placement.UNPLACED
    assert not f.placement("b").provisional


def test_closures_of_one_match_never_confirm_each_other(world) -> None:
    f = Fleet(world)
    for k, objects in ((5, range(0, 10)), (20, range(10, 20)), (35, range(20, 30))):  # three stretches, one match
        assert f.closure("a", k, "b", k, match=1, objects=objects).accepted
    p = f.placement("b")
    assert f.pg.is_anchored("b") and p.placement is Placement.PROVISIONAL and p.provisional
    assert p.partner == "a" and p.matches == 1 and p.keyframes == (5, 20, 35)
    assert "provisionally" in describe("b", p) and "a" in describe("b", p)


def test_a_decisive_match_places_a_robot_provisionally_and_says_so(world) -> None:
    """With two independent matches needed, one decisive match places b alone; its place rests on one piece of
    evidence, so it is provisional, and the line says why one match sufficed. A second match confirms it."""
    f = Fleet(world)
    f.pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    for r in ("a", "b"):
        for k in range(N):
            f.pg.add_keyframe(r, k, world["odo"][r][k])
    gt = world["gt"]
    d = f.pg.add_inter_robot_closure("a", 5, "b", 5, inverse(gt["a"][5]) @ gt["b"][5], match_id=1, decisive=True)
    f.support[d.closure_id] = {"a": frozenset(range(10)), "b": frozenset(range(1000, 1010))}
    p = f.placement("b")
    assert f.pg.is_anchored("b") and p.placement is Placement.PROVISIONAL and p.decisive
    assert "a single graph match" in describe("b", p) and "backend.decisive_match" in describe("b", p)
    f.closure("a", 30, "b", 30, match=2, objects=range(40, 50))
    assert f.placement("b").placement is Placement.CONFIRMED


def test_second_match_on_other_objects_confirms(world) -> None:
    f = Fleet(world)
    f.closure("a", 5, "b", 5, match=1, objects=range(0, 10))
    assert f.placement("b").provisional
    assert f.closure("a", 30, "b", 30, match=2, objects=range(40, 50)).accepted  # another stretch, consistent
    p = f.placement("b")
    assert p.placement is Placement.CONFIRMED and p.matches == 2
    assert "confirmed" in describe("b", p)


def test_a_rematch_of_the_same_objects_does_not_confirm_even_crosswise(world) -> None:
    f = Fleet(world)
    # match 1 cut into two stretches; match 2 (the growing graph matched again at once) finds both again,
    # with a few objects more: each of its closures shares objects with one of match 1's
    f.closure("a", 5, "b", 5, match=1, objects=range(0, 10))
    f.closure("a", 20, "b", 20, match=1, objects=range(10, 20))
    f.closure("a", 6, "b", 6, match=2, objects=range(8, 12))
    f.closure("a", 21, "b", 21, match=2, objects=range(15, 25))
    assert all(c.status is ClosureStatus.ACCEPTED for c in f.pg.closures())
    assert f.placement("b").provisional
    # a later match that also reaches a new stretch confirms through that stretch alone
    f.closure("a", 36, "b", 36, match=3, objects=range(60, 70))
    assert f.placement("b").placement is Placement.CONFIRMED


def test_an_inconsistent_second_match_does_not_confirm(world) -> None:
    f = Fleet(world)
    f.closure("a", 5, "b", 5, match=1, objects=range(0, 10))
    d = f.closure("a", 30, "b", 30, match=2, objects=range(40, 50), wrong=True)
    assert not d.accepted  # a tie: the first set stays
    assert f.placement("b").provisional


def test_confirmation_spreads_only_through_confirmed_agents(world) -> None:
    f = Fleet(world, ("a", "b", "c"))
    f.closure("a", 5, "b", 5, match=1, objects=range(0, 10))  # b: provisional
    f.closure("b", 10, "c", 10, match=2, objects=range(100, 110))
    f.closure("b", 30, "c", 30, match=3, objects=range(120, 130))  # c: two independent matches, but with b
    assert f.pg.is_anchored("c")
    assert f.placement("b").provisional and f.placement("c").provisional
    c = f.placement("c")
    assert c.partner == "b" and not c.partner_confirmed and "b is provisional itself" in describe("c", c)
    f.closure("a", 30, "b", 30, match=4, objects=range(40, 50))  # b confirmed: c follows
    assert f.placement("b").placement is Placement.CONFIRMED
    assert f.placement("c").placement is Placement.CONFIRMED


def test_loop_closures_do_not_confirm(world) -> None:
    f = Fleet(world)
    f.closure("a", 5, "b", 5, match=1, objects=range(0, 10))
    gt = world["gt"]["b"]
    f.pg.add_loop_closure("b", 2, 30, inverse(gt[2]) @ gt[30], match_id=2)
    f.pg.add_loop_closure("b", 4, 34, inverse(gt[4]) @ gt[34], match_id=3)
    assert f.placement("b").provisional


def test_confirms_needs_another_match_and_other_objects() -> None:
    from shgm_slam.backend.pose_graph import ClosureRecord

    def rec(cid, match):
        return ClosureRecord(cid, "a", cid, "b", cid, np.eye(4), 5, ClosureStatus.ACCEPTED, match_id=match)

    one, same_match, other = rec(0, 1), rec(1, 1), rec(2, 2)
    support = {0: {"a": frozenset({1, 2}), "b": frozenset({7})}, 1: {"a": frozenset({3})},
               2: {"a": frozenset({4}), "b": frozenset({8})}}  # fmt: skip
    assert not confirms(same_match, [one], support)
    assert confirms(other, [one, same_match], support)
    support[2] = {"a": frozenset({4}), "b": frozenset({7, 8})}  # shares b's object 7 with closure 0
    assert not confirms(other, [one, same_match], support)
    assert confirms(rec(3, None), [one], {})  # no recorded objects: its own match suffices


def test_the_object_index_decides_like_confirms_on_random_pairs() -> None:
    """``placements`` (an object index over the matches) agrees with ``confirms`` (the definition) on
    random robot pairs: few matches, closures sharing objects at random."""
    from shgm_slam.backend.pose_graph import ClosureRecord

    rng = np.random.default_rng(5)
    outcomes = set()
    for _ in range(300):
        n = int(rng.integers(1, 8))
        closures = [
            ClosureRecord(i, "a", i, "b", i, np.eye(4), 5, ClosureStatus.ACCEPTED, match_id=int(rng.integers(0, 3)))
            for i in range(n)
        ]  # fmt: skip
        support = {
            c.closure_id: {r: frozenset(rng.choice(12, size=rng.integers(1, 4), replace=False).tolist()) for r in "ab"}
            for c in closures if rng.random() < 0.9
        }  # fmt: skip
        by_match: dict = {}
        for c in closures:
            by_match.setdefault(c.evidence, []).append(c)
        expected = any(confirms(c, m, support) for m in by_match.values() for c in closures)
        placed = placements(["a", "b"], "a", ["a", "b"], closures, support)["b"]
        assert (placed.placement is Placement.CONFIRMED) == expected
        outcomes.add(expected)
    assert outcomes == {True, False}  # both cases were drawn


def test_waiting_line_counts_matches_and_evidence() -> None:
    one = describe_waiting("car2", "car1", evidence=1, needed=2, matches=1)
    assert one.startswith("car2 is not placed") and "1 accepted graph match with car1 is one piece of evidence" in one
    many = describe_waiting("car2", "car1", evidence=1, needed=3, matches=4)
    assert "4 accepted graph matches with car1 are one piece of evidence" in many and "once 3 independent" in many
    assert "do not count" not in many
    assert "(matches that found the same objects, matches along the same straight stretches of both drives, " \
        "matches too close to chance for the number the pair has tried, count once)" in many  # not known: all kinds
    assert "count once" not in one  # a single match is one piece by itself
    why = describe_waiting("car2", "car1", evidence=1, needed=2, matches=4,
                           sharing=(Sharing.STRETCHES, Sharing.OBJECTS))  # fmt: skip
    assert "(here: matches that found the same objects and matches along the same straight stretches of both " \
        "drives count once)" in why
    across = describe_waiting("car2", "car1", evidence=1, needed=2, matches=4, others=("uav",))
    assert across.endswith("its accepted matches with uav do not count as another piece: they lie on the same "
                           "straight stretch of its drive, rest on the same objects or disagree on its place")


def test_a_provisional_place_names_what_tied_its_matches() -> None:
    """Several matches with one partner that are one piece of evidence: the line says why (the same objects, or the
    same straight stretches of both drives, on which a match on other objects is no other piece either)."""
    p = AgentPlacement(Placement.PROVISIONAL, "a", 5, (3, 9), True, decisive=True)
    assert "5 graph matches with a (its keyframes 3-9) that all found the same objects" in describe("b", p)
    assert describe("b", p, (Sharing.OBJECTS,)) == describe("b", p)
    both = describe("b", p, (Sharing.OBJECTS, Sharing.STRETCHES))
    assert "that are one piece of evidence (here: matches that found the same objects and matches along the same " \
           "straight stretches of both drives count once)" in both
    assert both.endswith("until a match on other objects away from those straight stretches confirms it")
