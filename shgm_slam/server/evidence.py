"""What a graph match rests on: its evidence record, the objects behind its closures (what makes two matches
independent evidence) and the kinds of what several matches share."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.confirmation import Sharing, Support
from shgm_slam.backend.stretches import is_stretch_token
from shgm_slam.matching import MatchResult
from shgm_slam.server.records import MatchEvidence

MARGINAL_OBJECT = "marginal-with"
"""Pseudo-object every marginal match of a robot pair rests on (``MapServer._marginal``), with the partner's name."""


def match_evidence(result: MatchResult, keyframe_b: int) -> MatchEvidence | None:
    """The match's best hypothesis and its verification numbers (None when it formed no hypothesis).

    Args:
        result: the graph match (its ``T_a_b_hypothesis`` maps B's odometry frame into A's).
        keyframe_b: B's newest keyframe when the match was made.
    """
    if result.T_a_b_hypothesis is None:
        return None
    return MatchEvidence(
        np.asarray(result.T_a_b_hypothesis, dtype=np.float64), keyframe_b, float(result.llr),
        float(result.llr_threshold), int(result.support), float(result.expected_chance), int(result.overlap_a),
        int(result.overlap_b), float(result.rival_llr), float(result.centroid_sigma_m),
    )  # fmt: skip


def support_objects(support: Support) -> frozenset[tuple[str, int]]:
    """A closure's support (agent -> node ids) as the pose graph's objects: ``(agent, node id)`` pairs."""
    return frozenset((agent, node) for agent, nodes in support.items() for node in nodes)


def match_objects(robot_a: str, robot_b: str, support: Support, marginal: bool) -> frozenset:
    """The objects behind every closure of a match between ``robot_a`` and ``robot_b`` (what the pose graph
    compares to tell independent evidence): the match's inliers of both robots (``support``: agent -> node
    ids) as ``(agent, node id)`` pairs, none for a loop closure (one robot), and for a ``marginal`` match
    (``MapServer._marginal``) the pair's shared pseudo-object (``MARGINAL_OBJECT``)."""
    objects = support_objects(support) if robot_a != robot_b else frozenset()
    if marginal:  # every marginal match of the pair rests on one shared pseudo-object: one piece at most
        objects |= {(robot_a, f"{MARGINAL_OBJECT}:{robot_b}"), (robot_b, f"{MARGINAL_OBJECT}:{robot_a}")}
    return objects


def sharing(shared: frozenset) -> tuple[Sharing, ...]:
    """The kinds of what several graph matches rest on in common (``MultiRobotPoseGraph.shared_support``):
    stretch tokens (``backend/stretches.py``), the marginal pseudo-object (``MARGINAL_OBJECT``), objects."""
    kinds = set()
    for item in shared:
        if is_stretch_token(item):
            kinds.add(Sharing.STRETCHES)
        elif isinstance(item, tuple) and len(item) == 2 and str(item[1]).startswith(MARGINAL_OBJECT):
            kinds.add(Sharing.CHANCE)
        else:
            kinds.add(Sharing.OBJECTS)
    return tuple(k for k in Sharing if k in kinds)
