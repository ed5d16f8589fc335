"""What crosses the robot / map-server boundary (robots may be separate processes)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from shgm_slam.graph.semantic_graph import GraphUpdate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeyframeMessage:
    """What a robot sends to the map server for each keyframe (small: a pose and graph node states).

    ``T_odom_kf`` is the keyframe's camera pose in the robot's odometry frame (its first camera frame).
    ``robot`` is the sending agent: the robot, or one of its later trajectory segments (``segment_agent``).
    """

    robot: str
    kf_index: int
    frame_index: int
    timestamp_s: float
    T_odom_kf: np.ndarray
    graph_update: GraphUpdate
    up_odom: np.ndarray | None = None  # (3,) unit "up" (ground normal) in the odometry frame, if known
