"""Robots' front ends in worker processes (``run --jobs``): the same results as one process, sooner.

A robot's front end (perception, pseudo-LiDAR, odometry, keyframes, semantic graph) never reads anything
back from the map server: corrections only move the robot's *fused* view. So the front ends can run
ahead in other processes while the orchestrator (``runner.run_slam``) still hands the map server every
frame in exactly the order of the one-process run (``data.interleave``). KISS-ICP's binding holds the
GIL, so threads would not help; processes do.

The robots are spread over ``jobs`` worker processes (``assign_workers``: by frames, longest first). A
worker builds its robots' front ends from the same fleet configuration (``runner.make_frontend``; the
orchestrator built them first, to refuse a bad run before anything is written, and the worker checks
that it resolved the same configuration), processes its robots' frames in the run's order and sends, per
frame, a ``FrameDelta``: the ``FrameResult`` and what changed in the front end's state. The orchestrator
keeps a ``FrontendMirror`` per robot - the state a ``RobotFrontend`` exposes (per-frame poses and
segments, keyframes, failures, counters), exactly as of the last frame it took - so everything
downstream (the robot node, the viewer, the evaluation) reads it as it reads a front end in its own
process. At most ``LOOKAHEAD_FRAMES`` frames of a worker wait for the orchestrator. A worker's log
records travel with its frames and are logged when the orchestrator reaches them.

A front end that fails on a bug, or a worker that dies (killed, out of memory), leaves its robots'
remaining frames skipped with the reason, said once in the log; the run finishes with everything the
map server has. A script that calls ``run_slam`` with worker processes needs the usual
``if __name__ == "__main__":`` guard (they are spawned, not forked).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import queue
import signal
import threading
import traceback
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection

import numpy as np

from shgm_slam.arrays import thinning_stride
from shgm_slam.config import ShgmConfig
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.odometry.health import OdometryFailure
from shgm_slam.odometry.sources import OdometryChoice
from shgm_slam.robot.frontend import FrameResult, RobotFrontend
from shgm_slam.types import Sequence

log = logging.getLogger(__name__)

LOOKAHEAD_FRAMES = 16
"""Frames a worker may run ahead of the orchestrator: enough to ride out a keyframe's matching in the map
server, few enough that a KITTI-size robot's waiting frames stay below ~100 MB."""
POLL_S = 1.0
"""The orchestrator checks that a worker it waits on is still alive this often."""


class FrontendLostError(DataError):
    """A robot's worker process is gone (died, or failed on an error): its remaining frames are skipped.

    ``repeat`` is False for the first frame it costs (log that one) and True after.
    """

    def __init__(self, message: str, repeat: bool) -> None:
        super().__init__(message)
        self.repeat = repeat


@dataclass
class SegmentState:
    """What the orchestrator reads of one trajectory segment (``robot.segments.TrajectorySegment``)."""

    index: int
    agent: str
    first_frame: int
    num_nodes: int = 0
    kf_frames: list[int] = field(default_factory=list)
    kf_poses: list[np.ndarray] = field(default_factory=list)
    end_failure: OdometryFailure | None = None

    @property
    def num_keyframes(self) -> int:
        return len(self.kf_frames)


@dataclass
class FrameDelta:
    """One processed frame and what it changed in its front end's state.

    ``rows_from``..``index`` (inclusive) are the rows of the per-frame arrays it may have changed (a
    divergence cuts its segment back to the failure's onset, a restarted segment may move its origin:
    ``RobotFrontend.first_changed_row``); ``segments`` the segments from the one current
    before the frame on, whose ``kf_frames`` / ``kf_poses`` hold only the keyframes this frame added (poses
    (4, 4), T_odom_kf in the segment's odometry frame); counters are totals, lists only what was appended.
    """

    index: int
    result: FrameResult
    rows_from: int
    T_odom_cam: np.ndarray  # (R, 4, 4) rows rows_from..index
    frame_kf: np.ndarray  # (R,)
    frame_segment: np.ndarray  # (R,)
    segments: list[SegmentState]  # kf_frames / kf_poses: only the keyframes added by this frame
    new_failures: list[OdometryFailure]
    new_depth_scales: list[float]
    # measured_frames, planar_turns, road_steps, image_steps, image_windows, references, levelled_references
    counters: tuple[int, int, int, int, int, int, int]


