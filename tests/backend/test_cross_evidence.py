"""Evidence from different partners (``backend/cross_evidence.py``): two placed robots' independent matches that
agree place a robot whose overlap with each is one piece of evidence; an alias, the same stretch or the same
objects do not."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.confirmation import Placement, describe, placements
from shgm_slam.backend.consistency import ConsistencyThresholds
from shgm_slam.backend.cross_evidence import Piece, agreeing_pieces
from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.geometry.se3 import make_pose
from tests.backend.test_stretches import corner

STEP_M = 2.0
K = 100  # keyframes of a straight drive along +z, 2 m apart


def straight_odometry(k: int = K) -> tuple[np.ndarray, np.ndarray]:
    """(K, 4, 4) keyframe poses along +z and (K,) path lengths: the robot's odometry frame."""
    poses = np.stack([make_pose(np.eye(3), [0.0, 0.0, STEP_M * i]) for i in range(k)])
    return poses, STEP_M * np.arange(k, dtype=np.float64)


def piece(cid: int, partner: str, kf: int, offset_m: float = 0.0, objects=(), stretch=None, inliers=20) -> Piece:
    """A piece placing keyframe ``kf`` where the odometry has it (shared = odometry frame), ``offset_m`` off
    sideways."""
    T = make_pose(np.eye(3), [offset_m, 0.0, STEP_M * kf])
    return Piece(cid, partner, kf, T, frozenset(objects), stretch, inliers)


def chosen(pieces, needed=2, thresholds=ConsistencyThresholds()) -> list[int]:
    odom, path = straight_odometry()
    return [p.closure_id for p in agreeing_pieces(pieces, odom, path, thresholds, needed)]


def test_independent_agreeing_pieces_of_two_partners_are_found():
    pieces = [piece(0, "a", 10, objects={("r", 1)}, stretch=0), piece(1, "b", 60, objects={("r", 2)}, stretch=1)]
    assert sorted(chosen(pieces)) == [0, 1]


@pytest.mark.parametrize(
    "second",
    [
        piece(1, "a", 60, objects={("r", 2)}, stretch=1),  # the same partner: the pair's own rule decides
        piece(1, "b", 60, objects={("r", 1)}, stretch=1),  # the same object of the robot found again
        piece(1, "b", 30, objects={("r", 2)}, stretch=0),  # the same straight stretch: an alias keeps aliasing
        piece(1, "b", 60, offset_m=20.0, objects={("r", 2)}, stretch=1),  # they disagree by 20 m
    ],
    ids=["same-partner", "same-object", "same-stretch", "disagree"],
)
def test_pieces_that_are_not_independent_or_disagree_are_not(second: Piece):
    assert chosen([piece(0, "a", 10, objects={("r", 1)}, stretch=0), second]) == []


def test_the_tolerance_grows_with_the_distance_driven_between_the_keyframes():
    """5 m + 5 % of the path between the two keyframes (the consistency thresholds)."""
    near = [piece(0, "a", 0, stretch=0), piece(1, "b", 50, offset_m=9.0, stretch=1)]  # 100 m: 10 m allowed
    far = [piece(0, "a", 0, stretch=0), piece(1, "b", 99, offset_m=9.0, stretch=1)]  # 198 m: 14.9 m allowed
    assert sorted(chosen(near)) == [0, 1]
    assert sorted(chosen(far)) == [0, 1]
    assert chosen([piece(0, "a", 0, stretch=0), piece(1, "b", 50, offset_m=11.0, stretch=1)]) == []


def test_a_wrong_best_piece_does_not_hide_two_right_ones():
    """The alias has the most inliers; the greedy search from the next seed still finds the two that agree."""
    pieces = [
        piece(0, "a", 10, offset_m=40.0, stretch=0, objects={("r", 9)}, inliers=50),
        piece(1, "b", 20, stretch=1, objects={("r", 1)}),
        piece(2, "c", 70, stretch=2, objects={("r", 2)}),
    ]
    assert sorted(chosen(pieces)) == [1, 2]
    assert sorted(chosen(pieces[::-1])) == [1, 2]  # input order does not matter


def test_needed_counts_distinct_partners():
    pieces = [piece(0, "a", 10, stretch=0), piece(1, "b", 40, stretch=1), piece(2, "c", 80, stretch=2)]
    assert sorted(chosen(pieces, needed=3)) == [0, 1, 2]
    assert chosen(pieces[:2], needed=3) == []
    with pytest.raises(ValueError, match="at least 2"):
        chosen(pieces, needed=1)


# --- in the pose graph ---------------------------------------------------------------------------------------

LEG = 50  # keyframes per leg of the L every robot drives (2 m apart)


