"""GTSAM keys of robot keyframes: one symbol letter per robot, the keyframe index as the symbol index.

Robot ``i`` (its position in the robot list) gets letter ``ROBOT_LETTERS[i]``: 'a', 'b', ... 'z', then
'A' ... 'Z' (52 robots at most). Keys are ``gtsam.symbol(letter, kf_index)``, so the pose graph, its
g2o export and gtsam's printouts all read ``a0, a1, b0 ...``.
"""

from __future__ import annotations

import string

import gtsam

from shgm_slam.errors import BackendError

ROBOT_LETTERS = string.ascii_lowercase + string.ascii_uppercase
MAX_AGENTS = len(ROBOT_LETTERS)
"""Agents the pose graph holds: robots and their later trajectory segments (after odometry failures)."""
MAX_KEYFRAMES = 1 << 56
"""gtsam symbols keep 56 bits for the index."""


def segments_per_robot(num_robots: int) -> int:
    """Trajectory segments each of ``num_robots`` robots may have so that all fit the pose graph's
    ``MAX_AGENTS`` together (at least 1 for ``num_robots <= MAX_AGENTS``)."""
    return MAX_AGENTS // max(num_robots, 1)


def robot_letter(robot_index: int) -> str:
    """Symbol letter of robot ``robot_index`` (0 -> 'a')."""
    if not 0 <= robot_index < len(ROBOT_LETTERS):
        raise BackendError(
            f"robot index {robot_index} has no key letter: at most {len(ROBOT_LETTERS)} robots are supported"
        )
    return ROBOT_LETTERS[robot_index]


def key(robot_index: int, kf_index: int) -> int:
    """gtsam key of keyframe ``kf_index`` of robot ``robot_index``."""
    if not 0 <= kf_index < MAX_KEYFRAMES:
        raise BackendError(f"keyframe index {kf_index} is out of range for a gtsam symbol")
    return int(gtsam.symbol(robot_letter(robot_index), kf_index))


def decode(k: int) -> tuple[int, int]:
    """Inverse of ``key``: (robot_index, kf_index). BackendError for keys no robot owns."""
    letter = chr(gtsam.symbolChr(k))
    idx = ROBOT_LETTERS.find(letter)
    if idx < 0 or not letter:
        raise BackendError(f"key {k} ({gtsam.Symbol(k).string()}) is not a robot keyframe key")
    return idx, int(gtsam.symbolIndex(k))


class RobotKeys:
    """Robot names <-> indices <-> gtsam keys for an ordered list of robots (agents), which may grow
    at run time (``add``: e.g. a robot's new trajectory segment after an odometry failure)."""

    def __init__(self, robot_names: list[str]) -> None:
        names = list(robot_names)
        if not names:
            raise BackendError("the pose graph needs at least one robot name")
        if len(set(names)) != len(names):
            raise BackendError(f"robot names must be unique, got {names}")
        robot_letter(len(names) - 1)  # raises when there are too many robots
        self.names = names
        self._index = {n: i for i, n in enumerate(names)}

    def add(self, robot: str) -> int:
        """Append a new agent; returns its index.

        Raises:
            BackendError: the name is taken, or all 52 key letters are in use.
        """
        if robot in self._index:
            raise BackendError(f"robot {robot!r} is already in the pose graph")
        if len(self.names) >= MAX_AGENTS:
            raise BackendError(
                f"cannot add {robot!r}: the pose graph holds at most {MAX_AGENTS} agents (robots and "
                "their trajectory segments after odometry failures); use fewer robots or fix the odometry"
            )
        self._index[robot] = len(self.names)
        self.names.append(robot)
        return self._index[robot]

    def __len__(self) -> int:
        return len(self.names)

    def index(self, robot: str) -> int:
        """Position of ``robot`` in the robot list; BackendError for unknown names."""
        try:
            return self._index[robot]
        except KeyError:
            raise BackendError(f"unknown robot {robot!r}; the pose graph knows {self.names}") from None

    def key(self, robot: str, kf_index: int) -> int:
        """gtsam key of ``robot``'s keyframe ``kf_index``."""
        return key(self.index(robot), kf_index)

    def decode(self, k: int) -> tuple[str, int]:
        """(robot name, kf_index) of a key."""
        i, kf = decode(k)
        if i >= len(self.names):
            raise BackendError(f"key {gtsam.Symbol(k).string()} belongs to no robot of {self.names}")
        return self.names[i], kf
