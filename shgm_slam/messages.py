"""What crosses the robot / map-server boundary: the message schema (robots are separate processes).

Robots send ``HelloMessage`` (once per process start), ``KeyframeMessage`` (one per keyframe) and
``DoneMessage`` (after their last frame); the map server answers each robot with ``CorrectionMessage``
(where its agents are in the shared frame, and which keyframes arrived) and broadcasts
``StatusMessage``. ``shgm_slam.wire`` turns them into versioned, compact bytes and back.

Agents: a robot's keyframes belong to the robot (``car1``) or to one of its later trajectory segments
(``car1#1``, ``agents.segment_agent``); keyframe indices count per agent from 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from shgm_slam.graph.semantic_graph import GraphUpdate


@dataclass(frozen=True)
class HelloMessage:
    """A robot process announces itself. ``session`` is random per process start: a hello with a new
    session under a known name is a restart (resume) if the old session went silent, else a clash."""

    robot: str
    session: str
    num_frames: int


@dataclass(frozen=True)
class KeyframeMessage:
    """What a robot sends to the map server for each keyframe (small: a pose and graph node states).

    ``T_odom_kf`` is the keyframe's camera pose in the agent's odometry frame (its first camera frame).
    ``robot`` is the sending agent: the robot, or one of its later trajectory segments (``segment_agent``).
    """

    robot: str
    kf_index: int
    frame_index: int
    timestamp_s: float
    T_odom_kf: np.ndarray
    graph_update: GraphUpdate
    up_odom: np.ndarray | None = None  # (3,) unit "up" (ground normal) in the odometry frame, if known
    session: str = ""  # the sending robot process (``HelloMessage.session``)


@dataclass(frozen=True, eq=False)
class RobotTrajectory:
    """Every frame of one robot in its odometry: what the server needs to write per-frame trajectories.

    ``timestamps_s`` (N,) seconds; ``frame_segment`` (N,) the trajectory segment of each frame (-1: in
    none, e.g. dropped after an odometry failure); ``T_odom_cam`` (N, 4, 4) each frame in its segment's
    odometry frame (NaN rows where the segment is -1).
    """

    timestamps_s: np.ndarray
    frame_segment: np.ndarray
    T_odom_cam: np.ndarray


@dataclass(frozen=True)
class DoneMessage:
    """A robot has sent its last keyframe: ``keyframes`` is how many each of its agents sent in all;
    ``trajectory`` its per-frame odometry (None: the robot does not share it)."""

    robot: str
    session: str
    keyframes: dict[str, int]
    trajectory: RobotTrajectory | None = None


@dataclass(frozen=True)
class CorrectionMessage:
    """The map server's answer to one robot.

    ``received``: keyframes the server holds per agent of the robot (0 .. n-1 arrived; the robot
    re-sends from n on). ``T_shared_kf``: (K, 4, 4) fused keyframe poses in the shared frame for each
    agent of the robot that is placed (K = the agent's keyframes the server holds; unplaced agents are
    absent). ``session`` echoes the robot session it answers ("" = any).
    """

    robot: str
    session: str
    received: dict[str, int]
    T_shared_kf: dict[str, np.ndarray] = field(default_factory=dict)


class RobotState(str, Enum):
    """What the map server knows of a robot's process."""

    ACTIVE = "active"  # heard from recently
    STALE = "stale"  # silent for longer than the stale timeout; kept, resumes when it comes back
    DONE = "done"  # sent its last keyframe


@dataclass(frozen=True)
class RobotStatus:
    """One robot in a ``StatusMessage``."""

    state: RobotState
    keyframes: int  # over all its agents
    placed_agents: tuple[str, ...]
    agents: tuple[str, ...]
    provisional_agents: tuple[str, ...] = ()  # placed, not confirmed by an independent graph match yet


@dataclass(frozen=True)
class StatusMessage:
    """The map server's broadcast: who it knows, their state, whether it has finished.

    ``refused`` names robots whose last hello was refused (name clash) with the reason."""

    server_session: str
    reference: str
    robots: dict[str, RobotStatus]
    finished: bool = False
    refused: dict[str, str] = field(default_factory=dict)


Message = HelloMessage | KeyframeMessage | DoneMessage | CorrectionMessage | StatusMessage