def l_graph(min_closures_to_anchor: int = 2) -> MultiRobotPoseGraph:
    """a, b and c drive the same L from the same start (each odometry frame at its first keyframe); b is placed
    through two independent matches with a (before and after the corner)."""
    pg = MultiRobotPoseGraph(["a", "b", "c"], min_closures_to_anchor=min_closures_to_anchor, stretch_turn_deg=30.0)
    for r in ("a", "b", "c"):
        for k, p in enumerate(corner(LEG)):
            pg.add_keyframe(r, k, make_pose(np.eye(3), p))
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), match_id=1, support={("a", 1), ("b", 1)})
    pg.add_inter_robot_closure("a", 80, "b", 80, np.eye(4), match_id=2, support={("a", 2), ("b", 2)})
    assert pg.is_anchored("b")
    return pg


def confirmed(pg: MultiRobotPoseGraph) -> dict:
    anchored = [r for r in ("a", "b", "c") if pg.is_anchored(r)]
    return placements(["a", "b", "c"], "a", anchored, pg.closures(), {}, pg.stretches(), pg.agreeing_partners)


def test_a_robot_with_one_piece_each_from_two_placed_robots_is_placed_and_confirmed():
    """c's only match with a lies on its first leg, its only match with b after the corner: neither pair has
    two pieces, together they are two that agree."""
    pg = l_graph()
    pg.add_inter_robot_closure("a", 12, "c", 12, np.eye(4), match_id=3, support={("a", 11), ("c", 1)})
    assert not pg.is_anchored("c")
    pg.add_inter_robot_closure("b", 85, "c", 85, np.eye(4), match_id=4, support={("b", 12), ("c", 2)})
    assert pg.is_anchored("c")
    est = pg.estimate()["c"]
    np.testing.assert_allclose(est[:, :3, 3], corner(LEG), atol=1e-3)
    c = confirmed(pg)["c"]
    assert c.placement is Placement.CONFIRMED and {c.partner, *c.also} == {"a", "b"}
    assert "a and b" in describe("c", c) or "b and a" in describe("c", c)


def test_an_alias_from_the_second_partner_does_not_place_the_robot():
    """c's match with b puts it 30 m further along the second leg: the two pieces disagree."""
    pg = l_graph()
    pg.add_inter_robot_closure("a", 12, "c", 12, np.eye(4), match_id=3, support={("a", 11), ("c", 1)})
    alias = make_pose(np.eye(3), [0.0, 0.0, 30.0])
    pg.add_inter_robot_closure("b", 85, "c", 85, alias, match_id=4, support={("b", 12), ("c", 2)})
    assert not pg.is_anchored("c")
    assert pg.agreeing_partners("c", ["a", "b"]) == ()


def test_two_partners_on_one_stretch_of_the_robot_do_not_place_it():
    """Both matches lie on c's first leg: two partners that mapped one street place c's alias alike."""
    pg = l_graph()
    pg.add_inter_robot_closure("a", 12, "c", 12, np.eye(4), match_id=3, support={("a", 11), ("c", 1)})
    pg.add_inter_robot_closure("b", 30, "c", 30, np.eye(4), match_id=4, support={("b", 12), ("c", 2)})
    assert not pg.is_anchored("c")


def test_a_provisional_robot_is_confirmed_through_a_second_partner():
    """With single-match anchoring (min_closures_to_anchor 1) c enters on its first match, provisional; an
    agreeing match with another confirmed robot on another stretch confirms it."""
    pg = l_graph(min_closures_to_anchor=1)
    pg.add_inter_robot_closure("a", 12, "c", 12, np.eye(4), match_id=3, support={("a", 11), ("c", 1)})
    assert confirmed(pg)["c"].placement is Placement.PROVISIONAL
    pg.add_inter_robot_closure("b", 85, "c", 85, np.eye(4), match_id=4, support={("b", 12), ("c", 2)})
    assert confirmed(pg)["c"].placement is Placement.CONFIRMED


def test_the_search_keeps_the_strongest_pieces_per_partner_and_stretch():
    from shgm_slam.backend.cross_evidence import PIECES_PER_STRETCH, strongest

    partners = ["a"] * 10 + ["b"] * 3
    stretches = [0] * 10 + [1] * 3
    inliers = [*range(10), 5, 5, 5]
    kept = strongest(partners, stretches, inliers, 2)
    assert kept == sorted([*[9, 8, 7, 6][:PIECES_PER_STRETCH], 10, 11, 12])
    assert strongest(["a", "a"], [0, 1], [5, 5], 2) == []  # one partner
    assert strongest(["a", "b"], [0, 0], [5, 5], 2) == []  # one stretch of the robot: never independent
    assert strongest(["a", "b"], [None, None], [5, 5], 2) == [0, 1]  # stretches not tracked: objects decide


def test_closures_on_one_stretch_of_the_robot_never_place_it():
    """Eighty matches with two partners, all on c's first leg: c never joins (the search drops them before it
    reads a pose)."""
    pg = l_graph()
    for k in range(0, 40):
        pg.add_inter_robot_closure("a", k, "c", k, np.eye(4), match_id=100 + k, support={("c", 1000 + k)}, update=False)
        pg.add_inter_robot_closure("b", k, "c", k, np.eye(4), match_id=200 + k, support={("c", 2000 + k)}, update=False)
    pg.update()
    assert not pg.is_anchored("c")
    assert pg.agreeing_partners("c", ["a", "b"]) == ()
