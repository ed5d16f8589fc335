"""Match records: one graph-match attempt and what the back end decided (``matches.json`` rows)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class MatchRecord:
    """One inter-robot match attempt and what the back end decided (a row of ``matches.json``)."""

    step: int
    robot_a: str
    robot_b: str
    query: str  # "submap" | "whole": which part of robot_b's graph was matched against robot_a's graph;
    # "loop": robot_b == robot_a, its recent submap against its own older graph (intra-robot loop closure)
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
        }
