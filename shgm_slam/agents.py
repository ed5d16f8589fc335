"""Agent names: a robot and its later trajectory segments (after odometry failures) are agents of
the map server: ``car1``, ``car1#1``, ``car1#2`` ..."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)


SEGMENT_SEPARATOR = "#"
"""Agent names of trajectory segments: ``car1`` (the first), ``car1#1``, ``car1#2`` ... (robot names
cannot contain it, see ``runner.parse_robot_arg``)."""


def segment_agent(robot: str, segment: int) -> str:
    """The map server's agent name of ``robot``'s trajectory segment ``segment`` (0: the robot's name)."""
    return robot if segment == 0 else f"{robot}{SEGMENT_SEPARATOR}{segment}"


def agent_robot(agent: str) -> tuple[str, int]:
    """Inverse of ``segment_agent``: (robot, segment index)."""
    robot, _, seg = agent.partition(SEGMENT_SEPARATOR)
    return robot, int(seg) if seg else 0
