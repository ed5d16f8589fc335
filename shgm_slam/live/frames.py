"""What live runs share: the pose each frame gets (``LivePose``), a robot's first frames until its settings can be
set (``Warmup``), the configuration check, and a frame's pose from its front-end result (``pose_of``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.api import config_of
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run starts
    from shgm_slam.robot.build import RobotPerception
    from shgm_slam.robot.frontend import FrameResult, RobotFrontend
    from shgm_slam.robot.node import RobotNode
    from shgm_slam.scene_scale import ScaleSampler

@dataclass(frozen=True)
class LivePose:
    """What the system made of one frame, as soon as it ran.

    Attributes:
        robot: the robot's name.
        index: the frame's index among the robot's frames (0 = its first ``add_frame``).
        timestamp_s: the frame's time, seconds, as given.
        T_odom_cam: (4, 4) camera -> the robot's odometry frame (of ``agent``, its current trajectory segment);
            NaN when the frame belongs to no segment (after an odometry failure, before it measures again).
        T_shared_cam: (4, 4) camera -> the shared frame (the first robot's first camera; where the run started
            without a first camera that sent nothing, the first robot it started with: ``START_WAIT_FRAMES``)
            as the map server has placed the segment so far, or None while it is not placed.
        keyframe: the frame became a keyframe (its objects went into the semantic graph).
        agent: the trajectory segment it belongs to (``car1``, ``car1~1`` after a failure); "" when skipped.
        skipped: why the frame was skipped (unreadable depth, a model error on it), else None.
        measured: the odometry measured this frame's pose; False where it only predicted it from the last motion
            (no usable depth or too few points, registration or tracking failed: the health check ends such a
            stretch after ``odometry.max_coast_s``), and for a skipped frame.
    """

    robot: str
    index: int
    timestamp_s: float
    T_odom_cam: np.ndarray
    T_shared_cam: np.ndarray | None
    keyframe: bool
    agent: str
    skipped: str | None = None
    measured: bool = False


class Warmup:
    """One robot's first frames until its settings can be set: its perception, made at its first frame, and a
    ``ScaleSampler`` offered the frames it wants (``ready``: no later frame would change the settings).

    Args:
        name: the robot.
        stream: its frames.
        cfg: the fleet configuration.
    """

    def __init__(self, name: str, stream: FrameStream, cfg: ShgmConfig) -> None:
        self.name, self.stream, self.cfg = name, stream, cfg
        self._prepared: RobotPerception | None = None
        self._sampler: ScaleSampler | None = None

    @property
    def ready(self) -> bool:
        """Its frames so far set its settings as the whole sequence would."""
        return self._sampler is not None and self._sampler.done

    def offer(self, index: int) -> None:
        """Frame ``index`` has arrived: measured when the sampler wants it.

        Raises:
            DataError, ModelError: the robot's perception cannot be made (no depth and no depth model, ...).
        """
        from shgm_slam.robot.build import robot_perception
        from shgm_slam.scene_scale import ScaleSampler

        if self._prepared is None:
            self._prepared = robot_perception(self.name, self.stream, self.cfg)
            self._sampler = ScaleSampler(self._prepared.perceive)
        if self._sampler.wants(index):  # type: ignore[union-attr]
            self._sampler.offer(index, self.stream)  # type: ignore[union-attr]

    def frontend(self, max_segments: int | None = None) -> RobotFrontend:
        """The robot's front end from the frames it has (``robot.build.make_frontend``).

        Raises:
            DataError, ModelError: its first frames cannot be used.
        """
        from shgm_slam.robot.build import make_frontend

        return make_frontend(self.name, self.stream, self.cfg, max_segments=max_segments, prepared=self._prepared,
                             sampler=self._sampler)  # fmt: skip


def live_config(config: ShgmConfig | Path | str | None, names: list[str]) -> ShgmConfig:
    """``config`` as an ``ShgmConfig`` (``api.config_of``), refused where it cannot run frames that arrive one by one.

    Raises:
        ConfigError: a bad configuration; a poses-file odometry for any of ``names``.
    """
    cfg = config_of(config)
    if any(cfg.for_robot(r).odometry.kind is OdometryKind.FILE for r in names):
        raise ConfigError(
            "odometry 'file' reads a recorded sequence's poses file, which frames fed one by one do not have; give "
            "your odometry's pose with each frame instead (add_frame(..., T_odom_cam=...), run as odometry "
            "'given', which 'auto' chooses), or use auto, kiss-icp, visual, hybrid or gt"
        )
    return cfg


def pose_of(
    robot: str, index: int, timestamp_s: float, res: FrameResult | None, node: RobotNode | None, skipped: str | None
) -> LivePose:
    """The ``LivePose`` of a frame: ``res`` its ``FrameResult`` (None: skipped, ``skipped`` says why), ``node`` the
    robot's node (where the server has placed its segments)."""
    if res is None:
        return LivePose(robot, index, timestamp_s, np.full((4, 4), np.nan), None, False, "", skipped)
    T_shared_odom = None if node is None else node.T_shared_odom(res.agent)
    placed = T_shared_odom is not None and np.isfinite(res.T_odom_cam).all()
    T_shared_cam = T_shared_odom @ res.T_odom_cam if placed else None
    measured = res.odometry_ok and bool(np.isfinite(res.T_odom_cam).all())
    return LivePose(robot, index, timestamp_s, res.T_odom_cam.copy(), T_shared_cam, res.message is not None, res.agent,
                    measured=measured)  # fmt: skip
