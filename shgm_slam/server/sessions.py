"""What the map server knows of each robot's process: its session, liveness, last message, keyframe times."""

from __future__ import annotations

from collections.abc import Callable, Container
from dataclasses import dataclass, field

from shgm_slam.corrections import FusedView
from shgm_slam.messages import DoneMessage, RobotState
from shgm_slam.server.map_server import MapServer


@dataclass
class RobotSession:
    """What the server knows of one robot's process."""

    name: str
    session: str
    state: RobotState = RobotState.ACTIVE
    last_heard_s: float = 0.0
    done: DoneMessage | None = None
    kf_timestamps: dict[str, list[float]] = field(default_factory=dict)  # agent -> keyframe times
    kf_frames: dict[str, list[int]] = field(default_factory=dict)  # agent -> keyframe frame indices
    went_stale: int = 0  # how often it went silent (and was kept)
    corrected_version: int = -1  # pose-graph version of the last correction with poses (-1: send one now)
    view: FusedView = field(default_factory=FusedView)  # what the robot holds of its fused poses
    start_s: float | None = None  # its sequence's first timestamp (from its hellos; not kept in snapshots)
    progress_s: float | None = None  # how far it has got, seconds since start_s (hellos and keyframes)

    def complete(
        self, server: MapServer, queued: Callable[[str], int] = lambda _agent: 0, dropped: Container[str] = ()
    ) -> bool:
        """True when the robot said it is done and every keyframe it sent has arrived (in the map, or
        ``queued(agent)`` more waiting for their turn), but those of ``dropped`` agents (segments the map had no
        room for)."""
        return self.done is not None and all(
            server.received(a) + queued(a) >= n for a, n in self.done.keyframes.items() if a not in dropped
        )
