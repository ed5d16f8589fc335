"""Placement notices: each change of an agent's place in the shared frame reported once, at its level."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.confirmation import AgentPlacement, Placement, describe
from shgm_slam.server.placement import PlacementWatch, describe_drift


class _Server:
    """The part of a map server the watch reads: agents, their placements (and a provisional one's line) and
    measured drifts."""

    def __init__(self) -> None:
        self.agents = ["car1", "car2"]
        self.places = {"car1": AgentPlacement(Placement.REFERENCE), "car2": AgentPlacement(Placement.UNPLACED)}
        self.drift: dict[str, float | None] = {"car1": None, "car2": None}

    def placement(self, agent: str) -> AgentPlacement:
        return self.places[agent]

    def placement_note(self, agent: str) -> str | None:
        return describe(agent, self.places[agent]) if self.places[agent].provisional else None

    def measured_drift(self, agent: str) -> float | None:
        return self.drift[agent]


def test_each_change_is_reported_once_and_the_reference_never() -> None:
    server, watch = _Server(), PlacementWatch()
    assert watch.changes(server) == []  # the reference and an unplaced agent: nothing to say
    server.places["car2"] = AgentPlacement(Placement.PROVISIONAL, partner="car1", matches=1, keyframes=(4, 9))
    ((level, text),) = watch.changes(server)
    assert level == "WARN" and text.startswith("car2") and "car1" in text
    assert watch.changes(server) == []  # said once
    server.places["car2"] = AgentPlacement(Placement.CONFIRMED, partner="car1", matches=3, keyframes=(4, 30))
    assert [lvl for lvl, _ in watch.changes(server)] == ["INFO"]
    server.places["car2"] = AgentPlacement(Placement.UNPLACED)
    assert watch.changes(server) == [("WARN", "car2 left the shared frame: the closures that placed it were outvoted")]


def test_a_measured_drift_is_reported_when_it_changes_and_when_it_goes() -> None:
    server, watch = _Server(), PlacementWatch()
    watch.changes(server)
    server.drift["car1"] = np.radians(1.5) / 100.0  # 1.5 deg per 100 m
    ((level, text),) = watch.changes(server)
    assert level == "INFO" and "1.5 deg per 100 m" in text and text == describe_drift("car1", server.drift["car1"])
    assert watch.changes(server) == []
    server.drift["car1"] = None
    assert watch.changes(server) == [("INFO", describe_drift("car1", None))]
    assert "no longer" in describe_drift("car1", None)
