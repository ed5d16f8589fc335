"""Placement notices: lines for the log and the viewer when agents join the shared frame provisionally,
get confirmed, or lose their place (``backend.confirmation``)."""

from __future__ import annotations

from shgm_slam.backend.confirmation import Placement, describe
from shgm_slam.server.map_server import MapServer


class PlacementWatch:
    """Remembers each agent's last placement and reports the changes since the previous call."""

    def __init__(self) -> None:
        self._last: dict[str, Placement] = {}

    def changes(self, server: MapServer) -> list[tuple[str, str]]:
        """``(level, text)`` per agent whose placement changed: WARN when it became provisional or lost its
        place, INFO when it was confirmed (the reference is never reported)."""
        out = []
        for agent in server.agents:
            p = server.placement(agent)
            before = self._last.get(agent, Placement.UNPLACED)
            if p.placement is before:
                continue
            self._last[agent] = p.placement
            if p.placement is Placement.REFERENCE:
                continue
            if p.placement is Placement.UNPLACED:
                out.append(("WARN", f"{agent} left the shared frame: the closures that placed it were outvoted"))
            else:
                out.append(("INFO" if p.placement is Placement.CONFIRMED else "WARN", describe(agent, p)))
        return out
