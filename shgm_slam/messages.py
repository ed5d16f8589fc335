"""What crosses the robot / map-server boundary: the message schema (robots are separate processes).

Robots send ``HelloMessage`` (when the process starts, then as heartbeat), ``KeyframeMessage`` (one per
keyframe) and ``DoneMessage`` (after their last frame); the map server answers each robot with
``CorrectionMessage`` (which keyframes arrived; where its agents are in the shared frame: in full when the
robot (re)connects or asks, else only what moved, ``shgm_slam.corrections``) and broadcasts
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
    """A robot process announces itself (and repeats it as its heartbeat). ``session`` is random per
    process start: a hello with a new session under a known name is a restart (resume) if the old
    session went silent, else a clash. ``resync``: the robot missed a correction and asks for a full one.
    ``start_s``: the timestamp of its sequence's first frame (s); ``progress_s``: how far it has got, in
    seconds since that first frame (None before its first frame): every keyframe it made of frames up to
    there has arrived at the map server session ``server_session`` ("" = none known yet), by that server's
    acknowledgements (the map server takes keyframes of all robots in this time order). ``settings_digest``:
    ``ShgmConfig.front_end_digest`` of the robot's configuration ("" = not said; the map server refuses a robot
    whose digest differs from its own for that robot)."""

    robot: str
    session: str
    num_frames: int
    resync: bool = False
    start_s: float = 0.0
    progress_s: float | None = None
    server_session: str = ""
    settings_digest: str = ""


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
    up_odom: np.ndarray | None = None  # (3,) this keyframe's unit ground normal (up) in the odometry frame, if fitted
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
    ``trajectory`` its per-frame odometry (None: the robot does not share it); ``settings`` its front end's
    data-derived values, ``{stage: {field: value}}`` (``scene_scale.effective_fields``; the map server writes
    them into its ``config.yaml``), None when not said."""

    robot: str
    session: str
    keyframes: dict[str, int]
    trajectory: RobotTrajectory | None = None
    settings: dict[str, dict[str, float | int | bool]] | None = None


@dataclass(frozen=True, eq=False)
class AgentCorrection:
    """Where one agent of a robot is in the shared frame, or what changed of it (``CorrectionMessage``).

    ``T_shared_odom``: (4, 4) the agent's odometry frame in the shared frame (at its latest keyframe), or
    None when the agent is not placed (the robot drops what it holds of it). ``num_keyframes``: K, the
    agent's keyframes the server holds. ``T_move``: (4, 4) a rigid motion of the shared frame applied
    first to every pose the robot holds of the agent (``T_move @ T_shared_kf``), or None. ``kf_indices``
    (M,) int64, increasing, < K, and ``T_shared_kf`` (M, 4, 4): the fused poses of the keyframes that are
    new or moved otherwise; the robot keeps the others.
    """

    T_shared_odom: np.ndarray | None
    num_keyframes: int = 0
    kf_indices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    T_shared_kf: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    T_move: np.ndarray | None = None


@dataclass(frozen=True)
class CorrectionMessage:
    """The map server's answer to one robot.

    ``received``: keyframes the server holds per agent of the robot (0 .. n-1 arrived; the robot
    re-sends from n on). ``seq``: 0 for an acknowledgement alone; otherwise the number of this
    correction for the robot's session (1, 2, ...). A ``full`` correction replaces everything the robot
    holds (agents absent are not placed); any other carries only what changed since correction
    ``seq - 1``, which the robot must hold (else it asks for a full one: ``HelloMessage.resync``).
    ``agents``: agent -> ``AgentCorrection``. ``session`` echoes the robot session it answers ("" = any).
    """

    robot: str
    session: str
    received: dict[str, int]
    seq: int = 0
    full: bool = False
    agents: dict[str, AgentCorrection] = field(default_factory=dict)


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
    waiting_agents: tuple[str, ...] = ()  # not placed: accepted matches, too few independent ones to enter
    segments_allowed: int = 0  # trajectory segments the robot may start (its share of the pose graph; 0: not said)


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
