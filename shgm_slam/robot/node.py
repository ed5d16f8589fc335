"""A robot as a node: its front end, the keyframes it sends, the corrections it applies.

Used by ``shgm-slam robot`` over Eclipse Zenoh and by ``shgm-slam run`` over the in-process bus (one
code path). The node

- says hello (with a random session id) when it starts and every ``HEARTBEAT_S`` after: the server
  uses it to tell a restart from a name clash and a silent robot from a live one;
- sends one ``KeyframeMessage`` per keyframe and keeps it until the server acknowledges it
  (``CorrectionMessage.received``); what stays unacknowledged for ``resend_after_s`` is sent again,
  so lost messages, a restarted robot (the server tells it what it already has) and a restarted
  server (it sees a new server session and says hello again) all end with nothing lost;
- applies the corrections it receives (only what moved since the last one, ``shgm_slam.corrections``; a
  full one when it (re)connects, or when it missed one and asks with ``resync``) to its own frames
  (``fused``);
- after its last frame sends a ``DoneMessage`` with its per-frame odometry, re-sends it until the
  server's status says the robot is done (a done sent while the server still held a restarted robot's
  hello back is ignored, so it must come again), and waits (bounded) until the server holds every keyframe;
- says (a log warning) when no map server has answered for ``SERVER_SILENT_S``, when the one it had goes silent
  and when it finishes without all of this robot's keyframes, and goes on keeping them for a server that resumes.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.corrections import FusedView
from shgm_slam.errors import ProtocolError, ShgmError
from shgm_slam.fusion import fuse_segments
from shgm_slam.messages import (
    CorrectionMessage,
    DoneMessage,
    HelloMessage,
    RobotState,
    RobotTrajectory,
    StatusMessage,
)
from shgm_slam.robot.frontend import FrameResult, RobotFrontend
from shgm_slam.scene_scale import effective_fields
from shgm_slam.transport.base import Inbox, Transport
from shgm_slam.transport.keys import STATUS_KEY, correction_key, done_key, hello_key, keyframe_key
from shgm_slam.wire import decode, encode

log = logging.getLogger(__name__)

HEARTBEAT_S = 0.5
"""A robot says hello this often (its heartbeat)."""

SERVER_SILENT_S = 10.0
"""A robot that has heard no map server for this long (none has answered since it started, or the one it had went
silent) says so, once until it hears one again; it goes on and keeps what the server has not acknowledged."""

DONE_RESEND_MAX_S = 30.0
"""Until the server's status says it holds a robot's done, the robot re-sends it after ``resend_after_s``,
then twice as long each time, at most this long apart."""


class RobotNode:
    """One robot's front end behind a transport (see the module docstring).

    Args:
        frontend: the robot's front end (its name is the robot's name).
        transport: where keyframes go and corrections come from.
        session: this process's session id (random when None).
        resend_after_s: re-send keyframes the server has not acknowledged after this long.
        clock: monotonic seconds (tests pass a fake).
    """

    def __init__(
        self,
        frontend: RobotFrontend,
        transport: Transport,
        *,
        session: str | None = None,
        resend_after_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.front = frontend
        self.name = frontend.name
        self.transport = transport
        self.session = session or uuid.uuid4().hex[:16]
        self.resend_after_s = resend_after_s
        self.clock = clock
        ts = frontend.sequence.timestamps_s
        self._start_s = float(ts[0]) if len(ts) else 0.0
        self._progress_s: float | None = None  # seconds since its first frame of the last frame processed
        self._kf_times_s: dict[str, list[float]] = {}  # agent -> its keyframes' seconds since the first frame
        self._server_answered = False  # a correction of the current server session has arrived
        self._inbox = Inbox()
        transport.subscribe(correction_key(self.name), self._inbox)
        transport.subscribe(STATUS_KEY, self._inbox)
        # agent -> every encoded keyframe, kept for re-sending (a server restarted on an empty folder can
        # be given everything again; ~2-5 KB per keyframe)
        self._payloads: dict[str, list[bytes]] = {}
        self._acked: dict[str, int] = {}
        self._last_progress_s: dict[str, float] = {}
        self._view = FusedView()
        self._resync = False  # a correction was missed: ask for a full one with every hello until it comes
        self._last_hello_s = -np.inf
        self._done: bytes | None = None
        self._done_sent_s = -np.inf
        self._done_every_s = resend_after_s  # doubles with every re-send (a done carries every frame's pose)
        self._done_held = False  # the server's latest status says it holds the done (this robot is DONE)
        self.server_session: str | None = None
        self.server_finished = False
        self._server_heard_s = self.clock()  # when the map server last spoke (from the start: none yet)
        self._silence_said = False  # its silence was said (``_check_server_silence``) and it has not spoken since
        self._unfinished_said: str | None = None  # the server session said to have finished without this robot
        self.provisional_agents: tuple[str, ...] = ()  # its agents the server placed provisionally (status)
        self.waiting_agents: tuple[str, ...] = ()  # its unplaced agents with too few independent matches (status)
        self.bytes_sent: dict[str, int] = {"hello": 0, "keyframe": 0, "done": 0}
        self.bytes_received: dict[str, int] = {"correction": 0, "status": 0}
        self.keyframes_sent = 0
        self.resent = 0
        self.resent_done = 0

    # --- sending -------------------------------------------------------------------------------

    def hello(self) -> None:
        """Say hello (also the heartbeat)."""
        self._last_hello_s = self.clock()
        self._publish("hello", hello_key(self.name), encode(self._hello_message()))

    def heartbeat(self) -> None:
        """Say hello when the last one is ``HEARTBEAT_S`` old."""
        if self.clock() - self._last_hello_s >= HEARTBEAT_S:
            self.hello()

    def _hello_message(self) -> HelloMessage:
        return HelloMessage(self.name, self.session, len(self.front.sequence), self._resync, self._start_s,
                            self.progress_s(), self.server_session or "", self.front.settings_digest)  # fmt: skip

    def progress_s(self) -> float | None:
        """How far the server holds this robot's keyframes, in seconds since its first frame: the last frame
        processed, or just before the first keyframe the server has not acknowledged; None before the
        first frame and until the current server has answered (after a server restart the old
        acknowledgements may overstate what the new one holds)."""
        if self._progress_s is None or not self._server_answered:
            return None
        p = self._progress_s
        for agent, times in self._kf_times_s.items():
            n = self._acked.get(agent, 0)
            if n < len(times):
                if times[n] <= 0.0:
                    return None
                p = min(p, float(np.nextafter(times[n], -np.inf)))
        return p

    def step(self, index: int) -> FrameResult:
        """Run frame ``index`` through the front end and send its keyframe, if it made one.

        Raises:
            DataError: the frame cannot be used (the caller logs and skips it).
        """
        self.heartbeat()
        try:
            res = self.front.process(index)
        finally:  # a skipped frame is passed too
            t = float(self.front.sequence.timestamps_s[index]) - self._start_s
            self._progress_s = max(t, self._progress_s or 0.0)
        if res.message is not None:
            msg = replace(res.message, session=self.session)
            payload = encode(msg)
            sent = self._payloads.setdefault(msg.robot, [])
            sent.append(payload)
            self._kf_times_s.setdefault(msg.robot, []).append(msg.timestamp_s - self._start_s)
            self._last_progress_s.setdefault(msg.robot, self.clock())
            self.keyframes_sent += 1
            if msg.kf_index >= self._acked.get(msg.robot, 0):
                self._publish("keyframe", keyframe_key(self.name), payload)
        return res

    def done(self) -> None:
        """Tell the server the last keyframe has been sent, with the per-frame odometry."""
        f = self.front
        traj = RobotTrajectory(np.asarray(f.sequence.timestamps_s, dtype=np.float64), f.frame_segment.copy(),
                               f.T_odom_cam.copy())  # fmt: skip
        counts = {s.agent: s.num_keyframes for s in f.segments if s.num_keyframes}
        self._done = encode(DoneMessage(self.name, self.session, counts, traj, effective_fields(f.cfg)))
        self._send_done()

    def _send_done(self) -> None:
        assert self._done is not None
        self._done_sent_s = self.clock()
        self._publish("done", done_key(self.name), self._done)

    def _publish(self, kind: str, key: str, payload: bytes) -> None:
        self.bytes_sent[kind] += len(payload)
        self.transport.publish(key, payload)

    # --- receiving -----------------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.0) -> None:
        """Apply every queued correction and status; re-send what the server is missing.

        Raises:
            ProtocolError: the server refused this robot (its name is taken by a live process).
        """
        items = self._inbox.drain()
        if not items and timeout_s > 0:
            first = self._inbox.get(timeout_s)
            items = [first, *self._inbox.drain()] if first is not None else []
        for key, payload in items:
            try:
                msg = decode(payload)
            except ShgmError as exc:
                log.warning("%s: unreadable message on %s refused: %s", self.name, key, exc)
                continue
            if isinstance(msg, CorrectionMessage) and msg.robot == self.name:
                self.bytes_received["correction"] += len(payload)
                self._correction(msg)
            elif isinstance(msg, StatusMessage):
                self.bytes_received["status"] += len(payload)
                self._status(msg)
        self._check_server_silence()
        self._resend_stalled()

    def _correction(self, msg: CorrectionMessage) -> None:
        if msg.session not in ("", self.session):
            return
        self._server_heard_s = self.clock()  # (said to be back, if it was silent, with its next status)
        self._server_answered = True
        now = self.clock()
        for agent, n in msg.received.items():
            if agent_robot(agent)[0] != self.name:
                continue
            if n > self._acked.get(agent, 0):
                self._last_progress_s[agent] = now
            if n < self._acked.get(agent, 0):  # the server lost some (e.g. restarted without its journal)
                self._last_progress_s[agent] = -np.inf
            self._acked[agent] = n
        if self._view.apply(msg):
            self._resync = self._resync and not msg.full
        elif not self._resync:
            log.info("%s: correction %d does not follow %d (one was lost); asking for a full one", self.name,
                     msg.seq, self._view.seq)  # fmt: skip
            self._resync = True
            self.hello()

    def _status(self, msg: StatusMessage) -> None:
        refusal = msg.refused.get(self.name)
        if refusal is not None and refusal.startswith(self.session + ":"):
            raise ProtocolError(f"the map server refused robot {self.name!r}: {refusal.partition(':')[2].strip()}")
        self._server_spoke(msg.server_session)
        if msg.server_session != self.server_session:
            if self.server_session is not None:
                log.warning("%s: the map server restarted; resuming with it", self.name)
            self.server_session = msg.server_session
            self._server_answered = False
            self.hello()  # the (new) server answers with what it holds; missing keyframes follow
            for agent in self._payloads:
                self._last_progress_s[agent] = -np.inf
            if self._done is not None:
                self._send_done()
        self.server_finished = msg.finished
        mine = msg.robots.get(self.name)
        self._done_held = mine is not None and mine.state is RobotState.DONE
        if msg.finished and not self._done_held and self._unfinished_said != msg.server_session:
            self._unfinished_said = msg.server_session
            log.warning("%s: the map server finished before this robot was done (it was stopped?): its results hold "
                        "%d of the %d keyframes this robot made so far; start it again on the same --out (it resumes) "
                        "and this robot sends it the rest", self.name, mine.keyframes if mine is not None else 0,
                        self.keyframes_sent)  # fmt: skip
        self.provisional_agents = mine.provisional_agents if mine is not None else ()
        self.waiting_agents = mine.waiting_agents if mine is not None else ()
        if mine is not None and mine.segments_allowed and mine.segments_allowed != self.front.max_segments:
            log.info("%s: the map server allows it %d trajectory segments", self.name, mine.segments_allowed)
            self.front.max_segments = mine.segments_allowed  # its share of the pose graph: stop at the last one

    def _server_spoke(self, server_session: str) -> None:
        """A status of map server ``server_session`` arrived: it is not silent. After a silence was said, say that a
        server answers (one other than the server heard before is said to have restarted, in ``_status``)."""
        if self._silence_said and self.server_session in (None, server_session):
            log.warning("%s: the map server answers %s", self.name,
                        "now" if self.server_session is None else "again")  # fmt: skip
        self._server_heard_s, self._silence_said = self.clock(), False

    def _check_server_silence(self) -> None:
        """Say once (``SERVER_SILENT_S``) that no map server has answered since this robot started, or that the one
        it had went silent; not once the server said it finished (it then leaves)."""
        silent_s = self.clock() - self._server_heard_s
        if self._silence_said or self.server_finished or silent_s < SERVER_SILENT_S:
            return
        self._silence_said = True
        if self.server_session is None:
            log.warning("%s: no map server has answered in %.0f s (is it running? does --connect name its endpoint?); "
                        "this robot goes on and sends its keyframes once one answers", self.name, silent_s)  # fmt: skip
        else:
            log.warning("%s: the map server has been silent for %.0f s (stopped, or the link is down?); this robot "
                        "goes on and keeps its keyframes until it answers again (a server started again on the same "
                        "--out resumes)", self.name, silent_s)  # fmt: skip

    def _resend_stalled(self) -> None:
        now = self.clock()
        for agent, sent in self._payloads.items():
            n = self._acked.get(agent, 0)
            if n >= len(sent) or not self._allowed(agent):
                continue
            if now - self._last_progress_s.get(agent, -np.inf) < self.resend_after_s:
                continue
            missing = sent[n:]
            log.info("%s: re-sending %d keyframes of %s from %d", self.name, len(missing), agent, n)
            for p in missing:
                self._publish("keyframe", keyframe_key(self.name), p)
            self.resent += len(missing)
            self._last_progress_s[agent] = now
        if (self._done is not None and not (self._done_held or self.server_finished)
                and now - self._done_sent_s >= self._done_every_s):
            self._send_done()
            self.resent_done += 1
            self._done_every_s = min(2 * self._done_every_s, DONE_RESEND_MAX_S)

    # --- state ---------------------------------------------------------------------------------

    def all_acknowledged(self) -> bool:
        """True when the server holds every keyframe this robot made."""
        return all(self._acked.get(a, 0) >= len(sent) for a, sent in self._payloads.items() if self._allowed(a))

    def _allowed(self, agent: str) -> bool:
        """Whether the server takes ``agent``'s keyframes: a segment beyond the robot's share (a race: made before
        the server's status said the share) is dropped there, so it is neither re-sent nor waited for."""
        limit = self.front.max_segments
        return limit is None or agent_robot(agent)[1] < limit

    def wait_acknowledged(self, timeout_s: float, *, until_finished: bool = False) -> bool:
        """Poll until the server holds every keyframe (and, with ``until_finished``, has finished and sent
        its final correction), at most ``timeout_s``; keeps the heartbeat going. Returns success."""
        deadline = self.clock() + timeout_s
        while self.clock() < deadline:
            self.heartbeat()
            self.poll(timeout_s=0.1)
            if self.all_acknowledged() and (self.server_finished or not until_finished):
                return True
        return False

    def fused(self) -> np.ndarray | None:
        """(N, 4, 4) this robot's frames in the shared frame from the latest corrections (NaN for frames
        of unplaced segments), or None when no segment is placed."""
        f = self.front
        segs = [s for s in f.segments if s.num_keyframes]
        return fuse_segments(
            f.T_odom_cam, f.frame_segment,
            {s.index: np.asarray(s.kf_frames, dtype=np.int64) for s in segs},
            {s.index: np.stack(s.kf_poses) for s in segs},
            {s.index: self._view.T_shared_kf[s.agent] for s in segs if s.agent in self._view.T_shared_kf},
        )  # fmt: skip

    def T_shared_odom(self, agent: str) -> np.ndarray | None:
        """(4, 4) where ``agent``'s odometry frame lies in the shared frame (at its latest keyframe the server
        has), or None when the server has not placed it."""
        return self._view.T_shared_odom.get(agent)
