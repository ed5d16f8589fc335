"""What a match result claims: the bars a match must clear to count, and the JSON it prints."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from shgm_slam.matching.result import TIMING_KEYS, MatchResult


def _accepted(llr: float, threshold: float = 9.0) -> MatchResult:
    return MatchResult(True, np.eye(4), np.array([[1, 2], [3, 4]]), 40, llr=llr, llr_threshold=threshold)


def test_a_piece_of_evidence_pays_for_every_match_the_pair_tried() -> None:
    r = _accepted(12.0)
    assert r.evidence_bar() == 9.0 and r.evidence_bar(0) == 9.0  # a single `shgm-slam match`
    assert r.evidence_bar(20) == pytest.approx(9.0 + math.log(20))
    assert not r.is_marginal(1) and not r.is_marginal(20) and r.is_marginal(21)  # 3 nats clear e^3 ~ 20 tries


def test_a_decisive_match_is_as_far_beyond_chance_as_the_pieces_it_replaces() -> None:
    assert _accepted(18.0).is_decisive(2) and not _accepted(17.9).is_decisive(2)
    assert not _accepted(18.0).is_decisive(2, tried=2)  # the bar rose with the tries: 2 x (9 + ln 2)
    assert not _accepted(100.0).is_decisive(1)  # one piece is what any accepted match is
    rejected = MatchResult(False, None, np.zeros((0, 2), dtype=np.int64), 40, llr=100.0, llr_threshold=9.0)
    assert not rejected.is_decisive(2)


def test_the_json_is_plain_json_with_every_stage_timed_and_no_infinities() -> None:
    fail = MatchResult.failure("graph B has 2 node(s); matching needs at least 3", 0, {"descriptors": 0.5})
    d = json.loads(json.dumps(fail.to_json_dict(), allow_nan=False))
    assert d["success"] is False and d["T_a_b"] is None and d["inliers"] == [] and d["rmse_m"] is None
    assert set(d["timings_ms"]) == set(TIMING_KEYS) and d["timings_ms"]["descriptors"] == 0.5
    assert d["verification"]["llr"] is None and d["verification"]["llr_threshold"] is None
    assert d["reason"].startswith("graph B has 2")
    ok = json.loads(json.dumps(_accepted(12.3456).to_json_dict(), allow_nan=False))
    assert ok["T_a_b"] == np.eye(4).tolist() and ok["inliers"] == [[1, 2], [3, 4]]
    assert ok["verification"]["llr"] == 12.346 and ok["verification"]["rival_llr"] is None
