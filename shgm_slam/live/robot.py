"""``LiveRobot``: one robot fed frame by frame in its own process, for a map server over Eclipse Zenoh
(``shgm_slam.live``)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.config import ShgmConfig
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError, ShgmError
from shgm_slam.live.frames import LivePose, Warmup, live_config, pose_of
from shgm_slam.types import DepthOrigin, Intrinsics

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run starts
    from shgm_slam.robot.drive import DriveSummary
    from shgm_slam.robot.node import RobotNode

log = logging.getLogger(__name__)


class LiveRobot:
    """One robot fed frame by frame in its own process, talking to a map server over Eclipse Zenoh (``shgm-slam
    server`` elsewhere): ``shgm-slam robot`` for a camera that is driving now. Frames are held until its first
    frames set its settings (``Warmup``), then each ``add_frame`` runs its frame, sends its keyframe and applies the
    server's corrections. Between frames, ``poll`` keeps the link alive (the server takes a robot silent for long as
    gone). ``finish`` tells the server the robot is done and waits (at most ``wait_s``) until it holds every
    keyframe and has finished. Leaving a ``with`` block finishes it too: on a Ctrl-C (or ``sys.exit``) as
    ``shgm-slam robot`` does (its trajectories so far written; the server, not told the robot is done, keeps it and
    a robot of its name started again resumes it); on an error the link is closed (the server keeps what it holds)
    and the robot takes no more frames.

    Args:
        name: the robot's name (unique in the fleet).
        intrinsics: its camera's ``Intrinsics``.
        config: an ``ShgmConfig``, a YAML file, or None for the defaults (the fleet's: the server compares them).
        connect: the server's Zenoh endpoint(s), comma-separated (default ``tcp/127.0.0.1:7447``).
        out: where to write this robot's trajectories at the end (None: nowhere).
        depth_origin: whether the depth you give is measured or predicted by a network.
        wait_s: at ``finish``, wait at most this long for the server.

    Raises:
        ConfigError: a bad name, configuration or endpoint; a poses-file odometry.
        DataError: intrinsics that are not valid; ``out`` cannot be written.
    """

    def __init__(
        self,
        name: str,
        intrinsics: Intrinsics,
        *,
        config: ShgmConfig | Path | str | None = None,
        connect: str | None = None,
        out: Path | str | None = None,
        depth_origin: DepthOrigin = DepthOrigin.MEASURED,
        wait_s: float = 60.0,
    ) -> None:
        from shgm_slam.io.export import check_writable_dir
        from shgm_slam.transport.factory import NodeRole, make_transport
        from shgm_slam.transport.keys import validate_robot_name

        validate_robot_name(name)
        self.name, self.wait_s = name, float(wait_s)
        self.cfg = live_config(config, [name])
        self.stream = FrameStream(intrinsics, depth_origin=depth_origin, name=name)
        self.out_dir = None if out is None else check_writable_dir(Path(out))
        self._warmup = Warmup(name, self.stream, self.cfg)
        self._held: list[int] = []
        self._transport = make_transport(NodeRole.ROBOT, connect)
        self._node: RobotNode | None = None
        self._processed = 0
        self._skipped: list[str] = []
        self._t_start = time.perf_counter()
        self._summary: DriveSummary | None = None
        self._ended: str | None = None  # why the link was closed without a summary (an error, a failed finish)

    @property
    def started(self) -> bool:
        """Its first frames have set its settings and its frames now run as they arrive."""
        return self._node is not None

    def add_frame(
        self,
        image_rgb: np.ndarray,
        timestamp_s: float,
        *,
        depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
        T_world_cam: np.ndarray | None = None,
        T_odom_cam: np.ndarray | None = None,
    ) -> list[LivePose]:
        """Give the robot's next frame (arguments as ``LiveRun.add_frame``); returns the frames this call ran.

        Raises:
            ConfigError: the robot has finished, or its link was closed (an error left its ``with`` block, or
                ``finish`` failed). DataError: a bad frame (nothing changed), or its first frames cannot be used.
                ModelError: a model's output is unusable on its first frames. ProtocolError: the server refused
                this robot (its name is taken by a live process).
        """
        self._check_open()
        index = self.stream.append(image_rgb, timestamp_s, depth_m=depth_m, label_ids=label_ids,
                                   T_world_cam=T_world_cam, T_odom_cam=T_odom_cam)  # fmt: skip
        if self._node is not None and not self._held:
            return [self._step(index)]
        self._held.append(index)  # (a running robot's: behind frames a Ctrl-C left held)
        if self._node is None:
            try:
                self._warmup.offer(index)
                if not self._warmup.ready:
                    return []
                self._start()
            except ShgmError as exc:
                # its first frames cannot be used, a model's output is unusable, the server refused its name: each
                # later frame would be held and refused again, so the robot takes no more frames
                self._node, self._ended = None, f"it could not start ({exc})"
                self._held.clear()
                self._transport.close()
                raise
        return self._run_held()

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Every frame the robot has run in the shared frame as the server's latest corrections place it
        (``LiveRun.trajectory``): ``(timestamps_s (N,), T_shared_cam (N, 4, 4))``, NaN rows for frames of segments
        not placed; None before it runs or while no segment is placed."""
        fused = None if self._node is None else self._node.fused()
        if fused is None:
            return None
        return self.stream.timestamps_s[: len(fused)].copy(), fused

    def poll(self, timeout_s: float = 0.0) -> None:
        """Keep the link to the server alive between frames: the heartbeat, corrections, re-sends (at most
        ``timeout_s`` waiting for a message)."""
        if self._node is not None:
            self._node.heartbeat()
            self._node.poll(timeout_s=timeout_s)

    def finish(self) -> DriveSummary:
        """The robot is done: its last keyframes and per-frame odometry go to the server, which is waited for (at
        most ``wait_s``); its trajectories are written to ``out``. Finishing again returns the summary.

        Raises:
            DataError: no frame was given, or its first frames cannot be used (the link is then closed).
            ConfigError: the link was closed before (an error left the ``with`` block, or ``finish`` failed).
        """
        if self._summary is not None:
            return self._summary
        self._check_open()
        return self._finish(interrupted=False)

    def _finish(self, *, interrupted: bool) -> DriveSummary:
        """``finish``; ``interrupted`` (a stop left the ``with`` block): the frames still held are not run and the
        server is not waited for to finish, as ``shgm-slam robot`` does on a Ctrl-C."""
        from shgm_slam.robot.drive import drive_summary, write_robot_trajectories

        try:
            if self._node is None:
                if not len(self.stream):
                    raise DataError(f"robot {self.name!r}: no frame was given; nothing to send the map server")
                self._start()
            if not interrupted:
                self._run_held()
            node = self._node
            if not interrupted:  # a stopped robot is not done: the server keeps it and a robot of its name resumes
                node.done()
            acknowledged = node.wait_acknowledged(self.wait_s, until_finished=not interrupted)
            if not node.all_acknowledged():
                log.warning("%s: the map server did not acknowledge every keyframe within %.0f s", self.name,
                            self.wait_s)  # fmt: skip
            if self.out_dir is not None:
                write_robot_trajectories(self.out_dir, node)
            self._summary = drive_summary(node, self._processed, acknowledged, time.perf_counter() - self._t_start,
                                          interrupted, self._skipped)  # fmt: skip
        except BaseException as exc:
            self._ended = f"finish failed ({type(exc).__name__}: {exc})"
            raise
        finally:
            self._transport.close()
        return self._summary

    def __enter__(self) -> LiveRobot:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._summary is not None or self._ended is not None:
            return
        if kind is None:
            self.finish()
        elif not issubclass(kind, Exception) and self._node is not None:  # a Ctrl-C, sys.exit: as shgm-slam robot
            self._finish(interrupted=True)  # (its trajectories so far written; not done on the server)
        else:  # an error: the link goes; the server keeps what it holds and waits for the robot
            self._ended = f"its with block was left by {kind.__name__}: {exc}"
            self._transport.close()

    def _check_open(self) -> None:
        """ConfigError once the robot has finished or its link was closed."""
        if self._summary is not None:
            raise ConfigError(f"robot {self.name!r} has finished; start a new LiveRobot for more frames")
        if self._ended is not None:
            raise ConfigError(f"robot {self.name!r}: its link to the map server was closed: {self._ended}; start a "
                              "new LiveRobot for more frames")  # fmt: skip

    def _start(self) -> None:
        """Make the robot's front end from its first frames and say hello to the server."""
        from shgm_slam.robot.node import RobotNode

        self._node = RobotNode(self._warmup.frontend(), self._transport)
        self._node.hello()

    def _run_held(self) -> list[LivePose]:
        """Run the frames held so far, in order; each leaves ``_held`` as it runs (a Ctrl-C between them leaves the
        rest held, to run at the next frame or ``finish``)."""
        return [self._step(i, held=True) for i in list(self._held)]

    def _step(self, index: int, *, held: bool = False) -> LivePose:
        from shgm_slam.interrupts import stops_deferred

        node = self._node
        assert node is not None
        res, skipped = None, None
        with stops_deferred():  # a stop lands between frames, never inside the robot's step
            if held:
                self._held.remove(index)
            try:
                res = node.step(index)
                self._processed += 1
            except DataError as exc:
                skipped = f"frame {index}: {exc}"
                self._skipped.append(skipped)
                log.warning("%s: skipped frame %d: %s", self.name, index, exc)
            node.poll()
            self.stream.release(index)
            return pose_of(self.name, index, float(self.stream.timestamps_s[index]), res, node, skipped)