@dataclass
class _Marks:
    """Where a front end's append-only state stood before a frame."""

    segment: int
    kf_counts: list[int]
    failures: int
    depth_scales: int

    @classmethod
    def of(cls, front: RobotFrontend) -> _Marks:
        return cls(len(front.segments) - 1, [s.num_keyframes for s in front.segments], len(front.failures),
                   len(front.depth_scales))  # fmt: skip


def frame_delta(
    front: RobotFrontend, before: _Marks, res: FrameResult, index: int, *, viewer_points: int
) -> FrameDelta:
    """The ``FrameDelta`` of frame ``index`` that ``front`` just processed into ``res`` (``before``: its marks
    taken just before), carrying only the share of the frame's images and cloud that a viewer draws
    (``_viewer_share``)."""
    lo = min(index, front.first_changed_row)
    segs = []
    for s in front.segments[before.segment:]:
        n0 = before.kf_counts[s.index] if s.index < len(before.kf_counts) else 0
        segs.append(SegmentState(s.index, s.agent, s.first_frame, len(s.graph), list(s.kf_frames[n0:]),
                                 [p.copy() for p in s.kf_poses[n0:]], s.end_failure))  # fmt: skip
    rows = slice(lo, index + 1)
    return FrameDelta(
        index, _viewer_share(res, viewer_points), lo, front.T_odom_cam[rows].copy(), front.frame_kf[rows].copy(),
        front.frame_segment[rows].copy(), segs, list(front.failures[before.failures:]),
        list(front.depth_scales[before.depth_scales:]),
        (front.measured_frames, front.planar_turns, front.road_steps, front.image_steps, front.image_windows,
         front.references, front.levelled_references),
    )  # fmt: skip


def _viewer_share(res: FrameResult, viewer_points: int) -> FrameResult:
    """``res`` with only what crosses to the orchestrator: the image always (the still-camera check), and for
    the viewer (``viewer_points`` > 0, the most cloud points it draws) the labels of every frame, the depth
    and the cloud of keyframes only, the cloud thinned as the viewer thins it (``thinning_stride``): 0.7 MB
    a frame of the demo's UAV (640x192 pixels, a keyframe in three frames) against 1.7 MB in full.
    ``viewer_points`` 0: nothing for a viewer."""
    frame = replace(res.frame, depth_m=None, label_ids=None)  # the result's own ones are those drawn
    no_cloud = {"points_cam": np.zeros((0, 3), np.float32), "point_labels": None}
    if viewer_points < 1:
        return replace(res, frame=frame, depth_m=None, label_ids=None, **no_cloud)
    if res.message is None:
        return replace(res, frame=frame, depth_m=None, **no_cloud)
    step = thinning_stride(len(res.points_cam), viewer_points)
    labels = None if res.point_labels is None else res.point_labels[::step]
    return replace(res, frame=frame, points_cam=res.points_cam[::step], point_labels=labels)


