"""Plain records of the pose graph's answers: the solver choice, closure status and decisions, the stored
closures, how a robot was anchored, and the graph's counters (``pose_graph.MultiRobotPoseGraph`` makes them).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np


class Factorization(str, Enum):
    """iSAM2's linear solver (``pose_graph`` module docstring, "Numerics")."""

    CHOLESKY = "CHOLESKY"
    QR = "QR"


class ClosureStatus(str, Enum):
    ACCEPTED = "accepted"  # in its robot pair's maximum consistent set
    REJECTED = "rejected"  # outside it (may come back if the evidence changes)


@dataclass(frozen=True)
class ClosureDecision:
    """What happened to a closure when it was added (``accepted`` may change with later evidence)."""

    accepted: bool
    reason: str
    closure_id: int = -1


@dataclass
class ClosureRecord:
    """One closure, stored in canonical order: robot_a has the lower robot index; a loop closure
    (``robot_a == robot_b``) has the older keyframe as ``kf_a``.

    ``T_a_b`` is ``T_akf_bkf``: it maps points in b's keyframe ``kf_b`` camera frame into a's keyframe
    ``kf_a`` camera frame. ``in_graph`` tells whether its factor is currently in iSAM2.
    """

    closure_id: int
    robot_a: str
    kf_a: int
    robot_b: str
    kf_b: int
    T_a_b: np.ndarray
    num_inliers: int
    status: ClosureStatus = ClosureStatus.REJECTED
    reason: str = ""
    in_graph: bool = False
    match_id: int | None = None  # the graph match it came from (closures of one match share it)
    querier: str | None = None  # the robot whose query found it (``robot_b`` as given; None: unknown)
    decisive: bool = False  # its match alone carries the evidence of two independent ones (anchors alone)

    @property
    def evidence(self) -> tuple[str, int]:
        """Its independent source of evidence: its match, or the closure itself when not given."""
        return ("match", self.match_id) if self.match_id is not None else ("closure", self.closure_id)


@dataclass(frozen=True)
class Anchor:
    """How a robot entered the shared frame: the closure used (None for robot 0) and the odometry-frame
    alignment ``T_shared_odom`` (4, 4) its buffered keyframes were inserted with."""

    closure_id: int | None
    T_shared_odom: np.ndarray


@dataclass(frozen=True)
class PoseGraphStats:
    """Counters of the pose graph; ``last_update_ms`` is the latest iSAM2 update including extra passes."""

    num_keyframes: int
    num_variables: int
    num_factors: int
    closures_total: int
    closures_accepted: int
    closures_rejected: int
    closures_in_graph: int
    anchored_robots: tuple[str, ...]
    rebuilds: int
    last_update_ms: float
    recoveries: int = 0  # iSAM2 failures recovered by rebuilding with QR
    attitude_factors: int = 0  # keyframes whose ground normal is a factor in iSAM2 now
