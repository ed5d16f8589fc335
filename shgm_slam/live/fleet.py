"""``LiveRun``: the whole system in one process, stepped by frames as cameras deliver them (``shgm_slam.live``)."""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.api import viewer_mode
from shgm_slam.config import ShgmConfig
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.live.frames import LivePose, Warmup, live_config, pose_of
from shgm_slam.scene_scale import SAMPLE_SPAN_FRAMES
from shgm_slam.types import DepthOrigin, Intrinsics

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run starts
    from shgm_slam.run_report import RunSummary
    from shgm_slam.runner import FleetRun
    from shgm_slam.viz.rerun_logger import RerunMode

log = logging.getLogger(__name__)

START_WAIT_FRAMES = 2 * SAMPLE_SPAN_FRAMES
"""Frames a warm robot holds, at most, while the run waits to start: for a first camera that has sent no frame, or
for a robot that has sent some and is not warm yet (a camera unplugged after its first frames) (200: 20 s at 10 fps).
The run then starts with the robots that are warm (the first camera stays the shared frame's when it is warm, else
the first of them, in the cameras' order, takes it); the others join once their first frames are in, as a camera
that starts late does. Held frames are whole images and depth maps, so waiting without a bound ran out of memory
where a camera was unplugged (four cameras at 10 fps held 36,000 frames an hour each). Twice the most frames a
warm-up reads (``scene_scale.SAMPLE_SPAN_FRAMES``): cameras at one frame rate never reach it before they are warm,
and a first camera that starts sending before it keeps the run as it was."""