class FrontendMirror:
    """A ``RobotFrontend``'s state as of the last ``FrameDelta`` applied: the attributes the orchestrator, the
    robot node, the viewer and the evaluation read (not its perception, odometry or graphs).

    Args:
        front: the orchestrator's own front end of this robot (validated, never stepped): its name, sequence,
            resolved configuration and odometry choice.
    """

    def __init__(self, front: RobotFrontend) -> None:
        self.name = front.name
        self.sequence: Sequence = front.sequence
        self.cfg: ShgmConfig = front.cfg
        self.depth_predicted: bool = front.depth_predicted
        self.odometry_choice: OdometryChoice | None = front.odometry_choice
        self.ground_scale_on: bool = front.ground_scale_on
        self.max_segments: int | None = front.max_segments
        self.settings_digest: str = front.settings_digest
        n = len(front.sequence)
        self.T_odom_cam = np.full((n, 4, 4), np.nan)
        self.frame_kf = np.full(n, -1, dtype=np.int64)
        self.frame_segment = np.full(n, -1, dtype=np.int64)
        self.segments: list[SegmentState] = [
            SegmentState(s.index, s.agent, s.first_frame, len(s.graph)) for s in front.segments
        ]
        self.failures: list[OdometryFailure] = []
        self.depth_scales: list[float] = []
        self.measured_frames = self.planar_turns = self.road_steps = self.image_steps = self.image_windows = 0
        self.references = self.levelled_references = 0

    @property
    def segment(self) -> SegmentState:
        """The current trajectory segment."""
        return self.segments[-1]

    @property
    def num_keyframes(self) -> int:
        """Keyframes over all segments."""
        return sum(s.num_keyframes for s in self.segments)

    @property
    def stopped(self) -> bool:
        """Its last allowed segment diverged (``RobotFrontend.stopped``)."""
        return self.segment.end_failure is not None

    def apply(self, d: FrameDelta) -> FrameResult:
        """Bring the mirror to the state after frame ``d.index``; returns that frame's result."""
        rows = slice(d.rows_from, d.index + 1)
        self.T_odom_cam[rows], self.frame_kf[rows], self.frame_segment[rows] = d.T_odom_cam, d.frame_kf, d.frame_segment
        for s in d.segments:
            if s.index == len(self.segments):
                self.segments.append(SegmentState(s.index, s.agent, s.first_frame))
            mine = self.segments[s.index]
            mine.first_frame, mine.num_nodes, mine.end_failure = s.first_frame, s.num_nodes, s.end_failure
            mine.kf_frames.extend(s.kf_frames)
            mine.kf_poses.extend(s.kf_poses)
        self.failures.extend(d.new_failures)
        self.depth_scales.extend(d.new_depth_scales)
        (self.measured_frames, self.planar_turns, self.road_steps, self.image_steps, self.image_windows,
         self.references, self.levelled_references) = d.counters
        return d.result


class _Sender:
    """The worker's end of its pipe: a thread sends what the front end puts, so the front end computes the
    next frame while the last one travels; at most ``LOOKAHEAD_FRAMES`` wait. ``put`` blocks when full."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self._items: queue.Queue = queue.Queue(maxsize=LOOKAHEAD_FRAMES)
        self._thread = threading.Thread(target=self._run, name="shgm-frontend-sender", daemon=True)
        self._thread.start()

    def put(self, item: tuple) -> None:
        self._items.put(item)

    def _run(self) -> None:
        while (item := self._items.get()) is not None:
            try:
                self._conn.send(item)
            except (BrokenPipeError, OSError):  # the orchestrator is gone or closed this robot: nothing to do
                return

    def close(self) -> None:
        """Send what is queued, then close the pipe."""
        self._items.put(None)
        self._thread.join()
        self._conn.close()


class _LogToPipe(logging.Handler):
    """A worker's log records go down its pipe, in order with its frames (``RemoteFrontend`` logs them)."""

    def __init__(self, sender: _Sender) -> None:
        super().__init__(logging.INFO)
        self._sender = sender

    def emit(self, record: logging.LogRecord) -> None:
        try:
            record.msg, record.args, record.exc_info, record.exc_text = record.getMessage(), None, None, None
            self._sender.put(("log", record))
        except Exception:  # a record that cannot be formatted: logging's own report, never the worker's end
            self.handleError(record)


def default_jobs(robots: int, jobs: int | None = None) -> int:
    """Worker processes for ``robots`` front ends: ``jobs`` where given, else one per robot up to the cores
    (1: everything in the orchestrator's process)."""
    return max(1, jobs if jobs is not None else min(robots, os.cpu_count() or 1))


