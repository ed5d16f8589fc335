"""What a graph match rests on: the objects that make two matches independent, and what several share."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.confirmation import Sharing
from shgm_slam.backend.stretches import stretch_token
from shgm_slam.matching import MatchResult
from shgm_slam.server.evidence import MARGINAL_OBJECT, match_evidence, match_objects, sharing, support_objects


def test_a_matchs_objects_are_both_robots_inliers_and_a_marginal_match_shares_one_more() -> None:
    support = {"car1": frozenset({3, 4}), "car2#1": frozenset({7})}
    objects = support_objects(support)
    assert objects == {("car1", 3), ("car1", 4), ("car2#1", 7)}
    assert match_objects("car1", "car2", support, marginal=False) == objects
    assert match_objects("car1", "car1", support, marginal=False) == frozenset()  # a loop closure: none
    # every marginal match of a pair rests on one pseudo-object of that pair: two of them are never independent
    first = match_objects("car1", "car2", {"car1": frozenset({1})}, marginal=True)
    second = match_objects("car1", "car2", {"car1": frozenset({9})}, marginal=True)
    assert first & second and not (first & second) & objects
    assert not first & match_objects("car1", "uav", {"car1": frozenset({9})}, marginal=True)  # another pair


def test_what_matches_share_is_told_apart_in_a_fixed_order() -> None:
    marginal = next(iter(match_objects("car1", "car2", {}, marginal=True)))
    assert str(marginal[1]).startswith(MARGINAL_OBJECT)
    token = stretch_token("car2", 0, "car1", 3)
    assert sharing(frozenset({("car1", 3)})) == (Sharing.OBJECTS,)
    assert sharing(frozenset({token, marginal})) == (Sharing.STRETCHES, Sharing.CHANCE)
    assert sharing(frozenset({marginal, token, ("car1", 3)})) == (Sharing.OBJECTS, Sharing.STRETCHES, Sharing.CHANCE)
    assert sharing(frozenset()) == ()


def test_a_match_without_a_hypothesis_has_no_evidence_record() -> None:
    assert match_evidence(MatchResult.failure("no candidates"), keyframe_b=4) is None
    r = MatchResult(True, np.eye(4), np.zeros((0, 2), dtype=np.int64), 30, T_a_b_hypothesis=np.eye(4), llr=14.0,
                    llr_threshold=9.0, support=22, rival_llr=-float("inf"))  # fmt: skip
    e = match_evidence(r, keyframe_b=4)
    assert e is not None and e.llr == 14.0 and e.keyframe_b == 4 and e.support == 22 and e.rival_llr == -float("inf")
