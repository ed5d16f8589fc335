"""Straight stretches of a trajectory: which keyframes were driven along one street.

Two graph matches between the same robots count as independent evidence only when they rest on
different objects (``consistency.independent_sources``). On a street lined with regularly spaced trees,
lamps and parked cars that is not enough: a street that aliases onto another one keeps aliasing as both
robots drive on, so the next submap match finds *new* objects under the *same* wrong transform and
"confirms" it (airsim-like tuning seed 14 with objects placed at their centres: car1's straight street
merged 413 m off onto car2's, then confirmed 97 m further along the same street, both found by car1's
submap queries). So matches found on the same straight stretch of each robot's trajectory count once: each
closure also rests on a pseudo-object, (one robot, its stretch, the other, its stretch) (``stretch_token``), and
matches that share it are not independent, whichever robot's query found them. Evidence from around a corner
(either robot turned between the two matches) still is.

The token used to be per querying robot (a match the partner's own query found, on its recent submap, counted as
other evidence). Report world airsim-like 569 showed why it must not: car1 and car2 drove one long straight street
in opposite directions, and car2's submap query and car1's found the same alias 405-434 m along it, on disjoint
objects, seven keyframes apart: two "independent" pieces that placed car2 310 m off for most of the run. An
aliased street aliases whoever queries. In November the symmetric token had lost four of 19 right placements on
the airsim-like files tuning worlds 10-19 (car2s and a UAV whose only overlap with car1 is one straight street);
with the decisive match (``backend.decisive_match``) and the vote that counts it as two pieces, replayed on tuning
worlds 10-14 (all scenarios) and airsim-like 15-19, it lost none: every robot placed right as before, one car
provisional instead of confirmed (airsim-like 14's car2, placed by a decisive match on one straight street).

A stretch ends where the direction of travel, measured over ``HEADING_BASE_M`` of path, has turned more
than ``turn_rad`` from the direction the stretch started with (a 90° corner starts two or three new
stretches, a slow curve one every ``turn_rad`` of heading). Directions are 3-D (no up axis needed), so a
stretch id is a pure function of the keyframe poses up to it: a restored pose graph recomputes the same ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HEADING_BASE_M = 10.0
"""Path length over which the direction of travel is measured (metres; several keyframes, so the
odometry's step-to-step jitter does not start stretches)."""

STANDING_FRACTION = 0.5
"""A keyframe whose straight-line displacement over the base is below this fraction of the path driven
(turning on the spot, hovering, reversing) keeps the current stretch."""


@dataclass
class StretchTracker:
    """Stretch id of each keyframe of one robot, assigned as keyframes arrive (never changed later).

    Attributes:
        turn_rad: heading change that ends a stretch, radians (``BackendConfig.stretch_turn_deg``).
        ids: (K,) stretch id per keyframe so far (0, 1, 2, ... non-decreasing).
    """

    turn_rad: float
    ids: list[int] = field(default_factory=list)
    _current: int = 0
    _ref: np.ndarray | None = None  # (3,) unit direction the current stretch started with

    def append(self, positions_xyz: np.ndarray, path_m: np.ndarray) -> int:
        """Assign the newest keyframe its stretch id and return it.

        Args:
            positions_xyz: (K, 3) keyframe positions in the robot's odometry frame, metres; the last row is
                the new keyframe and the first K-1 rows are the keyframes assigned so far.
            path_m: (K,) odometry path length at each keyframe, metres (non-decreasing).
        """
        k = len(self.ids)
        if positions_xyz.shape[0] != k + 1 or path_m.shape[0] != k + 1:
            raise ValueError(f"stretch tracker holds {k} keyframes, got {positions_xyz.shape[0]} positions")
        j = int(np.searchsorted(path_m, path_m[k] - HEADING_BASE_M, side="right")) - 1
        if j >= 0 and path_m[k] - path_m[j] >= HEADING_BASE_M:
            d = positions_xyz[k] - positions_xyz[j]
            norm = float(np.linalg.norm(d))
            if norm >= STANDING_FRACTION * (path_m[k] - path_m[j]):
                u = d / norm
                if self._ref is None:
                    self._ref = u
                elif float(np.arccos(np.clip(u @ self._ref, -1.0, 1.0))) > self.turn_rad:
                    self._current += 1
                    self._ref = u
        self.ids.append(self._current)
        return self._current


def stretch_token(robot_a: str, stretch_a: int, robot_b: str, stretch_b: int) -> tuple[str, str, int, str, int]:
    """The pseudo-object a closure rests on (with its matched objects) when it joins ``robot_a``'s keyframe on
    stretch ``stretch_a`` and ``robot_b``'s on ``stretch_b``: closures that share it lie along one street of each
    robot and are not independent evidence. The same for either order of the two robots (and so for either
    robot's query)."""
    (r1, s1), (r2, s2) = sorted([(robot_a, int(stretch_a)), (robot_b, int(stretch_b))])
    return ("stretch", r1, s1, r2, s2)


def is_stretch_token(item: object) -> bool:
    """True when ``item`` is a pseudo-object ``stretch_token`` made (not a matched object)."""
    return isinstance(item, tuple) and len(item) == 5 and item[0] == "stretch"
