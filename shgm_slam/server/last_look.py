"""The last look for a second, independent match (``MapServer._independent_match``): which objects an
agent's look leaves out, and what came of each look (the run's summary lines)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

from shgm_slam.backend.confirmation import Placement, Support
from shgm_slam.backend.records import ClosureRecord, ClosureStatus
from shgm_slam.server.records import MatchRecord

LAST_LOOK_QUERY = "independent"
"""``MatchRecord.query`` of the last look for a second, independent match (``MapServer._independent_match``)."""

PARTNER_LOOK_QUERY = "independent-partner"
"""``MatchRecord.query`` of the same last look from the partner's side (the partner's graph as the query, robot_a
the waiting agent): versions before 2026-12-05 took it (a resumed server's match log may hold one); this one does
not (``MapServer._independent_match``)."""


def smallest_matches(
    agent: str, closures: Iterable[ClosureRecord], support: Mapping[int, Support]
) -> dict[str, dict[str, set[int]]]:
    """For every partner of ``agent``'s accepted inter-robot closures, the objects of its smallest graph match
    with that partner: what the last look leaves out.

    Args:
        agent: the agent looking.
        closures: the pose graph's closures (``MultiRobotPoseGraph.closures``).
        support: closure id -> agent -> the node ids behind it (``MapServer._support``).

    Returns:
        partner -> {agent: node ids, partner: node ids} of the match with the fewest objects (ties: the lower
        match), partners in that order.
    """
    objects: dict[tuple[str, int], dict[str, set[int]]] = {}  # (partner, match id) -> agent -> node ids
    for c in closures:
        if c.status is not ClosureStatus.ACCEPTED or c.robot_a == c.robot_b or agent not in (c.robot_a, c.robot_b):
            continue
        partner = c.robot_b if c.robot_a == agent else c.robot_a
        ids = objects.setdefault((partner, c.evidence[1]), {agent: set(), partner: set()})
        for a, nodes in support.get(c.closure_id, {}).items():
            ids[a] |= set(nodes)
    smallest: dict[str, dict[str, set[int]]] = {}  # partner -> the objects of its smallest match with agent
    for (partner, _), ids in sorted(objects.items(), key=lambda kv: (sum(map(len, kv[1].values())), kv[0])):
        smallest.setdefault(partner, ids)
    return smallest


def still_accepted(record: MatchRecord, closures: Iterable[ClosureRecord]) -> bool:
    """True when a closure that ``record`` added is in its pair's consistent set now (``closures``: the pose
    graph's, ``MultiRobotPoseGraph.closures``)."""
    added = {(record.robot_a, c["keyframe_a"], record.robot_b, c["keyframe_b"]) for c in record.closures
             if c.get("accepted")}  # fmt: skip
    return any(
        c.status is ClosureStatus.ACCEPTED
        and ((c.robot_a, c.kf_a, c.robot_b, c.kf_b) in added or (c.robot_b, c.kf_b, c.robot_a, c.kf_a) in added)
        for c in closures
    )


def last_look_lines(
    matches: Iterable[MatchRecord], placement: Callable[[str], Placement], accepted_now: Callable[[MatchRecord], bool]
) -> list[str]:
    """One line per last look in ``matches`` (the match log): whose, with whom, and what came of it (confirmed,
    provisional, outvoted, or why the match was rejected).

    Args:
        matches: every match attempt so far, in order.
        placement: agent -> its placement now (asked only for accepted looks).
        accepted_now: whether an accepted look's closures are still accepted (``still_accepted``; asked only
            when the agent is neither confirmed nor provisional).
    """
    lines = []
    for m in matches:
        if m.query not in (LAST_LOOK_QUERY, PARTNER_LOOK_QUERY):
            continue
        agent, partner = (m.robot_b, m.robot_a) if m.query == LAST_LOOK_QUERY else (m.robot_a, m.robot_b)
        if m.accepted:
            what = {
                Placement.CONFIRMED: "agreed: it is confirmed in the shared frame",
                Placement.PROVISIONAL: "was accepted; it is still provisional",
            }.get(placement(agent), "")
            what = what or (
                "agrees with its earlier matches but is not a second, independent piece of evidence (the "
                "reason under the robot's warning)"
                if accepted_now(m)
                else "was accepted, but outvoted"
            )
        else:
            what = f"did not confirm it: {m.reason}"
        look = f"a last look with {partner}" if m.query == LAST_LOOK_QUERY else f"{partner}'s last look at it"
        lines.append(f"{agent}: {look}, without the objects behind its accepted match, {what}")
    return lines