def assign_workers(frames: dict[str, int], jobs: int) -> list[list[str]]:
    """Robots spread over at most ``jobs`` workers: the longest (most frames) first, each onto the worker with
    the fewest frames so far; workers listed in the order of their first robot, robots in the given order.

    Args:
        frames: robot name -> its frames, in the run's robot order.
        jobs: workers (>= 1).
    """
    loads: list[tuple[int, list[str]]] = [(0, []) for _ in range(max(1, min(jobs, len(frames))))]
    for name in sorted(frames, key=lambda r: -frames[r]):  # stable: equal lengths keep the run's order
        k = min(range(len(loads)), key=lambda i: loads[i][0])
        loads[k] = (loads[k][0] + frames[name], loads[k][1] + [name])
    order = list(frames)
    groups = [sorted(members, key=order.index) for _, members in loads if members]
    return sorted(groups, key=lambda g: order.index(g[0]))


def _work(members: list[tuple[str, Sequence, ShgmConfig]], cfg: ShgmConfig, schedule: list[tuple[str, int]],
          conn: Connection, viewer_points: int) -> None:  # fmt: skip
    """A worker process: build its robots' front ends, process ``schedule``'s frames in order, send each
    frame's delta.

    Args:
        members: (robot name, sequence, the configuration the orchestrator resolved for it, its
            ``max_segments``) of its robots.
        cfg: the fleet configuration (each front end is built from it, as the orchestrator did).
        schedule: (robot, frame index) in the order the orchestrator will take them.

    Messages down ``conn``: ``("frame", robot, FrameDelta)``, ``("skip", robot, index, reason)`` (a
    ``DataError``), ``("log", LogRecord)``, ``("error", robot, text)`` (anything else: that robot's front end
    stops; robot None: the whole worker stops), ``("end",)``.
    """
    for sig in WORKER_IGNORED_SIGNALS:  # a Ctrl-C or a hangup stops the orchestrator, which ends the workers
        signal.signal(sig, signal.SIG_IGN)
    sender = _Sender(conn)
    root = logging.getLogger()
    root.handlers[:] = [logging.NullHandler()]  # nothing to stderr while it builds the front ends again
    root.setLevel(logging.INFO)

    def failed(exc: Exception) -> str:
        return f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"

    try:
        from shgm_slam.robot.build import make_frontend

        fronts: dict[str, RobotFrontend] = {}
        for name, sequence, expect, max_segments in members:  # unlogged: the orchestrator logged building them
            try:
                fronts[name] = make_frontend(name, sequence, cfg, max_segments=max_segments)
            except Exception as exc:  # the orchestrator built it: reported, never expected
                sender.put(("error", name, failed(exc)))
                continue
            if fronts[name].cfg.model_dump_json() != expect.model_dump_json():
                del fronts[name]
                sender.put(("error", name, f"the worker resolved {name}'s configuration differently"))
        root.handlers[:] = [_LogToPipe(sender)]
        for name, index in schedule:
            front = fronts.get(name)
            if front is None:  # failed: the orchestrator skips its frames without asking
                continue
            before = _Marks.of(front)
            try:
                res = front.process(index)
            except DataError as exc:
                sender.put(("skip", name, index, str(exc)))
                continue
            except Exception as exc:  # a bug in one front end: reported; the worker's other robots go on
                sender.put(("error", name, failed(exc)))
                del fronts[name]
                continue
            sender.put(("frame", name, frame_delta(front, before, res, index, viewer_points=viewer_points)))
        sender.put(("end",))
    except Exception as exc:  # reported to the orchestrator, which skips the rest of the worker's robots
        sender.put(("error", None, failed(exc)))
    finally:
        sender.close()


WORKER_IGNORED_SIGNALS = tuple(s for s in (signal.SIGINT, getattr(signal, "SIGHUP", None)) if s is not None)
"""Signals a worker ignores: a terminal sends them to the whole process group (Ctrl-C; a hangup when it closes),
and the orchestrator, which takes them as a stop, ends its workers itself. (SIGTERM is left as it is: it is how
workers are ended, also by ``multiprocessing`` at exit.)"""


