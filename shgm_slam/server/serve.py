"""The library function behind ``shgm-slam server``: a map server on Eclipse Zenoh until it is done.

It listens (peer mode, default ``tcp/127.0.0.1:7447``), runs a ``ServerNode`` with its journal in the
results folder (a server started again on the same folder recovers and continues), streams the fused
map to the viewer while robots are running, and returns when ``expect`` robots are done or on Ctrl-C /
SIGTERM (then whole graphs are matched once more and the results written all the same).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.config import ShgmConfig
from shgm_slam.errors import DataError
from shgm_slam.geometry import se3
from shgm_slam.interrupts import stops_deferred
from shgm_slam.messages import RobotState
from shgm_slam.server.node import ServerNode
from shgm_slam.server.placement import PlacementWatch
from shgm_slam.server.records import MatchRecord
from shgm_slam.transport.factory import NodeRole, make_transport
from shgm_slam.viz.map_positions import node_positions, odometry_start
from shgm_slam.viz.rerun_logger import NullLogger, Viz

log = logging.getLogger(__name__)

LINGER_S = 2.0
"""After finishing, the server keeps answering this long so every robot gets its final correction."""


@dataclass
class ServeSummary:
    """What ``serve`` returns: the server's metrics (``server.json``) and how it ended."""

    out_dir: Path
    summary: dict
    interrupted: bool
    wall_s: float


def _state_line(name: str, state: RobotState, robots: int, expect: int | None) -> str:
    """``car1: connected (1 of 3 robots expected)``, ``car1: silent (stale)``, ``car1: done`` ..."""
    text = {RobotState.ACTIVE: "connected", RobotState.STALE: "silent (stale; kept, it resumes when it returns)",
            RobotState.DONE: "sent its last keyframe"}[state]  # fmt: skip
    if state is RobotState.ACTIVE and expect and robots > expect:  # (it waits for every robot that connected)
        text += f" ({robots} robots, {expect} expected: the server waits for all {robots})"
    elif state is RobotState.ACTIVE and expect:
        text += f" ({robots} of {expect} robots expected)"
    return f"{name}: {text}"


