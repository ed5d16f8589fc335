"""One robot's record in the pose graph: its keyframe poses in its odometry frame, the path length and
ground normal at each, and the per-robot state the graph keeps about them (anchoring, attitude, drift,
straight stretches).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shgm_slam.backend.stretches import StretchTracker


@dataclass
class RobotTrack:
    """A robot of the pose graph: what it recorded (``append``) and what the graph decided about it."""

    index: int
    T_odom_kf: list[np.ndarray] = field(default_factory=list)
    path_m: list[float] = field(default_factory=list)
    anchor_closure: int | None = None  # closure id that anchored it (None for robot 0 or unanchored)
    anchored: bool = False
    T_shared_odom_init: np.ndarray | None = None  # alignment used when it was anchored
    up_odom: list[np.ndarray] = field(default_factory=list)  # each keyframe's ground normal (NaN: none)
    measured: list[int] = field(default_factory=list)  # keyframes with a ground normal
    attitude_sigma_rad: float | None = None  # measured once it has ``attitude_warmup`` normals
    attitude_next: int = 0  # keyframes before this one have had their attitude factor (if measured)
    drift_rot_rad_per_m: float | None = None  # rotation drift rate its odometry factors use (None: the prior)
    stretches: StretchTracker | None = None  # each keyframe's straight stretch (None: not tracked)
    _odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # T_odom_kf as a growing array
    _path: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def append(self, T_odom_kf: np.ndarray, up_odom: np.ndarray | None = None) -> None:
        """Record the next keyframe pose, its ground normal (odometry frame; None: not measured) and the
        odometry path length up to it."""
        k = len(self.T_odom_kf)
        self.up_odom.append(np.full(3, np.nan) if up_odom is None else up_odom)
        if up_odom is not None:
            self.measured.append(k)
        step = 0.0 if k == 0 else float(np.linalg.norm(T_odom_kf[:3, 3] - self.T_odom_kf[-1][:3, 3]))
        self.path_m.append((self.path_m[-1] if k else 0.0) + step)
        self.T_odom_kf.append(T_odom_kf)
        if k == self._odom.shape[0]:  # amortised O(1): double the buffers
            size = max(16, 2 * k)
            self._odom = np.concatenate([self._odom, np.zeros((size - k, 4, 4))])
            self._path = np.concatenate([self._path, np.zeros(size - k)])
        self._odom[k] = T_odom_kf
        self._path[k] = self.path_m[-1]
        if self.stretches is not None:
            self.stretches.append(self._odom[: k + 1, :3, 3], self._path[: k + 1])

    def odometry(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, 4, 4) keyframe poses in the odometry frame and (K,) path length at each, metres (views)."""
        k = len(self.T_odom_kf)
        return self._odom[:k], self._path[:k]
