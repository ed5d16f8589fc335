"""Placement notices: lines for the log and the viewer when agents join the shared frame provisionally,
get confirmed, or lose their place (``backend.confirmation``), and when an agent's loop closures change
the odometry heading drift the pose graph weighs its odometry with (``backend/drift.py``)."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.confirmation import Placement, describe
from shgm_slam.server.map_server import MapServer


class PlacementWatch:
    """Remembers each agent's last placement and reports the changes since the previous call."""

    def __init__(self) -> None:
        self._last: dict[str, Placement] = {}
        self._drift: dict[str, float | None] = {}

    def changes(self, server: MapServer) -> list[tuple[str, str]]:
        """``(level, text)`` per agent whose placement changed: WARN when it became provisional or lost its
        place, INFO when it was confirmed (the reference is never reported); and INFO per agent whose loop
        closures changed the odometry heading drift its odometry factors use (``backend/drift.py``)."""
        out = []
        for agent in server.agents:
            drift = server.measured_drift(agent)
            if drift != self._drift.get(agent):
                self._drift[agent] = drift
                out.append(("INFO", describe_drift(agent, drift)))
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
                confirmed = p.placement is Placement.CONFIRMED
                note = None if confirmed else server.placement_note(agent)  # names what tied its matches
                out.append(("INFO" if confirmed else "WARN", note or describe(agent, p)))
        return out


def describe_drift(agent: str, drift_rad_per_m: float | None) -> str:
    """One line on the odometry heading drift ``agent``'s loop closures measured (None: back to the prior)."""
    if drift_rad_per_m is None:
        return f"{agent}: its loop closures no longer measure more odometry heading drift than the prior"
    return (
        f"{agent}: its loop closures measure an odometry heading drift of {np.degrees(drift_rad_per_m) * 100:.1f} "
        "deg per 100 m, more than the pose graph's prior: its odometry now weighs that much less against closures"
    )