class ServerView:
    """Streams a live map server to the viewer: each agent's graph and keyframe trajectory in the shared
    frame (at most every ``every_s`` per robot, so long runs do not re-send everything each keyframe),
    matches, robots joining and going stale, agents placed provisionally or confirmed."""

    def __init__(self, viz: Viz, *, every_s: float = 1.0, say: Callable[[str], None] | None = None) -> None:
        self.viz = viz
        self.every_s = every_s
        self.say = say  # robots joining, going stale, coming back and done, as lines (the command line prints them)
        self._last: dict[str, float] = {}
        self._states: dict[str, str] = {}
        self._sessions: dict[str, str] = {}  # robot -> the process (session) last seen
        self._placements = PlacementWatch()

    def _tell(self, node: ServerNode, name: str, state: RobotState) -> None:
        """Log robot ``name``'s new ``state`` to the viewer and say it (``say``)."""
        self.viz.log_text(f"{name}: {state.value}", "WARN" if state is RobotState.STALE else "INFO")
        if self.say is not None:
            self.say(_state_line(name, state, len(node.robots), node.expect))

    def recovered(self, node: ServerNode) -> None:
        """Take the robots a restarted server recovered from its journal as they stand, said once as recovered
        (they used to be said to connect, though none had yet); what changes later is said as it happens."""
        for name, rs in node.robots.items():
            self._states[name], self._sessions[name] = rs.state.value, rs.session
            held = sum(node.map.received(a) for a in rs.kf_frames) if node.map is not None else 0
            queued = f", {q} more queued for their turn" if (q := node.queued_keyframes(name)) else ""
            last = "; it had sent its last" if rs.done else ""
            line = f"{name}: recovered from the journal ({held} keyframes{queued}{last})"
            self.viz.log_text(line, "INFO")
            if self.say is not None:
                self.say(line)

    def update(self, node: ServerNode, records: list[MatchRecord]) -> None:
        server = node.map
        if server is None:
            return
        now = time.monotonic()
        for name, rs in node.robots.items():
            if self._sessions.setdefault(name, rs.session) != rs.session:  # killed and started again
                self._sessions[name] = rs.session
                line = f"{name}: started again (a new process); it goes on from the keyframes the server holds"
                self.viz.log_text(line, "INFO")
                if self.say is not None:
                    self.say(line)
            if self._states.get(name) != rs.state.value:
                if name not in self._states and rs.state is not RobotState.ACTIVE:
                    # it connected and got further (done) within one poll: its hello and its done came in one
                    # batch, so it was never seen active; it did connect, and is said to have
                    self._tell(node, name, RobotState.ACTIVE)
                self._states[name] = rs.state.value
                self._tell(node, name, rs.state)
            if now - self._last.get(name, -np.inf) < self.every_s:
                continue
            self._last[name] = now
            agents = [a for a in server.agents if agent_robot(a)[0] == name and server.received(a)]
            if not agents:
                continue
            frames = rs.kf_frames.get(agents[-1], [0])
            times = rs.kf_timestamps.get(agents[-1], [0.0])
            self.viz.set_time(name, int(frames[-1]), float(times[-1]))
            fused = [server.T_shared_kf(a) for a in agents]
            fused_xyz = np.concatenate([T[:, :3, 3] for T in fused if T is not None]) if any(
                T is not None for T in fused) else None  # fmt: skip
            last = agents[-1]
            T_odom_kf = server.keyframe_poses(last)
            T_shared_start = odometry_start(server, last, T_odom_kf[0])
            odo_xyz = T_odom_kf[:, :3, 3]
            if T_shared_start is not None:  # from its fused start (the reference: its odometry file)
                odo_xyz = se3.transform_points(T_shared_start, odo_xyz)
            self.viz.log_trajectories(name, odo_xyz, fused_xyz)
            shared = server.shared_graph(last)  # the fused map, as shared_graph_<agent>.json
            self.viz.log_graph(name, server.graph(last) if shared is None else shared)
        if records:  # agents placed provisionally, confirmed or outvoted
            for level, text in self._placements.changes(server):
                self.viz.log_text(text, level)
        for m in records:  # drawn where each robot's map is drawn (placed or not)
            if m.success:
                pairs = np.asarray(m.inliers, dtype=np.int64).reshape(-1, 2)  # node ids of robot_a, robot_b
                pa = node_positions(server, m.robot_a, pairs[:, 0], m.inlier_positions_a)
                pb = node_positions(server, m.robot_b, pairs[:, 1], m.inlier_positions_b)
                self.viz.log_matches(m.robot_a, m.robot_b, pa, pb, m.accepted, len(m.inliers))


RESUME_ADVICE = "start the server on this folder again: it resumes from its journal (journal.bin)"
"""What ``incomplete.txt`` in a failed map server's folder tells the user to do."""


