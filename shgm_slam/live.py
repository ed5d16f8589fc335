"""Frames fed one by one, as cameras deliver them: the whole system (front ends, map server, viewer, results
folder) stepped by ``LiveRun.add_frame`` instead of a recorded sequence.

Each robot's first frames set its data-derived settings (extraction range, blob size, odometry voxel: the camera's
height above the ground and the depth it sees, ``scene_scale``), so a robot's frames are held until it has sent
enough of them (``ScaleSampler``: five frames that show the ground, 0.5 s apart: 21 frames at 10 fps where the ground
shows from the start, at most ``SAMPLE_SPAN_FRAMES``). The run starts once the first robot (the shared frame's)
and every other robot that has sent frames are that far; a robot whose camera starts later joins the running system
once its own first frames are in. Held frames run in the order they came, and from then on every ``add_frame`` of
a running robot runs its frame at once and returns its pose. Frames
given in the order ``run`` would take them (``data.interleave``: by time) give the same results as ``run`` on the
recorded sequences, file for file, where the depth is measured (a network's depth, scaled to the camera height, is
scaled from the frames seen so far, not from frames spread over the whole sequence). A frame the pipeline has run is
dropped (the robot's ``FrameStream`` holds only what is still to be run).

``finish`` ends the run (the final whole-graph matching, the results folder, the summary); leaving a ``with`` block
finishes it too, as stopped (no final matching) on a Ctrl-C, and marks the folder incomplete on any other error.

``LiveRobot`` is one robot fed the same way in its own process, for a map server elsewhere (``shgm-slam server``,
Eclipse Zenoh): ``shgm-slam robot`` on a camera that is driving now.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.api import config_of, viewer_mode
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.types import DepthOrigin, Intrinsics

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run starts
    from shgm_slam.robot.build import RobotPerception
    from shgm_slam.robot.drive import DriveSummary
    from shgm_slam.robot.frontend import RobotFrontend
    from shgm_slam.robot.node import RobotNode
    from shgm_slam.run_report import RunSummary
    from shgm_slam.runner import FleetRun
    from shgm_slam.scene_scale import ScaleSampler
    from shgm_slam.viz.rerun_logger import RerunMode

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LivePose:
    """What the system made of one frame, as soon as it ran.

    Attributes:
        robot: the robot's name.
        index: the frame's index among the robot's frames (0 = its first ``add_frame``).
        timestamp_s: the frame's time, seconds, as given.
        T_odom_cam: (4, 4) camera -> the robot's odometry frame (of ``agent``, its current trajectory segment);
            NaN when the frame belongs to no segment (after an odometry failure, before it measures again).
        T_shared_cam: (4, 4) camera -> the shared frame (the first robot's first camera) as the map server has
            placed the segment so far, or None while it is not placed.
        keyframe: the frame became a keyframe (its objects went into the semantic graph).
        agent: the trajectory segment it belongs to (``car1``, ``car1~1`` after a failure); "" when skipped.
        skipped: why the frame was skipped (unreadable depth, a model error on it), else None.
    """

    robot: str
    index: int
    timestamp_s: float
    T_odom_cam: np.ndarray
    T_shared_cam: np.ndarray | None
    keyframe: bool
    agent: str
    skipped: str | None = None


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
            "odometry 'file' reads a recorded sequence's poses file, which frames fed one by one do not have; "
            "use auto, kiss-icp, visual, hybrid or gt"
        )
    return cfg


def pose_of(robot: str, index: int, timestamp_s: float, res, node: RobotNode | None, skipped: str | None) -> LivePose:
    """The ``LivePose`` of a frame: ``res`` its ``FrameResult`` (None: skipped, ``skipped`` says why), ``node`` the
    robot's node (where the server has placed its segments)."""
    if res is None:
        return LivePose(robot, index, timestamp_s, np.full((4, 4), np.nan), None, False, "", skipped)
    T_shared_odom = None if node is None else node.T_shared_odom(res.agent)
    placed = T_shared_odom is not None and np.isfinite(res.T_odom_cam).all()
    T_shared_cam = T_shared_odom @ res.T_odom_cam if placed else None
    return LivePose(robot, index, timestamp_s, res.T_odom_cam.copy(), T_shared_cam, res.message is not None, res.agent)


class LiveRun:
    """The multi-robot system on frames that arrive one by one (module docstring).

    Args:
        cameras: robot name -> its camera's ``Intrinsics``, in order (the first robot's first camera frame is the
            shared frame).
        out: results folder (created now; written as the run goes, finished by ``finish``); None:
            ``results/<YYYYmmdd_HHMMSS>`` and ``results/latest``.
        config: an ``ShgmConfig``, a YAML file, or None for the defaults.
        viewer: where the Rerun recording goes (``viz.RerunMode``; None: nowhere).
        viewer_url: the viewer's gRPC URL for ``RerunMode.CONNECT``.
        depth_origin: whether the depth you give is measured (a sensor, a renderer: KISS-ICP) or predicted by a
            network (visual odometry, scaled to the camera height); one for all robots or one per robot.
        gt_shared_frame: the ground-truth poses you give share one world frame (the fused ATE is then measured in
            the shared frame).
        overwrite: reuse an ``out`` that holds an earlier run's results.

    Raises:
        ConfigError: no cameras, an invalid robot name, a bad configuration or viewer, a poses-file odometry
            (it needs the whole recorded sequence), a fleet the pose graph cannot hold.
        DataError: intrinsics that are not valid; ``out`` holds results (without ``overwrite``) or is in use.
    """

    def __init__(
        self,
        cameras: Mapping[str, Intrinsics],
        out: Path | str | None = None,
        *,
        config: ShgmConfig | Path | str | None = None,
        viewer: RerunMode | None = None,
        viewer_url: str | None = None,
        depth_origin: DepthOrigin | Mapping[str, DepthOrigin] = DepthOrigin.MEASURED,
        gt_shared_frame: bool = True,
        overwrite: bool = False,
    ) -> None:
        from shgm_slam.io.export import make_results_dir
        from shgm_slam.runner import check_fleet
        from shgm_slam.transport.keys import validate_robot_name
        from shgm_slam.viz.rerun_logger import make_viz

        if not isinstance(cameras, Mapping) or not cameras:
            raise ConfigError("no cameras given: pass {robot name: Intrinsics}, e.g. {'car1': Intrinsics(...)}")
        for name in cameras:
            validate_robot_name(name)
        self.cfg = cfg = live_config(config, list(cameras))
        self._share = check_fleet(list(cameras), cfg)
        origins = depth_origin if isinstance(depth_origin, Mapping) else dict.fromkeys(cameras, depth_origin)
        if set(origins) != set(cameras):
            raise ConfigError(f"depth_origin names robots {sorted(origins)}; give one for each of {list(cameras)}")
        self.streams = {r: FrameStream(K, depth_origin=origins[r], name=r) for r, K in cameras.items()}
        mode = viewer_mode(viewer, viewer_url)
        self.gt_shared_frame = gt_shared_frame
        self.out_dir = make_results_dir(None if out is None else Path(out), overwrite=overwrite)
        self._viz = make_viz(mode, robots=list(cameras), save_path=self.out_dir / "run.rrd", connect_url=viewer_url,
                             max_cloud_points=8000)  # fmt: skip
        self._warmups = {r: Warmup(r, stream, cfg) for r, stream in self.streams.items()}
        self._predicted = [r for r in cameras if cfg.for_robot(r).perception.depth_model is not None
                           or DepthOrigin(origins[r]) is DepthOrigin.PREDICTED]  # fmt: skip
        self._held: list[tuple[str, int]] = []  # frames of robots that do not run yet, in the order they came
        self._fleet: FleetRun | None = None
        self._summary: RunSummary | None = None
        self._closed = False  # finished, or ended by an error: no more frames
        self._lock = threading.RLock()  # cameras' threads may call at once: one frame at a time

    # --- feeding -------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """The run has started (the first robot's first frames and those of every robot that had sent any were in)."""
        return self._fleet is not None

    @property
    def warming(self) -> tuple[str, ...]:
        """The robots whose first frames are still too few to set their settings (their frames are held)."""
        return tuple(r for r, w in self._warmups.items() if not w.ready)

    def add_frame(
        self,
        robot: str,
        image_rgb: np.ndarray,
        timestamp_s: float,
        *,
        depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
        T_world_cam: np.ndarray | None = None,
    ) -> list[LivePose]:
        """Give the robot's next frame; run it, or hold it while the robot (or, before the run starts, another robot
        that has sent frames, or the first robot) is ``warming``.

        Args:
            robot: one of the cameras' names.
            image_rgb: (H, W, 3) uint8 RGB or (H, W) uint8 grey, the intrinsics' size.
            timestamp_s: seconds, later than the robot's last frame.
            depth_m: (H, W) float metres (0 or non-finite: invalid), or None when a depth model is configured.
            label_ids: (H, W) integer Cityscapes train ids, or None when a segmentation model is configured.
            T_world_cam: (4, 4) ground-truth pose, for the run's ATE (every frame or none), or None.

        Returns:
            The frames this call ran, in the order they came: this one once its robot runs; none while it is held;
            the held frames at the call that starts the run or lets a robot join it.

        Raises:
            ConfigError: an unknown robot, or the run has finished. DataError: a bad frame (nothing is changed:
                fix it and give it again), or a robot's first frames cannot be used (no valid depth, ...).
            ModelError: a model whose output is unusable on the robot's first frames.
        """
        with self._lock:
            self._check_open()
            stream = self.streams.get(robot)
            if stream is None:
                raise ConfigError(f"no camera {robot!r} in this run; its cameras are {', '.join(self.streams)}")
            index = stream.append(image_rgb, timestamp_s, depth_m=depth_m, label_ids=label_ids,
                                  T_world_cam=T_world_cam)  # fmt: skip
            if self._fleet is not None and robot in self._fleet.fronts:
                return [self._step(robot, index)]
            self._held.append((robot, index))
            with self._failing():
                self._warmups[robot].offer(index)
                return self._advance()

    def finish(self) -> RunSummary:
        """End the run: hold nothing back (robots still warming join with the frames they sent), the final
        whole-graph matching, the results folder and its summary (``metrics.json``). Robots that sent no frame are
        left out (a warning). Once finished, the run takes no more frames; ``finish`` again returns the summary.

        Raises:
            DataError: no robot sent a frame, or a robot's first frames cannot be used.
        """
        with self._lock:
            return self._finish()

    def _finish(self) -> RunSummary:
        if self._summary is not None:
            return self._summary
        self._check_open()
        with self._failing():
            self._advance(final=True)
            assert self._fleet is not None
            for r in self.streams.keys() - self._fleet.fronts.keys():
                log.warning("%s: no frame was given; the run went on without it", r)
                self._viz.log_text(f"{r}: no frame was given; the run went on without it", "WARN")
            self._summary = self._fleet.finish()
        self._release()
        return self._summary

    def __enter__(self) -> LiveRun:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._closed:
            return
        if kind is None:
            self.finish()
        elif issubclass(kind, KeyboardInterrupt) and self._fleet is not None and not self._fleet.finished:
            from shgm_slam.interrupts import stops_deferred

            with self._lock, stops_deferred():  # stopped between frames: what there is, written (no final matching)
                self._summary = self._fleet.finish(interrupted=True)
                self._release()
        else:
            self._mark_failed(exc)

    # --- inside ----------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            how = "finished" if self._summary is not None else f"ended with an error ({self.out_dir} is incomplete)"
            raise ConfigError(f"this live run has {how}; start a new LiveRun for more frames")

    def _advance(self, *, final: bool = False) -> list[LivePose]:
        """Start the run once the first robot and every robot that has sent frames are warm (``final``: with what
        they sent), let the robots that have warmed up since join it, and run the frames held for the robots that
        run; returns their poses in the order the frames came."""
        from shgm_slam.runner import FleetRun

        sent = [r for r, stream in self.streams.items() if len(stream)]
        if self._fleet is None:
            if not sent:
                raise DataError(f"no frames were given to any of the cameras ({', '.join(self.streams)}); "
                                "nothing to run")  # fmt: skip
            reference = next(iter(self.streams))
            if not final and not (reference in sent and all(self._warmups[r].ready for r in sent)):
                return []
            # at the end, a first camera that never sent a frame leaves the shared frame to the next one
            robots = {r: self.streams[r] for r in (sent if final else self.streams)}
            fronts = {r: self._warmups[r].frontend(self._share) for r in sent}
            self._fleet = FleetRun(robots, self.cfg, self.out_dir, fronts, viz=self._viz,
                                   gt_shared_frame=self.gt_shared_frame, predicted=self._predicted)  # fmt: skip
        fleet = self._fleet
        for r in sent:
            if r not in fleet.fronts and r in fleet.robots and (final or self._warmups[r].ready):
                fleet.add_robot(r, self._warmups[r].frontend(self._share))
                log.info("%s: joined the running system (its first frames set its settings)", r)
        now = [(r, i) for r, i in self._held if r in fleet.fronts]
        self._held = [(r, i) for r, i in self._held if r not in fleet.fronts]
        return [self._step(r, i) for r, i in now]

    def _step(self, robot: str, index: int) -> LivePose:
        from shgm_slam.interrupts import stops_deferred

        assert self._fleet is not None
        fleet = self._fleet
        with self._failing(), stops_deferred():  # a stop lands between frames, never inside a step
            skipped = len(fleet.skipped)
            res = fleet.step(robot, index)
        stream = self.streams[robot]
        stream.release(index)
        skipped_why = fleet.skipped[skipped] if res is None else None
        return pose_of(robot, index, float(stream.timestamps_s[index]), res, fleet.nodes[robot], skipped_why)

    @contextlib.contextmanager
    def _failing(self):
        """An error other than a bad frame ends the run: the folder is marked incomplete, the error goes on."""
        try:
            yield
        except Exception as exc:
            self._mark_failed(exc)
            raise

    def _mark_failed(self, exc: BaseException | None) -> None:
        from shgm_slam.io.export import ResultsWriter

        if self._closed:
            return
        if self.out_dir.is_dir() and isinstance(exc, Exception):
            ResultsWriter(self.out_dir).mark_failed(exc)
        elif self.out_dir.is_dir() and self._fleet is None:  # stopped before every robot's first frames came
            with contextlib.suppress(DataError):
                ResultsWriter(self.out_dir).mark_incomplete("stopped before every robot had sent its first frames")
        self._release()

    def _release(self) -> None:
        """The run is over: the results folder's lock released, the viewer's stream closed."""
        from shgm_slam.io.export import release_results_dir

        self._closed = True
        release_results_dir(self.out_dir)
        if self._fleet is None or not self._fleet.finished:  # (a finished run closed it)
            self._viz.close()


class LiveRobot:
    """One robot fed frame by frame in its own process, talking to a map server over Eclipse Zenoh (``shgm-slam
    server`` elsewhere): ``shgm-slam robot`` for a camera that is driving now. Frames are held until its first
    frames set its settings (``Warmup``), then each ``add_frame`` runs its frame, sends its keyframe and applies the
    server's corrections. Between frames, ``poll`` keeps the link alive (the server takes a robot silent for long as
    gone). ``finish`` tells the server the robot is done and waits (at most ``wait_s``) until it holds every
    keyframe and has finished.

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
    ) -> list[LivePose]:
        """Give the robot's next frame (arguments as ``LiveRun.add_frame``); returns the frames this call ran.

        Raises:
            ConfigError: the robot has finished. DataError: a bad frame (nothing changed), or its first frames
                cannot be used. ModelError: a model's output is unusable on its first frames. ProtocolError: the
                server refused this robot (its name is taken by a live process).
        """
        if self._summary is not None:
            raise ConfigError(f"robot {self.name!r} has finished; start a new LiveRobot for more frames")
        index = self.stream.append(image_rgb, timestamp_s, depth_m=depth_m, label_ids=label_ids,
                                   T_world_cam=T_world_cam)  # fmt: skip
        if self._node is not None:
            return [self._step(index)]
        self._held.append(index)
        self._warmup.offer(index)
        if not self._warmup.ready:
            return []
        self._start()
        held, self._held = self._held, []
        return [self._step(i) for i in held]

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
            DataError: no frame was given, or its first frames cannot be used.
        """
        from shgm_slam.robot.drive import drive_summary, write_robot_trajectories

        if self._summary is not None:
            return self._summary
        try:
            if self._node is None:
                if not len(self.stream):
                    raise DataError(f"robot {self.name!r}: no frame was given; nothing to send the map server")
                self._start()
                held, self._held = self._held, []
                for i in held:
                    self._step(i)
            node = self._node
            node.done()
            acknowledged = node.wait_acknowledged(self.wait_s, until_finished=True)
            if not node.all_acknowledged():
                log.warning("%s: the map server did not acknowledge every keyframe within %.0f s", self.name,
                            self.wait_s)  # fmt: skip
            if self.out_dir is not None:
                write_robot_trajectories(self.out_dir, node)
            self._summary = drive_summary(node, self._processed, acknowledged, time.perf_counter() - self._t_start,
                                          False, self._skipped)  # fmt: skip
        finally:
            self._transport.close()
        return self._summary

    def __enter__(self) -> LiveRobot:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._summary is not None:
            return
        if kind is None:
            self.finish()
        else:  # an error or a stop: the link goes; the server keeps what it holds and waits for the robot
            self._transport.close()

    def _start(self) -> None:
        from shgm_slam.robot.node import RobotNode

        self._node = RobotNode(self._warmup.frontend(), self._transport)
        self._node.hello()

    def _step(self, index: int) -> LivePose:
        from shgm_slam.interrupts import stops_deferred

        node = self._node
        assert node is not None
        res, skipped = None, None
        with stops_deferred():  # a stop lands between frames, never inside the robot's step
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
