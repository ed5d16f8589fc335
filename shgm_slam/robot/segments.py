"""Trajectory segments: stretches of one robot with one healthy odometry."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.odometry.health import OdometryFailure
from shgm_slam.robot.keyframes import KeyframeSelector

log = logging.getLogger(__name__)


@dataclass
class TrajectorySegment:
    """A stretch of one robot's frames with one healthy odometry: its own odometry frame (the camera of
    ``first_frame``), keyframes and semantic graph. The map server treats it as an agent of its own;
    its pose relative to the robot's other segments is unknown until graph matching places it."""

    index: int
    agent: str
    first_frame: int
    graph: SemanticGraph
    keyframes: KeyframeSelector
    kf_frames: list[int] = field(default_factory=list)
    kf_poses: list[np.ndarray] = field(default_factory=list)
    end_failure: OdometryFailure | None = None  # the divergence that ended it (None: healthy to the end)

    @property
    def num_keyframes(self) -> int:
        return len(self.kf_frames)

    @property
    def num_nodes(self) -> int:
        """Nodes of its semantic graph."""
        return len(self.graph)