def serve(
    cfg: ShgmConfig,
    out_dir: Path,
    *,
    listen: str | None = None,
    reference: str | None = None,
    expect: int | None = None,
    viz: Viz | None = None,
    stale_after_s: float = 5.0,
    started: Callable[[str], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> ServeSummary:
    """Run a map server until ``expect`` robots are done (or Ctrl-C / SIGTERM) and write its results.

    Args:
        cfg: the fleet configuration (written to ``config.yaml``).
        out_dir: the results folder; a journal already there is replayed first (restart).
        listen: Zenoh endpoint(s), comma-separated (default ``tcp/127.0.0.1:7447``).
        reference: the robot whose frame is the shared frame (default: the first to connect).
        expect: finish by itself once this many robots have connected and sent their last keyframe.
        viz: live viewer (``NullLogger`` when None).
        stale_after_s: a robot silent this long is marked stale (kept; it resumes when it returns).
        started: called once the endpoint is listened on and the folder's journal replayed, with "" or a line
            saying what was recovered (the command line says both then, not before).
        say: called with a line when a robot connects, goes silent, comes back or is done.

    Raises:
        TransportError, ConfigError: the endpoint cannot be listened on.
        DataError: ``out_dir`` holds a map server run that finished (``refuse_finished_folder``).
    """
    refuse_finished_folder(out_dir)
    viz = viz or NullLogger()
    viz.setup({})
    t0 = time.perf_counter()
    interrupted, linger = False, True
    with make_transport(NodeRole.SERVER, listen) as transport:
        node = ServerNode(cfg, transport, out_dir, reference=reference, expect=expect, stale_after_s=stale_after_s)
        node.writer.write_text("config.yaml", cfg.to_yaml())
        r = node.recovery
        resumed = ""
        if r.snapshot_records or r.replayed:
            resumed = (f"resumed from its journal: {r.snapshot_records} records from a snapshot and {r.replayed} "
                       f"replayed in {r.seconds:.1f} s")  # fmt: skip
            viz.log_text(resumed, "INFO")
        if started is not None:
            started(resumed)
        view = ServerView(viz, say=say)
        if resumed:
            view.recovered(node)
        try:
            while not node.finished:
                with stops_deferred():  # a stop lands between messages, never inside one
                    records = node.poll(timeout_s=0.1)
                view.update(node, records)
        except KeyboardInterrupt:
            interrupted = True
            node.interrupted = True  # server.json says so: the folder is not a finished run's
            log.warning("stopping: matching whole graphs once more and writing the results")
            linger = _finish_stopped(node, view)
        except Exception as exc:  # re-raised: the folder's files are a checkpoint, not the results
            node.writer.mark_failed(exc, RESUME_ADVICE)  # eval refuses the folder until a server finishes it
            raise
        summary = node.summary()  # as server.json says it (what comes while it lingers changes nothing)
        if linger and not _linger(node, LINGER_S) and not interrupted:
            raise KeyboardInterrupt  # a stop after the results were written ends the command as before (130)
    viz.close()
    return ServeSummary(Path(out_dir), summary, interrupted, time.perf_counter() - t0)


def _finish_stopped(node: ServerNode, view: ServerView) -> bool:
    """Finish a server stopped by Ctrl-C / SIGTERM: match whole graphs once more and write the results. A second
    stop meanwhile (an impatient Ctrl-C) waits until they are written, then only cuts short the linger (it used
    to end the process in the middle of the final matching, with the folder a checkpoint and one word said).
    Returns whether to linger (False after a second stop)."""
    try:
        with stops_deferred():
            records = node.finish()
    except KeyboardInterrupt:
        log.warning("stopped again: the results are written; not waiting for the robots' final corrections")
        return False
    view.update(node, records)
    return True


def _linger(node: ServerNode, seconds: float) -> bool:
    """Keep answering for ``seconds`` after finishing, so every robot gets its final correction; False when a stop
    (Ctrl-C / SIGTERM) cut it short."""
    until = time.monotonic() + seconds
    try:
        while time.monotonic() < until:
            with stops_deferred():
                node.poll(timeout_s=0.1)
    except KeyboardInterrupt:
        return False
    return True


def refuse_finished_folder(out_dir: Path) -> None:
    """Refuse a results folder whose map server finished (``server.json``: finished, not interrupted). Its journal
    would be replayed into a server that finishes at once (every expected robot done: robots of a new run then
    find no server), or, without ``expect``, that takes new robots of the same names for the old ones started
    again and ignores their keyframes up to the number the old ones sent. A stopped server's folder
    (``interrupted``) is resumed as before.

    Raises:
        DataError: naming the folder and what to do.
    """
    path = Path(out_dir) / "server.json"
    try:
        said = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return  # none (a new folder or a killed server's), or unreadable: the journal is what is resumed
    if isinstance(said, dict) and said.get("finished") is True and not said.get("interrupted"):
        raise DataError(
            f"results folder {out_dir} holds a map server run that finished ({path.name}: every expected robot was "
            "done); a server started on it would replay that run, not start a new one: choose another --out, or "
            "pass --overwrite to replace it"
        )

