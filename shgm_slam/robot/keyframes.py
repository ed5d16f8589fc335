"""Keyframe selection: a new keyframe after enough motion."""

from __future__ import annotations

import logging

import numpy as np

from shgm_slam.geometry import se3

log = logging.getLogger(__name__)


class KeyframeSelector:
    """A new keyframe every ``distance_m`` metres or ``angle_deg`` degrees of motion (the first frame too)."""

    def __init__(self, distance_m: float, angle_deg: float) -> None:
        self.distance_m = distance_m
        self.angle_rad = np.radians(angle_deg)
        self._T_odom_last: np.ndarray | None = None

    def is_keyframe(self, T_odom_cam: np.ndarray) -> bool:
        """True when ``T_odom_cam`` (4, 4) moved far enough from the last keyframe (and records it)."""
        if self._T_odom_last is not None:
            d = se3.inverse(self._T_odom_last) @ T_odom_cam
            if np.linalg.norm(d[:3, 3]) < self.distance_m and se3.rotation_angle(d) < self.angle_rad:
                return False
        self._T_odom_last = np.array(T_odom_cam, dtype=np.float64)
        return True
