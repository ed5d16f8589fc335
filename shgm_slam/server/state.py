"""The map server's snapshot: ``MapServerState``, everything a ``MapServer`` holds (what a snapshot stores)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shgm_slam.backend.state import PoseGraphState
from shgm_slam.graph.semantic_graph import GraphState
from shgm_slam.server.records import MatchRecord


@dataclass(frozen=True, eq=False)
class MapServerState:
    """Everything a ``MapServer`` holds (``MapServer.state``, what a snapshot stores);
    ``MapServer.from_state`` rebuilds a server that matches, votes and answers as this one would.

    Attributes:
        agents: every agent in the order the server learnt of them (the reference first).
        graphs: agent -> its mirrored semantic graph.
        T_odom_kf: agent -> (K, 4, 4) keyframe poses in its odometry frame, as received.
        up: agent -> (3,) sum of its keyframes' ground normals in its odometry frame (zeros while none
            fitted the ground; None is read as zeros).
        since_match: agent -> keyframes received since its last match.
        matches: every match attempt so far (the match log).
        closures: accepted closure keys ``(agent_a, kf_a, agent_b, kf_b)``.
        step, num_matches: keyframes received and successful matches so far.
        timings_ms: ``"match"`` / ``"backend"`` -> wall times so far, milliseconds.
        pose_graph: the pose graph's decisions and estimate.
        support: closure id -> agent -> the node ids behind it (confirmation of placements).
        surface_offset: the fleet's surface-to-centre offset estimate (``closures.SurfaceOffset.state``).
    """

    agents: tuple[str, ...]
    graphs: dict[str, GraphState]
    T_odom_kf: dict[str, np.ndarray]
    up: dict[str, np.ndarray | None]
    since_match: dict[str, int]
    matches: tuple[MatchRecord, ...]
    closures: tuple[tuple[str, int, str, int], ...]
    step: int
    num_matches: int
    timings_ms: dict[str, list[float]]
    pose_graph: PoseGraphState
    support: dict[int, dict[str, frozenset[int]]] = field(default_factory=dict)
    surface_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
