"""Query planning: which keyframes of a robot each kind of match query holds, and when a placed pair's
matching turns from whole graphs to windows near where the fused estimate puts them.

A match round of robot r (``MapServer.match_robot``) matches r's recent submap and whole graph against every
other robot's graph until the two are placed and confirmed (``CONFIRMING_MATCHES``); from then on r's submap
and r's recent window (``recent_window``, query ``"window"``) are matched against the other's nodes near them
(``places.rows_near``), and one of r's older windows that no closure ties yet in turn (``unclosed_window``,
query ``"backfill"``). The loop-closure query leaves the stretch r just drove out of r's older graph
(``loop_exclusion_m``, ``loop_cutoff``). Pure functions of keyframe counts and path lengths.
"""

from __future__ import annotations

import numpy as np

WINDOW_QUERY = "window"
"""``MatchRecord.query`` of a confirmed pair's re-match over the querying robot's recent window."""

RECENT_WINDOW_SUBMAPS = 2
"""Length of that window in submaps (``backend.submap_keyframes`` each): the querying robot's newest keyframes'
nodes against the partner's nodes near them in the fused estimate. Once two robots are placed, matching their
whole graphs again found one rigid transform for hundreds of metres of both robots' drift: exact near the
middle of its inliers, and metres off along the street at its ends, where the cut closures paired each object
with its neighbour and kept the error (RGB only, synthia-like tuning worlds: closures 5-13 m off at the newest
end outvoted later right ones, the backward camera ending 12-14 m off). A window twice a submap still holds
more evidence than a submap (whose likelihood ratios mostly stay below the threshold on a network's depth)
and spans little drift: on the RGB tuning seeds 10-19 (replayed journals) the backward cameras placed wrong
went from 5 of 10 to 1 (on seeds 10-14 three submaps also left none wrong, five one: two is the shorter);
the files-depth tuning worlds 10-29 kept the same robots right (placements 0.05 m from before on average)."""

BACKFILL_QUERY = "backfill"
"""``MatchRecord.query`` of a placed pair's re-match over an older window of the querying robot that no closure
ties yet (``MapServer._unclosed_window``): the recent window never returns to what a robot drove before it was
placed, which whole-graph re-matches used to reach."""

CONFIRMING_MATCHES = 2
"""Independent graph matches (on mutually disjoint objects, ``MultiRobotPoseGraph.evidence_between``) behind a
placed robot pair's accepted closures before its submaps are matched only near where the fused estimate puts
them (one match may be a wrong placement: global matching goes on)."""


def recent_window(n_kf: int, submap_keyframes: int) -> np.ndarray:
    """A robot's newest ``RECENT_WINDOW_SUBMAPS`` submaps of keyframes (indices).

    Args:
        n_kf: keyframes the robot has; submap_keyframes: keyframes per submap (``backend.submap_keyframes``).

    Returns:
        (W,) int keyframe indices, W <= ``RECENT_WINDOW_SUBMAPS * submap_keyframes``.
    """
    return np.arange(max(0, n_kf - RECENT_WINDOW_SUBMAPS * submap_keyframes), n_kf)


def unclosed_window(
    n_kf: int, submap_keyframes: int, match_every_keyframes: int, closed: np.ndarray
) -> np.ndarray | None:
    """One older window of a robot's keyframes (indices) that no closure ties yet, or None: its keyframes
    cut into windows as long as the recent one, those wholly before it that hold no closure keyframe,
    taken in turn (the robot's match round picks which), so each is tried again as the maps grow.

    Args:
        n_kf: keyframes the robot has; submap_keyframes: keyframes per submap (``backend.submap_keyframes``).
        match_every_keyframes: keyframes between the robot's match rounds (``backend.match_every_keyframes``).
        closed: (C,) sorted keyframe indices a closure ties (``MultiRobotPoseGraph.closure_keyframes``).

    Returns:
        (W,) int keyframe indices (W = ``RECENT_WINDOW_SUBMAPS * submap_keyframes``), or None.
    """
    w = RECENT_WINDOW_SUBMAPS * submap_keyframes
    starts = np.arange(0, n_kf - 2 * w + 1, w)
    if starts.size == 0:
        return None
    open_ = starts[np.searchsorted(closed, starts) == np.searchsorted(closed, starts + w)]
    if open_.size == 0:
        return None
    start = open_[(n_kf // match_every_keyframes) % open_.size]
    return np.arange(start, start + w)


def loop_exclusion_m(object_range_m: float | None, max_depth_m: float) -> float:
    """Metres of path before its submap whose keyframes a robot's loop query leaves out of its older graph:
    twice the robot's object range (``MapServer.object_range_m``, metres; the fleet's extraction depth
    ``max_depth_m`` until the graph has nodes)."""
    return 2.0 * (float(max_depth_m) if object_range_m is None else object_range_m)


def loop_cutoff(path_m: np.ndarray, submap_keyframes: int, exclusion_m: float) -> int:
    """First keyframe of the stretch a robot's loop query leaves out of its older graph: the submap (its newest
    ``submap_keyframes``), the ``submap_keyframes`` before it, and every keyframe within ``exclusion_m`` metres
    of path before it. The older graph is the nodes first seen from keyframes before it (none when <= 0).

    Args:
        path_m: (K,) cumulative odometry path length at each of the robot's keyframes, metres (K > submap).
        submap_keyframes: keyframes per submap; exclusion_m: ``loop_exclusion_m``.
    """
    first = len(path_m) - submap_keyframes  # the submap's first keyframe
    path = np.asarray(path_m)
    return min(first - submap_keyframes, int(np.searchsorted(path, path[first] - exclusion_m, "right")))
