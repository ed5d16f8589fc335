"""What a server node received and sent, by message kind and robot, and what it refused (``server.json``'s
``traffic``)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class TrafficStats:
    """Bytes and messages the server received, by kind, and what it refused."""

    bytes_by_kind: dict[str, int] = field(default_factory=dict)
    count_by_kind: dict[str, int] = field(default_factory=dict)
    bytes_by_robot: dict[str, int] = field(default_factory=dict)  # everything a robot sent
    sent_by_kind: dict[str, int] = field(default_factory=dict)  # what the server sent (corrections, status)
    sent_by_robot: dict[str, int] = field(default_factory=dict)  # corrections sent to each robot
    refused: int = 0
    refusal_reasons: list[str] = field(default_factory=list)

    def add(self, kind: str, size: int, robot: str) -> None:
        """Count one received message of ``kind`` (``size`` bytes) from ``robot``."""
        self.bytes_by_kind[kind] = self.bytes_by_kind.get(kind, 0) + size
        self.count_by_kind[kind] = self.count_by_kind.get(kind, 0) + 1
        self.bytes_by_robot[robot] = self.bytes_by_robot.get(robot, 0) + size

    def sent(self, kind: str, size: int, robot: str | None = None) -> None:
        """Count one sent message of ``kind`` (``size`` bytes), to ``robot`` (None: to every robot)."""
        self.sent_by_kind[kind] = self.sent_by_kind.get(kind, 0) + size
        if robot is not None:
            self.sent_by_robot[robot] = self.sent_by_robot.get(robot, 0) + size

    def refuse(self, reason: str) -> None:
        """Count one refused message; the first 50 reasons are kept."""
        self.refused += 1
        if len(self.refusal_reasons) < 50:
            self.refusal_reasons.append(reason)

    def to_json_dict(self) -> dict:
        """The counts as ``server.json``'s ``traffic`` (bytes per keyframe None before the first)."""
        kf_n = self.count_by_kind.get("keyframe", 0)
        return {
            "bytes_by_kind": dict(self.bytes_by_kind),
            "messages_by_kind": dict(self.count_by_kind),
            "bytes_by_robot": dict(self.bytes_by_robot),
            "bytes_sent_by_kind": dict(self.sent_by_kind),
            "bytes_sent_by_robot": dict(self.sent_by_robot),
            "bytes_per_keyframe": self.bytes_by_kind.get("keyframe", 0) / kf_n if kf_n else None,
            "refused": self.refused,
            "refusal_reasons": list(self.refusal_reasons),
        }
