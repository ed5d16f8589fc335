"""Match records: one graph-match attempt and what the back end decided (``matches.json`` rows)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.io.json_text import finite_or_none

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchEvidence:
    """The best hypothesis of a match attempt and the verification's numbers, kept also when the match was
    rejected: what the held-out benchmark judges to tell a rejected right alignment (a miss) from a rejected
    wrong one, and what a user reads to see how far from the decision a match was.

    Attributes:
        T_a_b_hypothesis: (4, 4) the best hypothesis, B's odometry frame into A's (as ``T_a_b``).
        keyframe_b: B's newest keyframe when the match was made (the place a rejected hypothesis is judged at).
        llr: its log likelihood ratio against chance, nats (``verification``).
        llr_threshold: the ratio it had to beat, nats.
        support: its same-label partners.
        expected_chance: B's overlapping nodes expected to find a partner by chance.
        overlap_a, overlap_b: nodes of A (B) inside the area the other robot observed.
        rival_llr: the ratio of the best verified alignment that places B elsewhere, nats (-inf: none was
            verified); an accepted match whose rival clears the threshold too leads it by log(1 / false alarm
            rate), so an accepted alias shows what it was weighed against.
        centroid_sigma_m: an accepted match's predicted RMS error at the centroid of B's queried nodes, metres
            (``MatchResult.centroid_sigma_m``; NaN when rejected, or in snapshots of versions before it).
    """

    T_a_b_hypothesis: np.ndarray
    keyframe_b: int
    llr: float
    llr_threshold: float
    support: int
    expected_chance: float
    overlap_a: int
    overlap_b: int
    rival_llr: float = -math.inf
    centroid_sigma_m: float = math.nan

    def to_json_dict(self) -> dict:
        return {
            "T_a_b_hypothesis": np.round(self.T_a_b_hypothesis, 9).tolist(),
            "keyframe_b": self.keyframe_b,
            "llr": finite_or_none(round(float(self.llr), 3)),
            "llr_threshold": finite_or_none(round(float(self.llr_threshold), 3)),
            "support": self.support,
            "expected_chance": round(float(self.expected_chance), 3),
            "overlap_a": self.overlap_a,
            "overlap_b": self.overlap_b,
            "rival_llr": finite_or_none(round(float(self.rival_llr), 3)),
            "centroid_sigma_m": finite_or_none(round(float(self.centroid_sigma_m), 3)),
        }


@dataclass
class MatchRecord:
    """One inter-robot match attempt and what the back end decided (a row of ``matches.json``)."""

    step: int
    robot_a: str
    robot_b: str
    query: str  # "submap" | "whole" | "window": which part of robot_b's graph was matched against robot_a's
    # (its recent submap, its whole graph, or a placed pair's recent window: queries.RECENT_WINDOW_SUBMAPS);
    # "backfill": a placed pair's older window of robot_b that no closure ties yet (queries.BACKFILL_QUERY);
    # "loop": robot_b == robot_a, its recent submap against its own older graph (intra-robot loop closure);
    # "independent": at the end, whole graphs without the objects behind robot_b's one piece of evidence
    # "independent-partner": the same from the partner's side (robot_a the waiting agent; versions before 2026-12-05)
    success: bool
    accepted: bool
    reason: str
    kf_a: int | None
    kf_b: int | None
    T_a_b: np.ndarray | None
    inliers: np.ndarray
    candidates: int
    nodes_a: int
    nodes_b: int
    timings_ms: dict[str, float]
    inlier_positions_a: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    inlier_positions_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    closures: list[dict] = field(default_factory=list)
    duplicate: bool = False  # every closure it gave was already in the pose graph (neither new nor rejected)
    evidence: MatchEvidence | None = None  # the best hypothesis and its verification (None: none was formed)

    def to_json_dict(self) -> dict:
        return {
            "step": self.step,
            "robot_a": self.robot_a,
            "robot_b": self.robot_b,
            "query": self.query,
            "success": self.success,
            "accepted": self.accepted,
            "reason": self.reason,
            "keyframe_a": self.kf_a,
            "keyframe_b": self.kf_b,
            "T_a_b": None if self.T_a_b is None else np.round(self.T_a_b, 9).tolist(),
            "inliers": self.inliers.tolist(),
            "candidates": self.candidates,
            "nodes_a": self.nodes_a,
            "nodes_b": self.nodes_b,
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
            "closures": self.closures,
            "evidence": None if self.evidence is None else self.evidence.to_json_dict(),
        }

    def conclude(self) -> None:
        """Sum up a successful match's decided ``closures`` (at least one) in the record's own fields: accepted
        when any closure was; the keyframes and reason of the first accepted closure (else of the first), the
        reason prefixed with the count accepted when there were several; a duplicate when every closure not
        accepted repeated an earlier one and none was accepted."""
        accepted = [c for c in self.closures if c["accepted"]]
        self.accepted = bool(accepted)
        shown = accepted[0] if accepted else self.closures[0]
        self.kf_a, self.kf_b, self.reason = shown["keyframe_a"], shown["keyframe_b"], shown["reason"]
        if len(self.closures) > 1:
            self.reason = f"{len(accepted)} of {len(self.closures)} local closures accepted; {self.reason}"
        self.duplicate = all(c["reason"].startswith("duplicate") for c in self.closures if not c["accepted"]) and (
            not accepted
        )


@dataclass(frozen=True)
class PairMatches:
    """How the matches between two robots went, over all their trajectory segments (a row of ``metrics.json``'s
    ``pairs``): what tells a user why two robots never met.

    Attributes:
        robot_a, robot_b: the robots (names sorted).
        tried: graph matches between them, both ways, submaps and whole graphs.
        accepted: of those, matches the back end accepted.
        closest_margin_nats: of the matches the verification rejected, the best log likelihood ratio minus the
            threshold it had to beat (negative, nats); None when no rejected match formed a hypothesis.
    """

    robot_a: str
    robot_b: str
    tried: int
    accepted: int
    closest_margin_nats: float | None

    def never_met(self) -> str | None:
        """A line saying that no match of the pair was accepted and how close the closest came (None when one was)."""
        if self.accepted:
            return None
        margin = self.closest_margin_nats
        why = (
            "no match formed a hypothesis (too few candidates)" if margin is None
            else "one beat the chance threshold but had too few, too loose or too clustered partners" if margin >= 0
            else f"the closest was {-margin:.1f} nats below the chance threshold: their maps do not overlap, or too "
            "little of what both mapped agrees"
        )  # fmt: skip
        return f"{self.robot_a} - {self.robot_b}: none of {self.tried} matches accepted ({why})"

    def to_json_dict(self) -> dict:
        margin = self.closest_margin_nats
        return {"robots": [self.robot_a, self.robot_b], "tried": self.tried, "accepted": self.accepted,
                "closest_margin_nats": None if margin is None else round(margin, 2)}  # fmt: skip


def pair_matches(records: list[MatchRecord]) -> list[PairMatches]:
    """The inter-robot match records grouped by robot pair (segments count as their robot; loop closures,
    a robot with itself, are left out), pairs in name order."""
    tried: dict[tuple[str, str], list[MatchRecord]] = {}
    for r in records:
        a, b = agent_robot(r.robot_a)[0], agent_robot(r.robot_b)[0]
        if a != b:
            tried.setdefault((min(a, b), max(a, b)), []).append(r)
    out = []
    for (a, b), rows in sorted(tried.items()):
        margins = [
            r.evidence.llr - r.evidence.llr_threshold
            for r in rows
            if not r.success and r.evidence is not None and np.isfinite(r.evidence.llr - r.evidence.llr_threshold)
        ]
        out.append(PairMatches(a, b, len(rows), sum(r.accepted for r in rows), max(margins) if margins else None))
    return out
