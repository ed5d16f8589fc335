"""Frames fed one by one, as cameras deliver them: the whole system (front ends, map server, viewer, results
folder) stepped by ``LiveRun.add_frame`` instead of a recorded sequence.

Each robot's first frames set its data-derived settings (extraction range, blob size, odometry voxel: the camera's
height above the ground and the depth it sees, ``scene_scale``), so frames are held until every robot has sent
enough of them (``ScaleSampler``: usually 21-26 frames, at most ``SAMPLE_SPAN_FRAMES``); the held frames are then
run in the order they came, and from then on every ``add_frame`` runs its frame at once and returns its pose. Frames
given in the order ``run`` would take them (``data.interleave``: by time) give the same results as ``run`` on the
recorded sequences, file for file, where the depth is measured (a network's depth, scaled to the camera height, is
scaled from the frames seen so far, not from frames spread over the whole sequence). A frame the pipeline has run is
dropped (the robot's ``FrameStream`` holds only what is still to be run).

``finish`` ends the run (the final whole-graph matching, the results folder, the summary); leaving a ``with`` block
finishes it too, as stopped (no final matching) on a Ctrl-C, and marks the folder incomplete on any other error.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.api import config_of
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.types import DepthOrigin, Intrinsics

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run starts
    from shgm_slam.robot.build import RobotPerception
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
        agent: the trajectory segment it belongs to (``car1``, ``car1~1`` after a failure).
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
        from shgm_slam.viz.rerun_logger import DEFAULT_CONNECT_URL, RerunMode, make_viz, viewer_address

        if not isinstance(cameras, Mapping) or not cameras:
            raise ConfigError("no cameras given: pass {robot name: Intrinsics}, e.g. {'car1': Intrinsics(...)}")
        self.cfg = cfg = config_of(config)
        for name in cameras:
            validate_robot_name(name)
        if any(cfg.for_robot(r).odometry.kind is OdometryKind.FILE for r in cameras):
            raise ConfigError(
                "odometry 'file' reads a recorded sequence's poses file, which frames fed one by one do not have; "
                "use auto, kiss-icp, visual, hybrid or gt"
            )
        self._share = check_fleet(list(cameras), cfg)
        origins = depth_origin if isinstance(depth_origin, Mapping) else dict.fromkeys(cameras, depth_origin)
        if set(origins) != set(cameras):
            raise ConfigError(f"depth_origin names robots {sorted(origins)}; give one for each of {list(cameras)}")
        self.streams = {r: FrameStream(K, depth_origin=origins[r], name=r) for r, K in cameras.items()}
        try:
            mode = RerunMode.OFF if viewer is None else RerunMode(viewer)
        except ValueError:
            raise ConfigError(f"viewer {viewer!r}: choose one of {', '.join(m.value for m in RerunMode)}") from None
        if mode is RerunMode.CONNECT:
            viewer_address(viewer_url or DEFAULT_CONNECT_URL)  # a malformed URL is refused before any work
        self.gt_shared_frame = gt_shared_frame
        self.out_dir = make_results_dir(None if out is None else Path(out), overwrite=overwrite)
        self._viz = make_viz(mode, robots=list(cameras), save_path=self.out_dir / "run.rrd", connect_url=viewer_url,
                             max_cloud_points=8000)  # fmt: skip
        self._prepared: dict[str, RobotPerception] = {}
        self._samplers: dict[str, ScaleSampler] = {}
        self._held: list[tuple[str, int]] = []  # frames that came before the run started, in order
        self._fleet: FleetRun | None = None
        self._summary: RunSummary | None = None
        self._closed = False  # finished, or ended by an error: no more frames

    # --- feeding -------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """Every robot's first frames have come and the run has started (frames now run as they arrive)."""
        return self._fleet is not None

    @property
    def warming(self) -> tuple[str, ...]:
        """The robots whose first frames are still too few to set their settings (frames are held until none)."""
        return tuple(r for r in self.streams if r not in self._samplers or not self._samplers[r].done)

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
        """Give the robot's next frame; run it (or hold it while robots are ``warming``).

        Args:
            robot: one of the cameras' names.
            image_rgb: (H, W, 3) uint8 RGB or (H, W) uint8 grey, the intrinsics' size.
            timestamp_s: seconds, later than the robot's last frame.
            depth_m: (H, W) float metres (0 or non-finite: invalid), or None when a depth model is configured.
            label_ids: (H, W) integer Cityscapes train ids, or None when a segmentation model is configured.
            T_world_cam: (4, 4) ground-truth pose, for the run's ATE (every frame or none), or None.

        Returns:
            The frames this call ran, in order: this one once the run has started; none while it is held; every
            held frame at the call that starts the run.

        Raises:
            ConfigError: an unknown robot, or the run has finished. DataError: a bad frame (nothing is changed:
                fix it and give it again), or a robot's first frames cannot be used (no valid depth, ...).
            ModelError: a model whose output is unusable on the robot's first frames.
        """
        self._check_open()
        stream = self.streams.get(robot)
        if stream is None:
            raise ConfigError(f"no camera {robot!r} in this run; its cameras are {', '.join(self.streams)}")
        index = stream.append(image_rgb, timestamp_s, depth_m=depth_m, label_ids=label_ids, T_world_cam=T_world_cam)
        if self._fleet is not None:
            return [self._step(robot, index)]
        self._held.append((robot, index))
        with self._failing():
            self._sample(robot, index)
            if self.warming:
                return []
            self._start()
            return self._run_held()

    def finish(self) -> RunSummary:
        """End the run: hold nothing back (robots still warming start with the frames they sent), the final
        whole-graph matching, the results folder and its summary (``metrics.json``). Robots that sent no frame are
        left out (a warning). Once finished, the run takes no more frames; ``finish`` again returns the summary.

        Raises:
            DataError: no robot sent a frame, or a robot's first frames cannot be used.
        """
        if self._summary is not None:
            return self._summary
        self._check_open()
        with self._failing():
            if self._fleet is None:
                self._start()
                self._run_held()
            assert self._fleet is not None
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

            with stops_deferred():  # stopped between frames: what there is, written (no final matching)
                self._summary = self._fleet.finish(interrupted=True)
            self._release()
        else:
            self._mark_failed(exc)

    # --- inside ----------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            how = "finished" if self._summary is not None else f"ended with an error ({self.out_dir} is incomplete)"
            raise ConfigError(f"this live run has {how}; start a new LiveRun for more frames")

    def _sample(self, robot: str, index: int) -> None:
        """Offer the frame to the robot's ``ScaleSampler`` (its perception made at its first frame)."""
        from shgm_slam.robot.build import robot_perception
        from shgm_slam.scene_scale import ScaleSampler

        if robot not in self._prepared:
            self._prepared[robot] = robot_perception(robot, self.streams[robot], self.cfg)
            self._samplers[robot] = ScaleSampler(self._prepared[robot].perceive)
        sampler = self._samplers[robot]
        if sampler.wants(index):
            sampler.offer(index, self.streams[robot])

    def _start(self) -> None:
        """Every robot's front end, from its first frames, and the run (robots without frames left out)."""
        from shgm_slam.robot.build import make_frontend, robot_perception
        from shgm_slam.runner import FleetRun

        robots = {r: s for r, s in self.streams.items() if len(s)}
        if not robots:
            raise DataError(f"no frames were given to any of the cameras ({', '.join(self.streams)}); nothing to run")
        for r in self.streams.keys() - robots.keys():
            log.warning("%s: no frame was given; the run goes on without it", r)
            self._viz.log_text(f"{r}: no frame was given; the run goes on without it", "WARN")
        fronts = {}
        for r, stream in robots.items():
            prepared = self._prepared.get(r) or robot_perception(r, stream, self.cfg)
            fronts[r] = make_frontend(r, stream, self.cfg, max_segments=self._share, prepared=prepared,
                                      sampler=self._samplers.get(r))  # fmt: skip
        self._fleet = FleetRun(robots, self.cfg, self.out_dir, fronts, viz=self._viz,
                               gt_shared_frame=self.gt_shared_frame)  # fmt: skip

    def _run_held(self) -> list[LivePose]:
        held, self._held = self._held, []
        return [self._step(r, i) for r, i in held]

    def _step(self, robot: str, index: int) -> LivePose:
        from shgm_slam.interrupts import stops_deferred

        assert self._fleet is not None
        fleet = self._fleet
        with self._failing(), stops_deferred():  # a stop lands between frames, never inside a step
            skipped = len(fleet.skipped)
            res = fleet.step(robot, index)
        stream = self.streams[robot]
        stream.release(index)
        if res is None:
            return LivePose(robot, index, float(stream.timestamps_s[index]), np.full((4, 4), np.nan), None, False,
                            fleet.fronts[robot].segment.agent, fleet.skipped[skipped])  # fmt: skip
        return LivePose(robot, index, res.frame.timestamp_s, res.T_odom_cam.copy(), fleet.T_shared_cam(robot, res),
                        res.message is not None, res.agent)  # fmt: skip

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