class LiveRun:
    """The multi-robot system on frames that arrive one by one (the ``shgm_slam.live`` package docstring).

    Args:
        cameras: robot name -> its camera's ``Intrinsics``, in order (the first robot's first camera frame is the
            shared frame); more can be added while the run goes (``add_camera``).
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
        from shgm_slam.io.export import make_results_dir, release_results_dir
        from shgm_slam.runner import check_fleet
        from shgm_slam.transport.keys import validate_robot_name
        from shgm_slam.viz.rerun_logger import make_viz

        if not isinstance(cameras, Mapping) or not cameras:
            raise ConfigError("no cameras given: pass {robot name: Intrinsics}, e.g. {'car1': Intrinsics(...)}")
        for name in cameras:
            validate_robot_name(name)
        self.cfg = cfg = live_config(config, list(cameras))
        self._share = check_fleet(list(cameras), cfg, "fix the names under 'robots:', or name such a camera when "
                                  "making the LiveRun (one that never sends a frame is left out) instead of adding "
                                  "it later")  # fmt: skip
        origins = depth_origin if isinstance(depth_origin, Mapping) else dict.fromkeys(cameras, depth_origin)
        if set(origins) != set(cameras):
            raise ConfigError(f"depth_origin names robots {sorted(origins)}; give one for each of {list(cameras)}")
        self.streams = {r: FrameStream(K, depth_origin=origins[r], name=r) for r, K in cameras.items()}
        mode = viewer_mode(viewer, viewer_url)
        self.gt_shared_frame = gt_shared_frame
        self.out_dir = make_results_dir(None if out is None else Path(out), overwrite=overwrite)
        try:
            self._viz = make_viz(mode, robots=list(cameras), save_path=self.out_dir / "run.rrd",
                                 connect_url=viewer_url, max_cloud_points=8000)  # fmt: skip
        except BaseException:  # refused (no display to spawn a viewer on, ...): the folder is free for the next try
            release_results_dir(self.out_dir)
            raise
        self._warmups = {r: Warmup(r, stream, cfg) for r, stream in self.streams.items()}
        self._predicted = [r for r in cameras if self._is_predicted(r, origins[r])]
        self._held: list[tuple[str, int]] = []  # frames of robots that do not run yet, in the order they came
        self._said_waiting = False  # the warning that the run waits for the first camera was given
        self._fleet: FleetRun | None = None
        self._summary: RunSummary | None = None
        self._closed = False  # finished, or ended by an error: no more frames
        self._lock = threading.RLock()  # cameras' threads may call at once: one frame at a time

    # --- feeding -------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """The run has started (the first robot's first frames and those of every robot that had sent any were in;
        or a warm robot held ``START_WAIT_FRAMES`` while the run waited for the others)."""
        return self._fleet is not None

    @property
    def warming(self) -> tuple[str, ...]:
        """The robots whose first frames are still too few to set their settings (their frames are held)."""
        return tuple(r for r, w in self._warmups.items() if not w.ready)

    def trajectory(self, robot: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The run's current estimate of every frame ``robot`` has run, in the shared frame: what the results
        folder's fused trajectory would say now. Earlier frames move as later closures correct the estimate
        (``LivePose.T_shared_cam`` is the estimate at the frame's own call); after ``finish``, the final one.

        Returns:
            ``(timestamps_s (N,), T_shared_cam (N, 4, 4))`` with NaN rows for frames of trajectory segments not
            placed (or in none), or None while the robot does not run yet or none of its segments is placed.

        Raises:
            ConfigError: ``robot`` is not one of the run's cameras.
        """
        from shgm_slam.run_report import fused_poses

        with self._lock:
            if robot not in self.streams:
                raise ConfigError(f"no camera {robot!r} in this run; its cameras are {', '.join(self.streams)}")
            fleet = self._fleet
            if fleet is None or robot not in fleet.fronts:
                return None
            T_shared_cam = fused_poses(fleet.fronts[robot], fleet.server)
            if T_shared_cam is None:
                return None
            return self.streams[robot].timestamps_s[: len(T_shared_cam)].copy(), T_shared_cam

    def add_camera(
        self, robot: str, intrinsics: Intrinsics, *, depth_origin: DepthOrigin = DepthOrigin.MEASURED
    ) -> None:
        """A camera that was not named when the run was made. Before the run starts it is one more robot the start
        waits for once it sends frames; after, its robot joins the running system once its first frames have set
        its settings, as a camera named at the start that sends late. Give its frames with ``add_frame``. (A camera
        with settings of its own under the configuration's ``robots:`` is named when the run is made.)

        Args:
            robot: its robot's name (not one of the run's cameras).
            intrinsics: its camera.
            depth_origin: whether the depth you will give is measured or predicted (``LiveRun``). A camera with
                predicted depth that joins a run which started with measured depth alone leaves the pose graph's
                odometry drift rates those of measured depth (a warning; set ``backend.odometry_drift_*`` in the
                configuration, or name the camera when making the run).

        Raises:
            ConfigError: an invalid name or one the run has (or one that differs from it only in case), the run
                has finished, a fleet the pose graph cannot hold (with the segments its robots have started).
                DataError: intrinsics that are not valid.
        """
        from shgm_slam.runner import check_fleet
        from shgm_slam.transport.keys import validate_robot_name

        with self._lock:
            self._check_open()
            validate_robot_name(robot)
            if robot in self.streams:
                raise ConfigError(f"camera {robot!r} is in this run already; give every camera its own name")
            share = check_fleet([*self.streams, robot], self.cfg)
            self._check_room(robot)
            stream = FrameStream(intrinsics, depth_origin=depth_origin, name=robot)
            self._share = share  # the newcomer's share of the pose graph (the map server tells the others theirs)
            self.streams[robot] = stream
            if self._fleet is not None:  # the running robots start no more segments than the newcomer leaves them
                self._fleet.server_node.expect_robots(len(self.streams))
                for node in self._fleet.nodes.values():
                    node.poll()
            self._warmups[robot] = Warmup(robot, stream, self.cfg)
            if self._is_predicted(robot, depth_origin):
                if self._fleet is not None and not self._predicted:
                    log.warning("%s: its depth is predicted, but the run started with measured depth alone: the "
                                "pose graph keeps measured depth's odometry drift rates (set "
                                "backend.odometry_drift_rot_rad_per_m and _trans_per_m in the configuration, or "
                                "name the camera when making the run)", robot)  # fmt: skip
                self._predicted.append(robot)
            log.info("%s: camera added to the live run", robot)

    def _check_room(self, robot: str) -> None:
        """Refuse (ConfigError) camera ``robot`` when the pose graph has no agent left for it: the running robots'
        trajectory segments (a robot alone may have started up to all ``MAX_AGENTS`` after odometry failures) and
        one for each camera that has not joined yet, this one included. (The map server refused such a robot's
        first keyframe, which ended the whole run.)"""
        from shgm_slam.backend.keys import MAX_AGENTS

        fronts = {} if self._fleet is None else self._fleet.fronts
        in_use = {r: len(front.segments) for r, front in fronts.items()}
        waiting = [r for r in self.streams if r not in fronts]
        if sum(in_use.values()) + len(waiting) + 1 > MAX_AGENTS:
            used = ", ".join(f"{r}: {n}" for r, n in in_use.items())
            raise ConfigError(f"camera {robot!r} cannot be added: the pose graph holds at most {MAX_AGENTS} agents "
                              f"(robots and their trajectory segments after odometry failures), and the running "
                              f"robots have started {sum(in_use.values())} ({used}) with {len(waiting)} more "
                              "camera(s) still to join; name every camera when making the LiveRun (each then gets "
                              "its share of the pose graph), or fix the odometry that keeps failing")  # fmt: skip

    def _is_predicted(self, robot: str, depth_origin: DepthOrigin) -> bool:
        """Whether ``robot``'s depth is predicted: a depth model configured for it, or depth given as predicted."""
        return self.cfg.for_robot(robot).perception.depth_model is not None or (
            DepthOrigin(depth_origin) is DepthOrigin.PREDICTED
        )

    def add_frame(
        self,
        robot: str,
        image_rgb: np.ndarray,
        timestamp_s: float,
        *,
        depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
        T_world_cam: np.ndarray | None = None,
        T_odom_cam: np.ndarray | None = None,
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
            T_odom_cam: (4, 4) the robot's own odometry's pose (camera -> its odometry frame, metres; every frame
                or none), which the robot then runs as its odometry (``OdometryKind.GIVEN``), or None.

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
                                  T_world_cam=T_world_cam, T_odom_cam=T_odom_cam)  # fmt: skip
            running = self._fleet is not None and robot in self._fleet.fronts
            if running and all(r != robot for r, _ in self._held):
                return [self._step(robot, index)]
            self._held.append((robot, index))  # (a running robot's: behind frames a Ctrl-C left held)
            with self._failing():
                if not running:
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
            try:
                self._summary = self._fleet.finish()
            except KeyboardInterrupt as stop:  # stopped while the results were written: a checkpoint, marked
                self._mark_failed(stop)
                raise
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
        elif self._fleet is None or self._fleet.finished:
            self._mark_failed(exc)
        elif not issubclass(kind, Exception):  # a Ctrl-C, sys.exit (a SIGTERM handler's), a generator closed
            from shgm_slam.interrupts import stops_deferred

            with self._lock, stops_deferred(), self._failing():  # stopped between frames: what there is, written
                self._summary = self._fleet.finish(interrupted=True)  # (no final matching; an error marks it)
                self._release()
        else:  # your code's error (the run is sound): every keyframe so far into the checkpoint, then marked
            with self._lock:
                try:
                    self._write_checkpoint()
                finally:
                    self._mark_failed(exc)

    # --- inside ----------------------------------------------------------------------------------

    def _write_checkpoint(self) -> None:
        """The running map server's results so far into the folder (as its periodic checkpoints are written): an
        error in the caller's code would otherwise lose the keyframes since the last one, which cannot be fed
        again (frames are dropped once run). A folder that cannot be written keeps its last checkpoint."""
        from shgm_slam.interrupts import stops_deferred

        assert self._fleet is not None
        try:
            with stops_deferred():
                self._fleet.server_node.write_results()
        except DataError as exc:
            log.warning("%s: cannot write the results so far: %s", self.out_dir, exc)

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
            start = self._start(sent, final)
            if start is None:
                return []
            order, first = start
            robots = {r: self.streams[r] for r in order}
            fronts = {r: self._warmups[r].frontend(self._share) for r in first}
            self._fleet = FleetRun(robots, self.cfg, self.out_dir, fronts, viz=self._viz,
                                   gt_shared_frame=self.gt_shared_frame, predicted=self._predicted)  # fmt: skip
        fleet = self._fleet
        for r in sent:
            if r not in fleet.fronts and (final or self._warmups[r].ready):
                newcomer = None if r in fleet.robots else self.streams[r]  # (a camera added after the start)
                fleet.add_robot(r, self._warmups[r].frontend(self._share), newcomer)
                log.info("%s: joined the running system (its first frames set its settings)", r)
        now = [(r, i) for r, i in self._held if r in fleet.fronts]
        return [self._step(r, i, held=True) for r, i in now]

    def _start(self, sent: list[str], final: bool) -> tuple[list[str], list[str]] | None:
        """Whether the run starts now, with which robots: ``(the fleet's robots in order, those among them that run
        from the start)`` (the first of both is the shared frame's robot), or None while it waits (a warning, once,
        when it waits for a first camera that has sent nothing).

        It starts once the first camera and every robot in ``sent`` (those that have sent frames) are warm; at
        ``finish`` (``final``) with the robots in ``sent`` (a first camera that sent no frame leaves the shared frame
        to the next); before that, once a warm robot holds ``START_WAIT_FRAMES``, with the warm robots (the first
        camera, if it has sent nothing or is not warm, and those still warming join later)."""
        reference = next(iter(self.streams))
        ready = [r for r in sent if self._warmups[r].ready]
        if final:
            return sent, sent
        if reference in sent and ready == sent:
            return list(self.streams), sent
        held = Counter(r for r, _ in self._held)
        longest = max(ready, key=lambda r: held[r], default=None)
        if longest is not None and held[longest] >= START_WAIT_FRAMES:
            waiting = [r for r in self.streams if r not in ready]
            said = [f"{r} has sent no frame" if r not in sent else
                    f"{r} has sent {len(self.streams[r])} frames and is not warm (its first frames stopped?)"
                    for r in waiting if r in sent or r == reference]  # fmt: skip
            why = (f"{'; '.join(said)}, while {longest} holds {held[longest]} frames (live.fleet.START_WAIT_FRAMES): "
                   f"the run starts with {', '.join(ready)}, and {ready[0]}'s first camera frame is the shared frame; "
                   "the others join once their first frames are in, as cameras that start late (check their cameras"
                   + (f"; to keep {reference} the shared frame, start its camera before the others)" if ready[0] !=
                      reference else ")"))  # fmt: skip
            log.warning(why)
            self._viz.log_text(why, "WARN")
            return ready + waiting, ready
        if ready == sent and not self._said_waiting:
            self._said_waiting = True  # (once: every later frame is held the same way)
            why = (f"{', '.join(sent)} ready, but the run starts with the first camera, {reference} (the shared "
                   f"frame), which has sent no frame: their frames are held ({len(self._held)} so far) until it "
                   f"does, until one of them holds {START_WAIT_FRAMES} (the run then starts without it), or "
                   "until finish() starts the run without it")  # fmt: skip
            log.warning(why)
            self._viz.log_text(why, "WARN")
        return None

    def _step(self, robot: str, index: int, *, held: bool = False) -> LivePose:
        """Run frame ``index`` of ``robot`` (``held``: one of ``_held``, which it leaves as it runs: a Ctrl-C
        between held frames leaves the rest held, to run in order at the robot's next frame or ``finish``)."""
        from shgm_slam.interrupts import stops_deferred

        assert self._fleet is not None
        fleet, stream = self._fleet, self.streams[robot]
        with self._failing(), stops_deferred():  # a stop lands between frames, never inside a step
            if held:
                self._held.remove((robot, index))
            skipped = len(fleet.skipped)
            res = fleet.step(robot, index)
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
        """The run ends without its results: ``incomplete.txt`` says why (the error ``exc``, or a stop before the
        run started or while its results were written), and the folder is released."""
        from shgm_slam.io.export import ResultsWriter

        if self._closed:
            return
        if self.out_dir.is_dir() and isinstance(exc, Exception):
            ResultsWriter(self.out_dir).mark_failed(exc)
        elif self.out_dir.is_dir() and (self._fleet is None or self._fleet.finished):
            # stopped before every robot's first frames came, or while the results were written (no metrics.json)
            why = "before every robot had sent its first frames" if self._fleet is None else (
                "while its results were being written")  # fmt: skip
            with contextlib.suppress(DataError):
                ResultsWriter(self.out_dir).mark_incomplete(f"stopped {why}")
        self._release()

    def _release(self) -> None:
        """The run is over: the results folder's lock released, the viewer's stream closed."""
        from shgm_slam.io.export import release_results_dir

        self._closed = True
        release_results_dir(self.out_dir)
        if self._fleet is None or not self._fleet.finished:  # (a finished run closed it)
            self._viz.close()