def _start_without_sigint(proc: multiprocessing.process.BaseProcess) -> None:
    """Start ``proc`` ignoring SIGINT (and SIGHUP: ``WORKER_IGNORED_SIGNALS``) from its first instruction
    (``_work`` keeps them so).

    A terminal's Ctrl-C goes to the whole process group: a worker still importing its modules died of it with a
    traceback, and the run reported its robots' front ends as failed (a hangup, the terminal closed, killed
    running workers the same way: "its worker process died (exit code -1)", its frames counted as skipped). An
    ignored signal stays ignored through fork and exec (a blocked mask does not survive multiprocessing's spawn),
    so they are ignored here while the process starts; they are also blocked meanwhile, so that a Ctrl-C in that
    moment stays pending and reaches this process once its handler is back. Off the main thread (no handler can be
    set there) it just starts."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        proc.start()
        return
    previous_mask = signal.pthread_sigmask(signal.SIG_BLOCK, set(WORKER_IGNORED_SIGNALS))
    try:
        previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in WORKER_IGNORED_SIGNALS}
        try:
            proc.start()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous_mask)


class _Worker:
    """The orchestrator's end of one worker process and its pipe (``_work``)."""

    def __init__(self, fronts: list[RobotFrontend], fleet_cfg: ShgmConfig, schedule: list[tuple[str, int]],
                 *, viewer_points: int) -> None:  # fmt: skip
        self.names = [f.name for f in fronts]
        self.dead: str | None = None  # why the whole worker is gone
        ctx = multiprocessing.get_context("spawn")  # never fork a process that holds ONNX or TBB threads
        self._conn, child = ctx.Pipe(duplex=False)
        members = [(f.name, f.sequence, f.cfg, f.max_segments) for f in fronts]
        self._proc = ctx.Process(target=_work, name=f"shgm-frontend-{'+'.join(self.names)}",
                                 args=(members, fleet_cfg, schedule, child, viewer_points), daemon=True)  # fmt: skip
        try:
            _start_without_sigint(self._proc)  # spawn: the sequences and the configuration are pickled here
        except (pickle.PicklingError, TypeError, AttributeError) as exc:
            self._conn.close()
            child.close()
            raise ConfigError(f"robot(s) {', '.join(self.names)}: cannot be handed to a worker process ({exc}); "
                              "run them in one process (--jobs 1)") from exc  # fmt: skip
        child.close()  # the worker holds the only sending end: a worker that dies mid-message ends in EOF here

    def take(self, name: str, index: int) -> tuple:
        """The worker's message about robot ``name``'s frame ``index``: ``("frame", name, delta)``,
        ``("skip", name, index, reason)`` or ``("error", name or None, text)``; log records on the way are
        logged. Anything out of order ends the worker."""
        if self.dead is None:
            msg = self._next()
            if msg[0] == "error" and (msg[1] is None or msg[1] == name):
                if msg[1] is None:
                    self._die(msg[2])
                return msg
            due = msg[0] in ("frame", "skip") and msg[1] == name
            if due and (msg[2].index if msg[0] == "frame" else msg[2]) == index:
                return msg
            self._die(f"it ended before {name}'s frame {index}" if msg[0] == "end"
                      else f"it sent {msg[0]} for {msg[1]} where {name}'s frame {index} was due")  # fmt: skip
        return ("error", None, self.dead)

    def _next(self) -> tuple:
        while True:
            try:
                if not self._conn.poll(POLL_S):
                    if self._proc.is_alive():
                        continue
                    if not self._conn.poll(0):  # it may have sent its last words just before it ended
                        raise EOFError
                msg = self._conn.recv()
            except (EOFError, OSError):
                self._proc.join(timeout=POLL_S)
                code = self._proc.exitcode
                return ("error", None, f"its worker process died (exit code {code}"
                                       f"{'; killed: out of memory?' if code == -signal.SIGKILL else ''})")  # fmt: skip
            if msg[0] != "log":
                return msg
            record = msg[1]
            logger = logging.getLogger(record.name)
            if logger.isEnabledFor(record.levelno):
                logger.handle(record)

    def _die(self, reason: str) -> None:
        self.dead = reason
        self.close()

    def close(self) -> None:
        """End the worker (it may still be running ahead) and close its pipe."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=10)
        self._conn.close()


class RemoteFrontend:
    """A robot's front end running in a worker process; ``process`` takes its frames in order.

    Duck-types ``RobotFrontend`` for the orchestrator through its ``mirror`` (attribute access falls
    through to it). The worker's log records are logged here when the frames around them are taken.

    Args:
        front: the orchestrator's validated front end of this robot (not stepped).
        worker: the worker process that runs it.
    """

    def __init__(self, front: RobotFrontend, worker: _Worker) -> None:
        self.mirror = FrontendMirror(front)
        self._worker = worker
        self._lost: str | None = None

    def __getattr__(self, attr: str):
        if attr == "mirror":  # not set yet (a failed __init__)
            raise AttributeError(attr)
        return getattr(self.mirror, attr)

    def process(self, index: int) -> FrameResult:
        """Frame ``index``'s result from the worker (it must be the robot's next frame the worker was given).

        Raises:
            DataError: the frame could not be used (the worker skipped it).
            FrontendLostError: the front end or its worker is gone; every later frame raises it too.
        """
        name = self.mirror.name
        if self._lost is not None:
            raise FrontendLostError(self._lost, repeat=True)
        msg = self._worker.take(name, index)
        if msg[0] == "frame":
            return self.mirror.apply(msg[2])
        if msg[0] == "skip":
            raise DataError(msg[3])
        first, _, detail = msg[2].partition("\n")
        log.error("%s: its front end failed in its worker process: %s%s", name, first,
                  f"\n{detail}" if detail else "")  # fmt: skip
        self._lost = f"{name}: its front end failed in its worker process ({first}); its remaining frames are skipped"
        raise FrontendLostError(self._lost, repeat=False)


class ParallelFrontends:
    """The robots' front ends in ``jobs`` worker processes (``assign_workers``); a context manager that ends
    every worker on exit.

    Args:
        fronts: the orchestrator's validated front ends (robot name -> front end; not stepped; released:
            their models are freed, and they cannot process frames any more).
        fleet_cfg: the fleet configuration they were built from.
        schedule: (robot, frame index) in the order the orchestrator will take them (``data.interleave``).
        jobs: worker processes (at most one per robot).
        viewer_points: the most cloud points the run's viewer draws of a frame (``Viz.max_cloud_points``; 0:
            no viewer): each frame's result carries only what it draws.
    """

    def __init__(self, fronts: dict[str, RobotFrontend], fleet_cfg: ShgmConfig, schedule: list[tuple[str, int]],
                 jobs: int, *, viewer_points: int) -> None:  # fmt: skip
        self.workers: list[_Worker] = []
        self.fronts: dict[str, RemoteFrontend] = {}
        try:
            for group in assign_workers({r: len(f.sequence) for r, f in fronts.items()}, jobs):
                mine = [(r, i) for r, i in schedule if r in group]
                worker = _Worker([fronts[r] for r in group], fleet_cfg, mine, viewer_points=viewer_points)
                self.workers.append(worker)
                for r in group:
                    self.fronts[r] = RemoteFrontend(fronts[r], worker)
        except BaseException:
            self.__exit__()
            raise
        self.fronts = {r: self.fronts[r] for r in fronts}  # the run's robot order
        for f in fronts.values():  # the workers built their own: this process's models are not used again
            f.release()

    def __enter__(self) -> dict[str, RemoteFrontend]:
        return self.fronts

    def __exit__(self, *exc) -> None:
        for w in self.workers:
            w.close()
