"""The library function behind ``shgm-slam robot``: one robot's front end on Eclipse Zenoh.

The robot connects to the map server (it may start before the server; Zenoh keeps trying), runs its
frames as fast as it can or paced by their timestamps (``realtime``), sends keyframes, applies the
corrections it receives, and after its last frame waits (bounded) until the server holds every
keyframe and has finished. It writes its own odometry and fused trajectories to ``out_dir``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shgm_slam.config import ShgmConfig
from shgm_slam.errors import DataError
from shgm_slam.interrupts import stops_deferred
from shgm_slam.io.export import ResultsWriter, check_writable_dir
from shgm_slam.robot.build import make_frontend
from shgm_slam.robot.node import RobotNode
from shgm_slam.transport.factory import NodeRole, make_transport
from shgm_slam.types import Sequence

log = logging.getLogger(__name__)


@dataclass
class DriveSummary:
    """What one robot process did."""

    name: str
    session: str
    frames: int
    frames_processed: int
    keyframes: int
    acknowledged: bool  # the server holds every keyframe
    server_finished: bool
    placed_agents: list[str]
    bytes_sent: dict[str, int]
    bytes_received: dict[str, int]
    resent: int
    wall_s: float
    interrupted: bool = False
    skipped: list[str] = field(default_factory=list)
    provisional_agents: list[str] = field(default_factory=list)  # placed, not confirmed by an independent match
    waiting_agents: list[str] = field(default_factory=list)  # not placed: too few independent accepted matches

    @property
    def bytes_per_keyframe(self) -> float:
        return self.bytes_sent.get("keyframe", 0) / max(self.keyframes, 1)


def drive_robot(
    name: str,
    sequence: Sequence,
    cfg: ShgmConfig,
    *,
    connect: str | None = None,
    realtime: bool = False,
    out_dir: Path | None = None,
    wait_s: float = 60.0,
    progress: Callable[[int, int], None] | None = None,
) -> DriveSummary:
    """Run one robot against a map server over Zenoh.

    Raises:
        DataError: ``out_dir`` cannot be written (checked before the first frame), or the sequence's data.

    Args:
        name: the robot's name (unique in the fleet).
        sequence: its frames.
        cfg: the fleet configuration (the robot's overrides are merged in).
        connect: the server's Zenoh endpoint(s), comma-separated (default ``tcp/127.0.0.1:7447``).
        realtime: pace frames by their timestamps (default: as fast as possible).
        out_dir: where to write this robot's trajectories (None: nowhere).
        wait_s: after the last frame, wait at most this long for the server's acknowledgements.
        progress: called with (frames done, frames total).
    """
    if out_dir is not None:  # refused now, not after every frame has run
        check_writable_dir(out_dir)
    front = make_frontend(name, sequence, cfg)
    t_start = time.perf_counter()
    times = np.asarray(sequence.timestamps_s, dtype=np.float64)
    skipped: list[str] = []
    processed = 0
    interrupted = False
    with make_transport(NodeRole.ROBOT, connect) as transport:
        node = RobotNode(front, transport)
        node.hello()
        t0 = time.monotonic()
        try:
            for i in range(len(sequence)):
                due = t0 + (times[i] - times[0])
                while realtime and (wait := due - time.monotonic()) > 0:  # poll returns on any message
                    node.heartbeat()
                    node.poll(timeout_s=min(wait, 0.1))
                with stops_deferred():  # a stop lands between frames, never inside the robot's step
                    try:
                        node.step(i)
                        processed += 1
                    except DataError as exc:
                        skipped.append(f"frame {i}: {exc}")
                        log.warning("%s: skipped frame %d: %s", name, i, exc)
                    node.poll()
                if progress:
                    progress(i + 1, len(sequence))
        except KeyboardInterrupt:
            interrupted = True
        if not interrupted:  # a stopped robot is not done: the server keeps it (stale) and the same command resumes
            node.done()
        acknowledged = node.wait_acknowledged(wait_s, until_finished=not interrupted)
        if not node.all_acknowledged():
            log.warning("%s: the map server did not acknowledge every keyframe within %.0f s", name, wait_s)
    if out_dir is not None:
        write_robot_trajectories(out_dir, node)
    return drive_summary(node, processed, acknowledged, time.perf_counter() - t_start, interrupted, skipped)


def write_robot_trajectories(out_dir: Path, node: RobotNode) -> None:
    """The robot's odometry and fused trajectories (``<robot>_odometry_tum.txt``, ``<robot>_fused_tum.txt``, ...) in
    ``out_dir``, as its node holds them; the fused one flagged provisional where the server said so."""
    front = node.front
    placed = [s.agent for s in front.segments if node.T_shared_odom(s.agent) is not None]
    provisional = [a for a in placed if a in node.provisional_agents]
    why = "placed provisionally by the map server (no independent match confirms it yet): "
    times = np.asarray(front.sequence.timestamps_s, dtype=np.float64)
    ResultsWriter(out_dir).write_trajectories(node.name, times, front.T_odom_cam, node.fused(),
                                              provisional=why + ", ".join(provisional) if provisional else None)


def drive_summary(
    node: RobotNode, processed: int, acknowledged: bool, wall_s: float, interrupted: bool, skipped: list[str]
) -> DriveSummary:
    """What a robot process did, once its node has sent its last keyframe and waited for the server
    (``acknowledged``: ``RobotNode.wait_acknowledged``'s answer)."""
    front = node.front
    placed = [s.agent for s in front.segments if node.T_shared_odom(s.agent) is not None]
    return DriveSummary(
        node.name, node.session, len(front.sequence), processed, node.keyframes_sent, node.all_acknowledged(),
        node.server_finished and acknowledged, placed, dict(node.bytes_sent), dict(node.bytes_received),
        node.resent, wall_s, interrupted, skipped, [a for a in placed if a in node.provisional_agents],
        [s.agent for s in front.segments if s.agent in node.waiting_agents],
    )  # fmt: skip
