"""The map server takes keyframes of all robots in one time order, however they arrive.

Robots run at their own pace (separate processes, as fast as they can or in real time), so their
keyframes reach the server interleaved by chance; matching is incremental, so the interleaving would
change which closures are found when. ``KeyframeOrder`` holds each robot's keyframes in a queue and
releases them in the order of ``(seconds since the robot's first frame, reference robot first, name)``
— the order ``shgm-slam run`` steps its robots in — as soon as that order is certain: every other robot
the server waits for has either a later keyframe queued or reported progress (``HelloMessage.progress_s``,
or a keyframe) at least that far. A robot that is done, silent (stale) or not connected is not waited
for. So a distributed run gives the same result as ``shgm-slam run`` on the same sequences, and the
robots' start-up times and speeds do not change it.

Pure bookkeeping: the caller says which robots to wait for and how far each has got.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from shgm_slam.agents import agent_robot
from shgm_slam.messages import KeyframeMessage


@dataclass(frozen=True)
class Held:
    """One queued keyframe: its time key, the message and its payload (for the journal)."""

    key: tuple[float, int, str]
    msg: KeyframeMessage
    payload: bytes


class KeyframeOrder:
    """Per-robot queues of keyframes released in one global time order (see the module docstring)."""

    def __init__(self) -> None:
        self._queues: dict[str, deque[Held]] = {}
        self._held: dict[str, int] = {}  # agent -> keyframes queued

    def held(self, agent: str) -> int:
        """Keyframes of ``agent`` queued (not released yet)."""
        return self._held.get(agent, 0)

    def queued(self, robot: str) -> int:
        """Keyframes of ``robot`` (all its agents) queued."""
        return len(self._queues.get(robot, ()))

    def agents(self) -> list[str]:
        """Agents with keyframes queued."""
        return [a for a, n in self._held.items() if n]

    def __len__(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def offer(self, msg: KeyframeMessage, payload: bytes, start_s: float, rank: int) -> None:
        """Queue a keyframe (the caller checked it is the agent's next one, ``held`` included).

        Args:
            start_s: the timestamp of the sending robot's first frame (s).
            rank: ties at equal times go to the lower rank, then the robot name (0: the reference robot,
                1: the others).
        """
        robot = agent_robot(msg.robot)[0]
        key = (msg.timestamp_s - start_s, rank, robot)
        self._queues.setdefault(robot, deque()).append(Held(key, msg, payload))
        self._held[msg.robot] = self._held.get(msg.robot, 0) + 1

    def drop(self, robot: str) -> int:
        """Forget ``robot``'s queued keyframes (its process restarted: the new one sends them again).
        Returns how many were dropped."""
        q = self._queues.pop(robot, deque())
        for h in q:
            self._held[h.msg.robot] -= 1
        return len(q)

    def release(self, progress_s: dict[str, float | None]) -> list[Held]:
        """Pop every keyframe whose place in the global order is certain, in that order.

        Args:
            progress_s: robot -> seconds since its first frame up to which every keyframe it made has
                arrived (None: nothing yet; ``math.inf``: not waited for: done, silent or gone). Robots
                absent are not waited for.
        """
        out: list[Held] = []
        while True:
            heads = [(q[0].key, r) for r, q in self._queues.items() if q]
            if not heads:
                return out
            key, robot = min(heads)
            for other, p in progress_s.items():
                if other == robot or self._queues.get(other):
                    continue  # its queued head comes later (the head is the minimum)
                if p is None or p < key[0]:
                    return out  # it may still send a keyframe that comes first
            held = self._queues[robot].popleft()
            self._held[held.msg.robot] -= 1
            out.append(held)
