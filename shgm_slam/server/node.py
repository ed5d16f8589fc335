"""The map server as a node: messages in through a transport, corrections and status out, results on disk.

One code path for both deployments: ``shgm-slam run`` drives a ``ServerNode`` over the in-process bus
next to its robots, ``shgm-slam server`` drives one over Eclipse Zenoh. The node

- decodes every message (``wire``); malformed bytes, another protocol version or a clashing robot name
  get a log line and are refused; nothing a peer sends can crash it;
- tracks each robot's process (``HelloMessage`` sessions): a new session under a live name is a clash
  and refused, under a silent one it is a restart and resumes where the robot left off;
- feeds keyframes to the ``MapServer`` in one time order over all robots (``ordering``: the order
  ``shgm-slam run`` uses, whatever the robots' speeds; idempotent: re-sent keyframes are ignored) and answers each
  robot with a ``CorrectionMessage`` (keyframes it holds; where its agents are in the shared frame, only
  what moved since the robot last heard, ``shgm_slam.corrections``);
- marks robots that went silent stale (kept; they resume when they come back);
- appends every accepted message to a journal and writes a snapshot of its state every so often, so a
  killed server started again on the same results folder loads the newest snapshot, replays the journal
  records after it and continues (``recovery``); keyframes waiting in the time order (acknowledged to their robot,
  not in the map yet, so not in the journal) are kept in ``queued.bin`` until the queue empties, and a restarted
  server queues them again: a robot that left with keyframes still waiting loses none;
- finishes by itself once ``expect`` robots have connected and each has sent its last keyframe: whole
  graphs are matched once more, the results folder is written and every robot gets its final correction;
  after that nothing changes its results: a robot process it does not hold is refused (it stops with the reason).
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.backend.keys import MAX_AGENTS, segments_per_robot
from shgm_slam.config import ShgmConfig
from shgm_slam.corrections import FusedView
from shgm_slam.errors import ConfigError, DataError, ShgmError
from shgm_slam.io.export import ResultsWriter
from shgm_slam.messages import (
    CorrectionMessage,
    DoneMessage,
    HelloMessage,
    KeyframeMessage,
    RobotState,
    RobotStatus,
    RobotTrajectory,
    StatusMessage,
)
from shgm_slam.server.journal import Journal
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.ordering import KeyframeOrder
from shgm_slam.server.records import MatchRecord, pair_matches
from shgm_slam.server.recovery import RecoveryReport, recover
from shgm_slam.server.results import fused_trajectory, keyframe_trajectory, provisional_note, robot_summary
from shgm_slam.server.sessions import RobotSession
from shgm_slam.server.snapshot import SnapshotStore, config_digest
from shgm_slam.server.snapshot_codec import ServerSnapshot, SnapshotError
from shgm_slam.server.traffic import TrafficStats
from shgm_slam.transport.base import Inbox, Transport
from shgm_slam.transport.keys import ALL_DONE, ALL_HELLO, ALL_KEYFRAMES, STATUS_KEY, correction_key, robot_of
from shgm_slam.wire import decode, encode

log = logging.getLogger(__name__)

CHECKPOINT_SHARE = 0.1
"""At most this share of the server's time goes into rewriting the results folder: a rewrite waits, beyond
``write_every_keyframes``, until ten times its last duration has passed (rewrites grow with the map)."""

CLASH_WINDOW_S = 2.5
"""A hello from a new session under a name whose current session was heard within this long is held:
if the current session speaks again it is a name clash and the newcomer is refused; once the current
session has been silent this long the newcomer is a restart and takes over (robots say hello every
``robot.node.HEARTBEAT_S``)."""

QUEUED_FILE = "queued.bin"
"""Keyframes waiting for their turn in the time order (journal records, ``server.journal``), kept until the queue
empties: acknowledged to their robot before the map takes them (and the journal records them)."""

CONNECT_WAIT_S = 30.0
"""With ``expect``, keyframes wait (in the server's time order, ``ordering``) at most this long after the
server started for the expected robots that have not connected yet."""


def finished_reason(interrupted: bool) -> str:
    """Why a map server that has finished refuses a robot process it does not hold, and what to do
    (``interrupted``: it was stopped before every expected robot was done)."""
    if interrupted:
        return ("the map server was stopped and has written its results; start it again on the same --out (it "
                "resumes from its journal), then this robot")
    return ("the map server has finished (every robot it expected was done) and written its results; run this "
            "robot with a new map server (another --out)")


class ServerNode:
    """The map server behind a transport (see the module docstring).

    Args:
        cfg: the fleet configuration (matching, back end).
        transport: where messages come from and corrections go.
        out_dir: the results folder (``journal.bin`` lives there too when ``journal`` is on).
        reference: the robot whose frame is the shared frame (None: the first robot to say hello).
        expect: finish by itself once this many robots have connected and each has sent its last
            keyframe (None: run until ``finish`` is called).
        journal: keep the crash-recovery journal and snapshots (``cfg.server``) and recover from them when
            ``out_dir`` has them.
        stale_after_s: a robot silent for this long is marked stale.
        status_every_s: how often the status is broadcast (and stale robots checked).
        correction_every_s: at most this often per robot a correction carries new fused poses
            (acknowledgements go out with every batch).
        write_every_keyframes: rewrite the results folder this often (0: only at the end), and less often
            when a rewrite would take more than ``CHECKPOINT_SHARE`` of the time since the last one.
        connect_wait_s: with ``expect``, how long keyframes wait for expected robots not connected yet.
        order_keyframes: take keyframes in one time order over all robots (``ordering``); off where the
            caller already sends them in that order (``shgm-slam run`` steps its robots so,
            ``data.interleave``), so each keyframe reaches the map at once.
        clock: monotonic seconds (tests pass a fake).
    """

    def __init__(
        self,
        cfg: ShgmConfig,
        transport: Transport,
        out_dir: Path,
        *,
        reference: str | None = None,
        expect: int | None = None,
        journal: bool = True,
        stale_after_s: float = 5.0,
        status_every_s: float = 1.0,
        correction_every_s: float = 0.5,
        write_every_keyframes: int = 50,
        connect_wait_s: float = CONNECT_WAIT_S,
        order_keyframes: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.transport = transport
        self.writer = ResultsWriter(out_dir)
        self.reference = reference
        self.expect = expect
        self.stale_after_s = stale_after_s
        self.status_every_s = status_every_s
        self.correction_every_s = correction_every_s
        self.write_every_keyframes = write_every_keyframes
        self.clock = clock
        self.connect_wait_s = connect_wait_s
        self.order_keyframes = order_keyframes
        self._order = KeyframeOrder()  # keyframes that arrived, waiting for their turn
        self._hellos: dict[str, bytes] = {}  # robot -> its current session's latest hello (payload; live or kept)
        self._hellos_kept: set[tuple[str, str]] = set()  # (robot, session) whose hello ``queued.bin`` holds
        self.session = uuid.uuid4().hex[:16]
        self.map: MapServer | None = None
        self.robots: dict[str, RobotSession] = {}
        self.traffic = TrafficStats()
        self.finished = False
        self.interrupted = False  # stopped (Ctrl-C / SIGTERM) before every expected robot was done
        self._refused: dict[str, str] = {}
        self._pending: dict[str, tuple[str, float]] = {}  # robot -> (newcomer session, first heard)
        self._admitted_agents: set[str] = set()  # agents whose keyframes go into the map (``_admitted``)
        self._dropped: dict[str, str] = {}  # agent -> why its keyframes are dropped
        self._pose_version = 0  # bumped whenever matching may have moved fused poses
        self._last_status_s = -np.inf
        self._last_correction_s: dict[str, float] = {}
        self._keyframes_since_write = 0
        self.timings_ms: dict[str, list[float]] = {"write": [], "correction": []}  # per call
        self._last_write_end_s = -np.inf  # perf_counter when the last rewrite ended
        self._inbox = Inbox()
        for key in (ALL_HELLO, ALL_KEYFRAMES, ALL_DONE):
            transport.subscribe(key, self._inbox)
        self.journal = Journal(Path(out_dir) / "journal.bin") if journal else None
        self.queued = Journal(Path(out_dir) / QUEUED_FILE, damaged_advice=(
            f"Delete {QUEUED_FILE} to resume: the keyframes it kept that the map does not hold are then lost, and the "
            "robots still running send theirs again")) if journal and order_keyframes else None  # fmt: skip
        every = cfg.server.snapshot_every_messages
        self.snapshots = SnapshotStore(out_dir, keep=cfg.server.snapshots_kept) if journal and every else None
        self.recovery = self._recover() if self.journal is not None else RecoveryReport()
        self.recovered_messages = self.recovery.replayed
        self._snapshot_at = (self.recovery.snapshot_records, self.clock())  # journal records, time
        self._snapshot_ms: list[float] = []  # wall time of each snapshot written
        self._started_s = self.clock()
        if self.reference is not None:
            self._map()

    # --- the loop ------------------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.0) -> list[MatchRecord]:
        """Handle every queued message (waiting up to ``timeout_s`` for the first), answer the robots,
        broadcast the status when due and finish when the expected robots are done.

        Returns the match attempts the messages triggered (for a viewer)."""
        items = self._inbox.drain()
        if not items and timeout_s > 0:
            first = self._inbox.get(timeout_s)
            items = [first, *self._inbox.drain()] if first is not None else []
        records: list[MatchRecord] = []
        touched: set[str] = set()
        for key, payload in items:
            robot, recs = self._handle(key, payload, live=True)
            records += recs
            if robot is not None:
                touched.add(robot)
        now = self.clock()
        stale_due = now - self._last_status_s >= self.status_every_s
        if stale_due:
            self._check_stale(now)
        records += self._release(now)
        if records:
            self._pose_version += 1
        for robot in sorted(touched):
            self._send_correction(robot, now)
        if stale_due:
            self._broadcast_status()
        if self.expect is not None and not self.finished and self._all_expected_done():
            records += self.finish()
        self._snapshot_if_due(now)
        return records

    def finish(self, *, match: bool = True) -> list[MatchRecord]:
        """Match whole graphs once more (``match``), write the results folder, send every robot its
        final correction and broadcast that the server has finished."""
        records = self._release(self.clock(), flush=True)
        if match and self.map is not None:
            records += self.map.finalize()
            self._pose_version += 1
        self.finished = True
        self.write_results()
        self.writer.clear_incomplete()  # (left by an earlier server on this folder that failed)
        for robot in self.robots:
            self._send_correction(robot, self.clock(), force=True)
        self._broadcast_status()
        for log_file in (self.journal, self.queued):
            if log_file is not None:
                log_file.close()
        return records

    # --- messages ------------------------------------------------------------------------------

    def _handle(self, key: str, payload: bytes, *, live: bool) -> tuple[str | None, list[MatchRecord]]:
        """Decode and apply one message; returns (robot to answer or None, match records)."""
        try:
            msg = decode(payload)
            sender = robot_of(key)
        except ShgmError as exc:
            self._refuse(f"{key}: {exc}")
            return None, []
        if isinstance(msg, HelloMessage):
            kind, robot = "hello", msg.robot
        elif isinstance(msg, KeyframeMessage):
            kind, robot = "keyframe", agent_robot(msg.robot)[0]
        elif isinstance(msg, DoneMessage):
            kind, robot = "done", msg.robot
        else:
            self._refuse(f"{key}: a {type(msg).__name__} is not for the server")
            return None, []
        if robot != sender:
            self._refuse(f"{key}: a {kind} message of robot {robot!r} on robot {sender!r}'s key")
            return None, []
        if live:
            self.traffic.add(kind, len(payload), robot)
        if self.finished:
            return self._after_finish(msg, robot), []
        now = self.clock()
        if isinstance(msg, HelloMessage):
            return self._hello(msg, payload, now, live=live), []
        rs = self.robots.get(robot)
        if rs is None or rs.session != msg.session:
            # not (or no longer) the robot's current process: after a server restart the robot says
            # hello again (it sees a new server session) and re-sends what is missing
            if live:
                log.debug("%s from %s session %s ignored (not its current session)", kind, robot, msg.session)
            return (robot if rs is not None else None), []
        self._heard(rs, now)
        if isinstance(msg, KeyframeMessage) and not self._admitted(rs, msg.robot):
            return robot, []
        if live and self.order_keyframes and isinstance(msg, KeyframeMessage) and rs.start_s is not None:
            self._offer(rs, msg, payload)
            return robot, []
        if isinstance(msg, DoneMessage):
            if live and self.journal is not None and rs.done is None:
                self.journal.append(payload)
            rs.done = self._settings_checked(msg)
            rs.state = RobotState.DONE  # it sent its last keyframe (the status tells it the done arrived)
            return robot, []
        return robot, self._keyframe(rs, msg, payload, live=live)

    def _after_finish(self, msg: HelloMessage | KeyframeMessage | DoneMessage, robot: str) -> str | None:
        """A message that came after the server finished (it lingers so every robot gets its final correction): its
        results are written, so nothing changes them, its summary or its journal any more. The current process of a
        robot it holds is answered (its keyframes held: a robot that was still sending learns what the results
        lack); a robot process it does not hold (a newcomer, or one started again) is refused with what to do, so
        it stops instead of being acknowledged into results that no longer take it in."""
        rs = self.robots.get(robot)
        if rs is not None and rs.session == msg.session:
            return robot
        if isinstance(msg, HelloMessage):
            reason = finished_reason(self.interrupted)
            if self._refused.get(robot) != f"{msg.session}: {reason}":
                self._refused[robot] = f"{msg.session}: {reason}"
                self._refuse(f"hello of {robot} (session {msg.session}): {reason}")
                self._broadcast_status()
        return None

    def _hello(self, msg: HelloMessage, payload: bytes, now: float, *, live: bool) -> str | None:
        if not self._same_settings(msg, live=live):
            return None
        rs = self.robots.get(msg.robot)
        new_session = rs is None or rs.session != msg.session
        if rs is not None and rs.session != msg.session:
            if live and rs.state is not RobotState.STALE and now - rs.last_heard_s < CLASH_WINDOW_S:
                # a restart or a second process under the same name? Hold the newcomer until the current
                # session is either heard again (a clash: refuse the newcomer) or silent long enough
                pending = self._pending.get(msg.robot)
                if pending is None or pending[0] != msg.session:
                    self._pending[msg.robot] = (msg.session, now)
                return None
            log.info("%s restarted (session %s); resuming after %d keyframes", msg.robot, msg.session,
                     sum(self._map().received(a) for a in rs.kf_frames) if self.map else 0)  # fmt: skip
            rs.session, rs.done, rs.progress_s = msg.session, None, None
            rs.state = RobotState.ACTIVE
            self._order.drop(msg.robot)  # the new process sends them again
        elif rs is None:
            if self.reference is None:
                self.reference = msg.robot
            rs = RobotSession(msg.robot, msg.session)
            self.robots[msg.robot] = rs
            ref = " (the reference: its frame is the shared frame)" if msg.robot == self.reference else ""
            log.info("%s connected (session %s)%s", msg.robot, msg.session, ref)
        self._refused.pop(msg.robot, None)
        rs.start_s = msg.start_s
        # its first frame's time, for the keyframes ``queued.bin`` keeps (also a replayed one: after a restart a
        # keyframe may come before the robot's next hello, and a snapshot keeps no start_s)
        self._hellos[msg.robot] = payload
        if live and msg.progress_s is not None and msg.server_session == self.session:  # (not a dead server's)
            rs.progress_s = max(msg.progress_s, rs.progress_s or 0.0)
        self._heard(rs, now)
        if new_session:
            if live and self.journal is not None:  # heartbeats of a known session change nothing to recover
                self.journal.append(payload)
        if new_session or (msg.resync and rs.view.seq):
            rs.view = FusedView()  # it holds nothing (new process) or missed a correction: a full one next
            rs.corrected_version = -1
        return msg.robot

    def _same_settings(self, msg: HelloMessage, *, live: bool = True) -> bool:
        """Whether the robot's front end runs on this server's settings for it (``front_end_digest``); else it
        is refused, once per session (its process stops with the reason). A hello without a digest passes.

        Raises:
            ConfigError: a hello replayed from the journal (``live`` False) differs: the server was restarted
                with another ``--config`` than the one it ran with, and refusing every robot would resume on
                an empty map.
        """
        ours = self.cfg.front_end_digest(msg.robot)
        if msg.settings_digest in ("", ours):
            return True
        if not live:
            raise ConfigError(
                f"the journal in {self.writer.root} holds {msg.robot}'s keyframes made with other front-end "
                "settings (extraction, graph, keyframes, odometry) than this --config gives it: restart the server "
                "with the --config it ran with, or pass --overwrite to start afresh with this one"
            )
        reason = (f"its front-end settings (extraction, graph, keyframes, odometry; digest {msg.settings_digest}) "
                  f"differ from the map server's for it (digest {ours}): start every robot with the server's "
                  "--config file (settings of one robot go under `robots: <name>:` in it)")  # fmt: skip
        refusal = f"{msg.session}: {reason}"
        if self._refused.get(msg.robot) != refusal:
            self._refused[msg.robot] = refusal
            self._refuse(f"hello of {msg.robot} (session {msg.session}): {reason}")
            self._broadcast_status()
        return False

    def _settings_checked(self, msg: DoneMessage) -> DoneMessage:
        """``msg``, without its ``settings`` when they are not valid front-end values for this config (logged)."""
        if msg.settings is None:
            return msg
        try:
            self.cfg.with_robot_values({msg.robot: msg.settings}).for_robot(msg.robot)
        except ValueError as exc:  # (pydantic's ValidationError is one)
            self._refuse(f"settings of {msg.robot}'s done: {str(exc).splitlines()[0]}; config.yaml leaves them out")
            return replace(msg, settings=None)
        return msg

    def robot_settings(self) -> dict[str, dict[str, dict[str, float | int | bool]]]:
        """Each done robot's front-end values as it said them (``DoneMessage.settings``), by robot name."""
        return {name: rs.done.settings for name, rs in self.robots.items()
                if rs.done is not None and rs.done.settings is not None}  # fmt: skip

    def _heard(self, rs: RobotSession, now: float) -> None:
        """The robot's current session spoke: it is alive, so a newcomer under its name is a clash."""
        rs.last_heard_s = now
        if rs.state is RobotState.STALE:
            log.info("%s is back", rs.name)
            rs.state = RobotState.ACTIVE
        pending = self._pending.get(rs.name)
        if pending is not None and pending[0] != rs.session and now > pending[1]:
            del self._pending[rs.name]
            reason = (f"robot name {rs.name!r} is in use by another running robot process; "
                      "give every robot its own name")  # fmt: skip
            self._refused[rs.name] = f"{pending[0]}: {reason}"
            self._refuse(f"hello of {rs.name} (session {pending[0]}): {reason}")
            self._broadcast_status()

    def expect_robots(self, count: int) -> None:
        """A robot that has not connected will (a camera added to a live run): the map server waits for ``count``
        robots (``expect``, never fewer than before) and shares the pose graph among them, and the robots hear
        their smaller share at once (``segments_allowed``), so the running ones leave the newcomer its agents."""
        self.expect = max(self.expect or 0, count)
        self._broadcast_status()

    def segments_allowed(self) -> int:
        """Trajectory segments each robot may start (the robot and its segments after odometry failures): its
        share of the pose graph's ``MAX_AGENTS`` among the fleet, the ``expect`` robots (or more, once more have
        connected) or, when the fleet size is not given, the robots connected so far and room for one more."""
        fleet = max(self.expect, len(self.robots)) if self.expect else len(self.robots) + 1
        return segments_per_robot(fleet)

    def _admitted(self, rs: RobotSession, agent: str) -> bool:
        """Whether ``agent``'s keyframes go into the map: an agent the map (or the time order) already holds, or
        a new one while its robot holds fewer than ``segments_allowed`` and the pose graph has room. A refused
        segment is logged once and its keyframes dropped (``dropped_segments``); a robot whose *first* agent
        finds the pose graph full is refused (its process stops with the reason)."""
        if agent in self._dropped:
            return False
        server = self._map()
        if agent in self._admitted_agents or agent in server.agents:
            return True
        known = self._admitted_agents | set(server.agents)
        held = sum(agent_robot(a)[0] == rs.name for a in known)
        allowed = self.segments_allowed()
        if len(known) >= MAX_AGENTS:
            reason = (f"the pose graph holds at most {MAX_AGENTS} agents (robots and their trajectory segments after "
                      "odometry failures) and all are in use; run fewer robots or fix the odometry")  # fmt: skip
        elif held >= allowed:
            reason = (f"{rs.name} has had its share of {allowed} trajectory segments (the pose graph's {MAX_AGENTS} "
                      "agents shared by the fleet); its later keyframes are dropped")  # fmt: skip
        else:
            self._admitted_agents.add(agent)
            return True
        self._dropped[agent] = reason
        self._refuse(f"keyframes of {agent}: {reason}")
        if held == 0:
            self._refused[rs.name] = f"{rs.session}: {reason}"
            self._broadcast_status()
        return False

    def queued_keyframes(self, robot: str) -> int:
        """Keyframes of ``robot`` waiting for their turn in the time order (``ordering``)."""
        return self._order.queued(robot)

    @property
    def dropped_segments(self) -> dict[str, str]:
        """Agents whose keyframes were dropped (no room in the pose graph) -> why."""
        return dict(self._dropped)

    def _offer(self, rs: RobotSession, msg: KeyframeMessage, payload: bytes, *, kept: bool = False) -> None:
        """Queue a live keyframe for its turn in the time order (``ordering``); re-sent ones are ignored. The
        keyframe is kept in ``queued.bin`` before its robot hears it is held (``kept``: it is there already)."""
        if msg.kf_index != self._map().received(msg.robot) + self._order.held(msg.robot):
            return  # a re-sent duplicate, or a gap after a lost message (the correction asks again)
        assert rs.start_s is not None
        if self.queued is not None and not kept:
            hello = self._hellos.get(rs.name)
            if (rs.name, rs.session) not in self._hellos_kept and hello is not None:
                # the robot's hello first: a snapshot does not keep its first frame's time, which orders them
                self.queued.append(hello)
                self._hellos_kept.add((rs.name, rs.session))
            self.queued.append(payload)
        rank = 0 if rs.name == self.reference else 1
        self._order.offer(msg, payload, rs.start_s, rank)
        rs.progress_s = max(msg.timestamp_s - rs.start_s, rs.progress_s or 0.0)

    def _queue_kept(self) -> int:
        """After recovery: queue again the keyframes ``queued.bin`` holds that the map has not taken (those of a
        robot's current process; the rest the map holds, or a restarted robot sends again). Returns how many."""
        before = len(self._order)
        for index, payload in enumerate(self.queued.replay() if self.queued is not None else ()):
            try:
                msg = decode(payload)
            except ShgmError as exc:
                log.warning("%s record %d unreadable (%s); skipped", QUEUED_FILE, index, exc)
                continue
            if isinstance(msg, HelloMessage):
                rs = self.robots.get(msg.robot)
                if rs is not None and rs.session == msg.session and rs.start_s is None:
                    rs.start_s, self._hellos[msg.robot] = msg.start_s, payload  # (kept again with its keyframes)
                continue
            if not isinstance(msg, KeyframeMessage):
                continue
            rs = self.robots.get(agent_robot(msg.robot)[0])
            if rs is None or rs.session != msg.session or rs.start_s is None or not self._admitted(rs, msg.robot):
                continue
            self._offer(rs, msg, payload, kept=True)
        return len(self._order) - before

    def _release(self, now: float, *, flush: bool = False) -> list[MatchRecord]:
        """Hand the map server every queued keyframe whose turn has come (all of them with ``flush``)."""
        if not len(self._order):
            return []
        progress: dict[str, float | None] = {}
        if not flush:
            for rs in self.robots.values():
                if rs.done is None:
                    waited = rs.state is RobotState.ACTIVE
                else:  # done, but keyframes are missing (e.g. lost with a killed server): it re-sends them
                    waited = now - rs.last_heard_s <= self.stale_after_s and not rs.complete(
                        self._map(), self._order.held, self._dropped
                    )
                progress[rs.name] = rs.progress_s if waited else float("inf")
            missing = (self.expect or 0) - len(self.robots)
            if missing > 0 and now - self._started_s < self.connect_wait_s:
                progress[""] = None  # an expected robot that has not connected yet
        records: list[MatchRecord] = []
        for held in self._order.release(progress):
            rs = self.robots[agent_robot(held.msg.robot)[0]]
            records += self._keyframe(rs, held.msg, held.payload, live=True)
        if not len(self._order) and self.queued is not None and self.queued.records:
            self.queued.clear()  # every keyframe it kept is in the map, so in the journal
            self._hellos_kept.clear()
        return records

    def _keyframe(self, rs: RobotSession, msg: KeyframeMessage, payload: bytes, *, live: bool) -> list[MatchRecord]:
        server = self._map()
        if msg.kf_index != server.received(msg.robot):
            return []  # a re-sent duplicate, or a gap after a lost message (the correction asks again)
        if live and self.journal is not None:
            self.journal.append(payload)
        rs.kf_timestamps.setdefault(msg.robot, []).append(msg.timestamp_s)
        rs.kf_frames.setdefault(msg.robot, []).append(msg.frame_index)
        records = server.receive(msg)
        self._keyframes_since_write += 1
        if live and self.write_every_keyframes and self._keyframes_since_write >= self.write_every_keyframes:
            last_s = self.timings_ms["write"][-1] / 1e3 if self.timings_ms["write"] else 0.0
            if time.perf_counter() - self._last_write_end_s >= last_s / CHECKPOINT_SHARE:
                self.write_results()
        return records

    def _refuse(self, reason: str) -> None:
        log.warning("refused: %s", reason)
        self.traffic.refuse(reason)

    def _map(self) -> MapServer:
        if self.map is None:
            if self.reference is None:
                raise ShgmError("no reference robot yet")  # not reached: a hello sets it first
            self.map = MapServer([self.reference], self.cfg)
        return self.map

    # --- answers -------------------------------------------------------------------------------

    def _send_correction(self, robot: str, now: float, *, force: bool = False) -> None:
        """Acknowledge ``robot``'s keyframes; when matching moved fused poses (at most every
        ``correction_every_s``), an agent of it is placed that it has not heard of (any agent, at once: the reference
        robot at its first keyframe) or ``force``, also send what moved beyond ``server.correction_tolerance_*``
        since the robot last got it (everything after a (re)connect or a resync request, and when
        ``force``: the final correction leaves the robot with exactly the server's poses)."""
        rs = self.robots.get(robot)
        if rs is None:
            return
        t0 = time.perf_counter()
        server = self._map()
        agents = [a for a in server.agents if agent_robot(a)[0] == robot]
        due = force or (
            rs.corrected_version != self._pose_version
            and now - self._last_correction_s.get(robot, -np.inf) >= self.correction_every_s
        ) or any(server.is_placed(a) and a not in rs.view.T_shared_odom for a in agents)  # placed, unheard of (the
        # reference at its first keyframe: before, it heard so only after the first match anywhere)
        seq, full, changes = 0, False, {}
        if due:
            full = force or rs.view.seq == 0
            current = {a: (server.T_shared_odom(a), server.T_shared_kf(a)) if server.is_placed(a) else None
                       for a in agents}  # fmt: skip
            scfg = self.cfg.server
            changes = rs.view.changes(current, scfg.correction_tolerance_m, scfg.correction_tolerance_rad, full=full)
            seq = rs.view.seq + 1 if changes or full else 0
            rs.corrected_version = self._pose_version
            self._last_correction_s[robot] = now
        queued = [a for a in self._order.agents() if agent_robot(a)[0] == robot and a not in agents]
        received = {a: server.received(a) + self._order.held(a) for a in agents + queued}  # queued ones held too
        msg = CorrectionMessage(robot, rs.session, received, seq, full, changes)
        rs.view.apply(msg)
        payload = encode(msg)
        self.traffic.sent("correction", len(payload), robot)
        self.transport.publish(correction_key(robot), payload)
        self.timings_ms["correction"].append((time.perf_counter() - t0) * 1e3)

    def _broadcast_status(self) -> None:
        self._last_status_s = self.clock()
        robots = {}
        for name, rs in self.robots.items():
            agents = tuple(a for a in (self.map.agents if self.map else []) if agent_robot(a)[0] == name)
            robots[name] = RobotStatus(
                rs.state,
                sum(self._map().received(a) for a in agents),
                tuple(a for a in agents if self._map().is_placed(a)),
                agents,
                tuple(a for a in agents if self._map().placement(a).provisional),
                tuple(a for a in agents if self._map().waiting_note(a) is not None),
                self.segments_allowed(),
            )
        payload = encode(StatusMessage(self.session, self.reference or "", robots, self.finished, dict(self._refused)))
        self.traffic.sent("status", len(payload))
        self.transport.publish(STATUS_KEY, payload)

    def _check_stale(self, now: float) -> None:
        for rs in self.robots.values():
            if rs.state is RobotState.ACTIVE and now - rs.last_heard_s > self.stale_after_s:
                log.warning("%s went silent (%.0f s); kept, marked stale until it comes back", rs.name,
                            now - rs.last_heard_s)  # fmt: skip
                rs.state = RobotState.STALE
                rs.went_stale += 1

    def _all_expected_done(self) -> bool:
        return (
            self.map is not None
            and len(self.robots) >= (self.expect or 0)
            and all(rs.complete(self.map, dropped=self._dropped) for rs in self.robots.values())
        )

    # --- recovery ------------------------------------------------------------------------------

    def _recover(self) -> RecoveryReport:
        """A restarted server: the newest usable snapshot, then the journal records after it."""
        report = recover(self.journal, self.snapshots, digest=config_digest(self.cfg), reference=self.reference,
                         restore=self.restore, replay=self._replay)  # fmt: skip
        if report.snapshot_records or report.replayed:
            for rs in self.robots.values():  # waited for (keyframe order) until they speak or go stale
                rs.last_heard_s, rs.progress_s = self.clock(), None
            log.info("recovered from %s in %.1f s (%d records from a snapshot, %d replayed): %s", self.journal.path,
                     report.seconds, report.snapshot_records, report.replayed,
                     ", ".join(f"{r} {sum(self._map().received(a) for a in rs.kf_frames)} keyframes"
                               for r, rs in self.robots.items()))  # fmt: skip
            if queued := self._queue_kept():
                log.info("queued again %d keyframes that were waiting for their turn (%s)", queued, QUEUED_FILE)
            self._say_missing_keyframes()
        return report

    def _say_missing_keyframes(self) -> None:
        """After recovery: name each robot that had sent its last keyframe but whose keyframes neither the journal
        nor ``queued.bin`` holds (a folder of an earlier version, or one whose ``queued.bin`` was lost): it must be
        started again to send them (the server waits for them and never finishes by itself before)."""
        for name, rs in self.robots.items():
            if rs.done is None or rs.complete(self._map(), self._order.held, dropped=self._dropped):
                continue
            made = sum(n for a, n in rs.done.keyframes.items() if a not in self._dropped)
            held = sum(self._map().received(a) + self._order.held(a) for a in rs.done.keyframes
                       if a not in self._dropped)  # fmt: skip
            log.warning("%s: the journal and %s hold %d of the %d keyframes it sent; start robot %s again (its same "
                        "command) to send them", name, QUEUED_FILE, held, made, name)  # fmt: skip

    def _replay(self, payload: bytes, index: int) -> None:
        """Apply journal record ``index`` (only accepted messages, each from its own robot)."""
        try:
            msg = decode(payload)
        except ShgmError as exc:
            log.warning("journal record %d unreadable (%s); skipped", index, exc)
            return
        robot = msg.robot if not isinstance(msg, KeyframeMessage) else agent_robot(msg.robot)[0]
        self._handle(f"shgm/{robot}/replay", payload, live=False)

    def snapshot(self) -> ServerSnapshot:
        """The server's state after every journal record so far (what ``restore`` loads)."""
        return ServerSnapshot(
            self.journal.records if self.journal is not None else 0, self.journal.chain if self.journal else 0,
            config_digest(self.cfg), self.reference, tuple(self.robots.values()),
            self.map.state() if self.map is not None else None,
        )  # fmt: skip

    def restore(self, snap: ServerSnapshot) -> None:
        """Load a snapshot into this fresh node (nothing changes when it raises).

        Raises:
            SnapshotError, GraphError, BackendError: the snapshot's content is inconsistent.
        """
        server = MapServer.from_state(snap.map, self.cfg) if snap.map is not None else None
        if server is not None and server.reference != snap.reference:
            raise SnapshotError(f"snapshot's shared frame is {server.reference}'s but it names {snap.reference}")
        robots = {rs.name: rs for rs in snap.sessions}
        for rs in robots.values():
            for a, frames in rs.kf_frames.items():
                held = server.received(a) if server is not None else 0
                if agent_robot(a)[0] != rs.name or len(frames) != held or len(rs.kf_timestamps.get(a, ())) != held:
                    raise SnapshotError(f"snapshot session of {rs.name} disagrees with the map about {a}'s keyframes")
        self.map, self.robots, self.reference = server, robots, snap.reference or self.reference

    def _snapshot_if_due(self, now: float) -> None:
        """Write a snapshot after ``snapshot_every_messages`` new journal records, or ``snapshot_every_s``
        seconds with new records; never after finishing (the journal has no record of the final matching)."""
        if self.snapshots is None or self.finished:
            return
        n = self.journal.records
        done, at_s = self._snapshot_at
        scfg = self.cfg.server
        if n == done or (n - done < scfg.snapshot_every_messages and now - at_s < scfg.snapshot_every_s):
            return
        t0 = time.perf_counter()
        try:
            path = self.snapshots.write(self.snapshot())
        except DataError as exc:  # the journal still holds everything: carry on without this snapshot
            log.warning("snapshot not written (%s); a restart would replay more of the journal", exc)
        else:
            self._snapshot_ms.append((time.perf_counter() - t0) * 1e3)
            log.debug("snapshot %s (%d bytes) in %.0f ms", path.name, self.snapshots.last_bytes, self._snapshot_ms[-1])
        self._snapshot_at = (n, now)

    # --- results -------------------------------------------------------------------------------

    def fused_trajectory(self, robot: str) -> tuple[np.ndarray, np.ndarray | None] | None:
        """``(timestamps_s (N,), T_shared_cam (N, 4, 4) or None)`` of ``robot``'s frames, once it has sent
        its trajectory (``DoneMessage``); None before (see ``keyframe_trajectory``) or for unknown robots."""
        rs = self.robots.get(robot)
        if rs is None or self.map is None or self.trajectory(robot) is None:
            return None
        return fused_trajectory(self.map, rs)

    def keyframe_trajectory(self, robot: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(timestamps_s (K,), T_odom_kf (K, 4, 4), T_shared_kf (K, 4, 4) or None)`` of all of ``robot``'s
        keyframes in time order (``results.keyframe_trajectory``; empty for unknown robots)."""
        rs = self.robots.get(robot)
        if rs is None or self.map is None:
            return np.zeros(0), np.zeros((0, 4, 4)), None
        return keyframe_trajectory(self.map, rs)

    def trajectory(self, robot: str) -> RobotTrajectory | None:
        """The per-frame odometry ``robot`` sent with its last keyframe, if it has."""
        rs = self.robots.get(robot)
        return rs.done.trajectory if rs is not None and rs.done is not None else None

    def write_results(self) -> None:
        """(Re)write the results folder: trajectories, graphs, matches, pose graph, server metrics."""
        self._keyframes_since_write = 0
        if self.map is None:
            return
        t0 = time.perf_counter()
        with self.writer.checkpoint():  # all files or none: a full disk keeps the previous checkpoint whole
            self._write_checkpoint(self.map)
        self._last_write_end_s = time.perf_counter()
        self.timings_ms["write"].append((self._last_write_end_s - t0) * 1e3)

    def _write_checkpoint(self, server: MapServer) -> None:
        for robot in self.robots:
            traj = self.trajectory(robot)
            note = self.provisional_note(robot)
            if traj is not None:
                fused = self.fused_trajectory(robot)[1]
                self.writer.write_trajectories(robot, traj.timestamps_s, traj.T_odom_cam, fused, provisional=note)
            else:
                times, T_odom_kf, T_shared_kf = self.keyframe_trajectory(robot)
                if len(times):
                    self.writer.write_keyframe_trajectory(robot, times, T_odom_kf, T_shared_kf, provisional=note)
            for a in server.agents:
                if agent_robot(a)[0] == robot:
                    self.writer.write_graph(a, server.graph(a))
                    self.writer.write_shared_graph(a, server.shared_graph(a))
        self.writer.write_matches(server.matches)
        self.writer.write_text("pose_graph.g2o", server.to_g2o())
        settings = self.robot_settings()
        if settings:  # with the robots' data-derived values: loading it reproduces their front ends
            self.writer.write_text("config.yaml", self.cfg.with_robot_values(settings).to_yaml())
        self.writer.write_json("server.json", self.summary())

    def provisional_note(self, robot: str) -> str | None:
        """Why ``robot``'s place in the shared frame is provisional (``results.provisional_note``), or None."""
        return provisional_note(self.map, robot) if self.map is not None else None

    def summary(self) -> dict:
        """Server-side metrics: robots, their state and placement, traffic, refusals."""
        server = self.map
        robots = {name: robot_summary(server, rs, self._dropped) for name, rs in self.robots.items()}
        return {
            "session": self.session,
            "reference": self.reference,
            "finished": self.finished,
            "interrupted": self.interrupted,
            "recovered_messages": self.recovered_messages,
            "recovery": self.recovery.to_json_dict(),
            "snapshots_written": self.snapshots.written if self.snapshots is not None else 0,
            "snapshot_bytes": self.snapshots.last_bytes if self.snapshots is not None else 0,
            "snapshot_write_ms": round(float(np.mean(self._snapshot_ms)), 1) if self._snapshot_ms else None,
            "segments_allowed": self.segments_allowed(),
            "robots": robots,
            "matches_tried": len(server.matches) if server else 0,
            "closures_accepted": sum(m.accepted for m in server.matches) if server else 0,
            "mean_match_ms": server.mean_match_ms() if server else 0.0,
            "anchorings": server.anchorings() if server else [],
            "last_looks": server.last_looks() if server else [],
            # a line per robot pair none of whose matches was accepted, and how close the closest came (as `run`)
            "never_met": [line for p in pair_matches(server.matches) if (line := p.never_met())] if server else [],
            "traffic": self.traffic.to_json_dict(),
        }
