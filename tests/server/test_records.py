"""Match records summed up per robot pair: why two robots never met, in numbers."""

from __future__ import annotations

import numpy as np

from shgm_slam.server.records import MatchEvidence, MatchRecord, pair_matches


def _record(a: str, b: str, *, success=False, accepted=False, llr: float | None = None, thr: float = 9.0):
    evidence = None if llr is None else MatchEvidence(np.eye(4), 3, llr, thr, 10, 6.0, 30, 28)
    T = np.eye(4) if success else None
    return MatchRecord(7, a, b, "whole", success, accepted, "", None, None, T, np.zeros((0, 2), np.int64), 40,
                       100, 90, {}, evidence=evidence)  # fmt: skip


def test_pairs_count_both_directions_and_segments_and_keep_the_closest_rejection():
    records = [
        _record("car1", "car2", llr=2.0),
        _record("car2", "car1", llr=5.5),  # the other direction: the same pair
        _record("car1", "car2#1", llr=-3.0),  # a later segment of car2: still car2
        _record("car1", "car2", llr=12.0, success=True, accepted=True),  # accepted: not a rejection
        _record("car1", "car2", llr=float("-inf")),  # no finite ratio: not a margin
        _record("car1", "car1", llr=8.9),  # a loop closure query: no pair
        _record("uav", "car1"),  # no hypothesis formed
        _record("uav", "car2", llr=-4.0, thr=8.0),
        _record("car2#2", "uav", llr=1.0, thr=9.5),
    ]
    pairs = {(p.robot_a, p.robot_b): p for p in pair_matches(records)}
    assert list(pairs) == [("car1", "car2"), ("car1", "uav"), ("car2", "uav")]
    car = pairs[("car1", "car2")]
    assert (car.tried, car.accepted, car.closest_margin_nats) == (5, 1, 5.5 - 9.0)
    assert pairs[("car1", "uav")].closest_margin_nats is None and pairs[("car1", "uav")].accepted == 0
    assert pairs[("car2", "uav")].tried == 2 and pairs[("car2", "uav")].closest_margin_nats == 1.0 - 9.5
    assert pairs[("car2", "uav")].to_json_dict() == {
        "robots": ["car2", "uav"], "tried": 2, "accepted": 0, "closest_margin_nats": -8.5}  # fmt: skip
    assert pair_matches([]) == []


def test_a_pair_that_never_met_says_how_close_it_came():
    from shgm_slam.server.records import PairMatches

    assert PairMatches("car1", "car2", 40, 6, -2.0).never_met() is None  # they met
    assert PairMatches("car1", "uav", 120, 0, -3.46).never_met().startswith(
        "car1 - uav: none of 120 matches accepted (the closest was 3.5 nats below the chance threshold")
    assert "no match formed a hypothesis" in PairMatches("car2", "uav", 9, 0, None).never_met()
    assert "one beat the chance threshold but had too few" in PairMatches("car1", "van", 5, 0, 1.5).never_met()
