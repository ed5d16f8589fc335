"""Whether an agent's place in the shared frame is confirmed or still provisional (early-stop safeguard).

The pose graph anchors an agent to the shared frame once a robot pair's consistent closures come from
``backend.min_closures_to_anchor`` independent matches (default 2; with 1, its first accepted closure
anchors it). One graph match
can be wrong in a way no check of that match alone reveals (perceptual aliasing that fits the whole
overlap), and every closure cut from one match shares its error: together they are one piece of
evidence (``ClosureRecord.evidence``). A run stopped early would keep such a wrong place without a word,
so a placed agent stays **provisional** until its place rests on two independent pieces of evidence:

    among the accepted closures between the agent and one *confirmed* agent, one that comes from
    another graph match than some other accepted closure and rests on none of the objects (either
    agent's matched nodes) behind any closure of that match.

The map server records *all* of a match's partners as the objects behind each of its closures (the match was
verified as a whole; a closure's own share of its partners was never judged against chance), so "none of the
objects" compares matches: a re-match of a grown graph whose closure on a new stretch rests on new objects
still rests on the old ones too (per-closure objects let a street alias re-found by whole-graph matches of a
KITTI 02 fleet enter as two pieces, 566 m off).

Accepted closures of one robot pair form its maximum consistent set, so the confirming closure agrees
with the first match through both odometries; resting on other objects means the second match saw
other things (another keyframe stretch), not the same objects found again by a later match of the
growing graph (and closures cut from two such re-matches never confirm each other crosswise). Where the
pose graph tracks straight stretches (``backend/stretches.py``) the confirming closure must also lie on
another pair of straight stretches of the two agents: an aliased street keeps aliasing along its length. An agent
without two such matches with any one confirmed agent is also confirmed by one match with each of two
confirmed agents when they rest on different objects and straight stretches of its own trajectory and
agree on its place (``cross_evidence.py``: a short overlap with each of two robots). The
reference agent (whose frame is the shared frame) is confirmed by definition, and confirmation spreads
like anchoring: an agent is confirmed only through agents that are confirmed themselves. Loop closures
(two keyframes of one agent) never confirm a place. Nothing here is a tuned constant: the only
threshold is "two", the smallest number of pieces of evidence that can check each other.

A robot can also enter the shared frame through one *decisive* match (``backend.decisive_match``,
``MapServer._decisive``): one whose likelihood ratio alone is as far beyond chance as two pieces together. It
is still one piece of evidence, so its place is provisional here until an independent match confirms it.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from enum import Enum

from shgm_slam.backend.records import ClosureRecord, ClosureStatus

Support = Mapping[str, frozenset[int]]
"""The objects behind one closure: agent -> ids of its graph nodes among the closure's inliers."""


class Placement(str, Enum):
    """Where an agent stands with the shared frame."""

    REFERENCE = "reference"  # its frame is the shared frame
    CONFIRMED = "confirmed"  # placed, and two independent matches agree
    PROVISIONAL = "provisional"  # placed from a single piece of evidence: may be wrong, may move
    UNPLACED = "unplaced"  # not in the shared frame (yet)


@dataclass(frozen=True)
class AgentPlacement:
    """One agent's placement; ``partner`` is the placed agent its best evidence links it to (a confirmed
    one when there is one; None for the reference and unplaced agents), ``matches`` how many graph
    matches gave that evidence and ``partner_confirmed`` whether the partner is confirmed itself."""

    placement: Placement
    partner: str | None = None
    matches: int = 0
    keyframes: tuple[int, ...] = ()  # the agent's keyframes in those closures
    partner_confirmed: bool = True
    also: tuple[str, ...] = ()  # further partners whose independent matches agree (``cross_evidence``)
    decisive: bool = False  # a match with the partner carries the evidence of two alone (``backend.decisive_match``)

    @property
    def provisional(self) -> bool:
        return self.placement is Placement.PROVISIONAL


def confirms(
    closure: ClosureRecord,
    match: Sequence[ClosureRecord],
    support: Mapping[int, Support],
    stretches: Mapping[int, Hashable] | None = None,
) -> bool:
    """True when ``closure`` is evidence independent of another graph match's closures ``match``: it comes
    from a different match, rests on none of the objects (either agent's nodes) behind any of them and,
    when ``stretches`` (closure id -> the pair of straight stretches its keyframes lie on,
    ``backend/stretches.py``) is given, lies on another pair of stretches than each of them.

    Closures without recorded support count by their match alone. Closures that share a match with
    ``closure`` never confirm it, and neither do closures of a later match that found the same objects
    again (a re-match of the growing graph), however the two matches cut them into keyframe stretches.
    """
    if any(closure.evidence == c.evidence for c in match):
        return False
    stretches = stretches or {}
    mine_stretch = stretches.get(closure.closure_id)
    if mine_stretch is not None and any(stretches.get(c.closure_id) == mine_stretch for c in match):
        return False
    mine = support.get(closure.closure_id, {})
    for c in match:
        theirs = support.get(c.closure_id, {})
        if any(mine[agent] & theirs[agent] for agent in mine.keys() & theirs.keys()):
            return False
    return True


def _confirmed_pair(
    closures: list[ClosureRecord], support: Mapping[int, Support], stretches: Mapping[int, Hashable]
) -> bool:
    """Whether one of a robot pair's accepted ``closures`` confirms another graph match's (``confirms``).

    Through an index from each object to the matches whose closures rest on it (a bit mask over the
    matches): a closure confirms some match when the matches touching its objects, its own included,
    are fewer than all of them. Linear in the objects: for 500 closures of 100 matches that all share
    one object (never confirmed, the worst case) 25-35 ms, where testing every closure against every
    match with ``confirms`` took 0.7 s (a 2-core machine shared with other jobs).
    """
    bit = {e: 1 << i for i, e in enumerate(dict.fromkeys(c.evidence for c in closures))}
    if len(bit) < 2:
        return False
    every = (1 << len(bit)) - 1
    index: dict[Hashable, int] = {}

    def objects(c: ClosureRecord) -> Iterable[Hashable]:
        yield from ((agent, node) for agent, nodes in support.get(c.closure_id, {}).items() for node in nodes)
        if c.closure_id in stretches:
            yield stretches[c.closure_id]

    for c in closures:
        for obj in objects(c):
            index[obj] = index.get(obj, 0) | bit[c.evidence]
    for c in closures:
        touching = bit[c.evidence]
        for obj in objects(c):
            touching |= index[obj]
            if touching == every:
                break
        if touching != every:
            return True
    return False


def placements(
    agents: Iterable[str],
    reference: str,
    anchored: Iterable[str],
    closures: Sequence[ClosureRecord],
    support: Mapping[int, Support],
    stretches: Mapping[int, Hashable] | None = None,
    agreeing: Callable[[str, frozenset[str]], tuple[str, ...]] | None = None,
) -> dict[str, AgentPlacement]:
    """Each agent's placement (see the module docstring).

    Args:
        agents: every agent of the pose graph.
        reference: the agent whose frame is the shared frame.
        anchored: the agents whose keyframes are in the shared frame (``MultiRobotPoseGraph.is_anchored``).
        closures: the pose graph's closures with their current status (``MultiRobotPoseGraph.closures``).
        support: closure id -> the matched objects behind it (closures without an entry count by their
            match alone).
        stretches: closure id -> the pair of straight stretches it lies on (``MultiRobotPoseGraph.stretches``);
            closures on the same pair do not confirm each other. None: objects alone decide.
        agreeing: (agent, confirmed agents) -> two of those whose accepted closures with the agent are
            independent pieces of evidence that agree on its place (``MultiRobotPoseGraph.agreeing_partners``),
            () when none: an agent without two independent matches with any one confirmed agent is confirmed
            through two. None: within robot pairs only.

    Returns:
        agent -> ``AgentPlacement`` for every agent in ``agents``.
    """
    placed = set(anchored)
    by_pair: dict[frozenset[str], list[ClosureRecord]] = {}
    for c in closures:
        if c.status is ClosureStatus.ACCEPTED and c.robot_a != c.robot_b:
            by_pair.setdefault(frozenset((c.robot_a, c.robot_b)), []).append(c)
    confirmed = {reference} if reference in placed else set()
    across: dict[str, tuple[str, ...]] = {}  # agent -> the confirmed partners whose matches agree on it
    grown = True
    while grown:  # confirmation spreads through confirmed agents only
        grown = False
        for agent in sorted(placed - confirmed):
            for other in sorted(confirmed):
                if _confirmed_pair(by_pair.get(frozenset((agent, other)), []), support, stretches or {}):
                    confirmed.add(agent)
                    grown = True
                    break
            else:
                partners = agreeing(agent, frozenset(confirmed)) if agreeing is not None and len(confirmed) > 1 else ()
                if partners:
                    confirmed.add(agent)
                    across[agent] = partners
                    grown = True
    out = {}
    for agent in agents:
        if agent == reference and agent in placed:
            out[agent] = AgentPlacement(Placement.REFERENCE)
        elif agent not in placed:
            out[agent] = AgentPlacement(Placement.UNPLACED)
        else:
            state = Placement.CONFIRMED if agent in confirmed else Placement.PROVISIONAL
            out[agent] = _with_evidence(agent, state, by_pair, placed, confirmed)
            if agent in across:
                out[agent] = replace(out[agent], partner=across[agent][0], also=across[agent][1:])
    return out


def _with_evidence(
    agent: str,
    state: Placement,
    by_pair: dict[frozenset[str], list[ClosureRecord]],
    placed: set[str],
    confirmed: set[str],
) -> AgentPlacement:
    """``state`` with the placed partner whose accepted closures with ``agent`` come from the most matches
    (confirmed partners first)."""
    best: tuple[bool, int, str, list[ClosureRecord]] | None = None
    for other in sorted(placed - {agent}):
        cs = by_pair.get(frozenset((agent, other)), [])
        rank = (other in confirmed, len({c.evidence for c in cs}))
        if cs and (best is None or rank > best[:2]):
            best = (*rank, other, cs)
    if best is None:
        return AgentPlacement(state)
    partner_confirmed, n, other, cs = best
    kfs = sorted({c.kf_a if c.robot_a == agent else c.kf_b for c in cs})
    return AgentPlacement(state, other, n, tuple(kfs), partner_confirmed, decisive=any(c.decisive for c in cs))


def describe(agent: str, p: AgentPlacement, sharing: tuple[Sharing, ...] = ()) -> str:
    """One line for users: what ``agent``'s placement means (the log, the viewer, metrics, the summary).
    ``sharing``: for a provisional agent placed by several matches with one partner, what tied them into one piece
    of evidence (``MapServer.placement_note`` reads it from the pose graph); not given: "the same objects"."""
    if p.placement is Placement.REFERENCE:
        return f"{agent} defines the shared frame"
    if p.placement is Placement.UNPLACED:
        return f"{agent} is not placed in the shared frame"
    where = f" with {p.partner}" if p.partner else ""
    if p.keyframes:
        first, last = p.keyframes[0], p.keyframes[-1]
        where += f" (its keyframe{'s' if last > first else ''} {first}{f'-{last}' if last > first else ''})"
    if p.placement is Placement.CONFIRMED:
        if p.also:
            return (
                f"{agent} is confirmed in the shared frame: independent graph matches with "
                f"{' and '.join((p.partner or '', *p.also))} agree on its place"
            )
        return f"{agent} is confirmed in the shared frame: independent graph matches{where} agree"
    if not p.partner_confirmed:
        return (
            f"{agent} is placed provisionally: it was placed through graph matches{where}, and {p.partner} is "
            "provisional itself; it may be wrong and may still move until both are confirmed"
        )
    if p.matches <= 1:
        evidence = f"a single graph match{where}"
    elif sharing and sharing != (Sharing.OBJECTS,):
        tied = f"one piece of evidence (here: {_listed(sharing)} count once)"
        evidence = f"{p.matches} graph matches{where} that are {tied}"
    else:
        evidence = f"{p.matches} graph matches{where} that all found the same objects"
    if p.decisive:
        evidence += " (one of them alone as far beyond chance as two independent matches: backend.decisive_match)"
    other = "a match on other objects away from those straight stretches" if Sharing.STRETCHES in sharing else (
        "a match on other objects"
    )
    return (
        f"{agent} is placed provisionally: its place in the shared frame rests on {evidence}; "
        f"it may be wrong and may still move until {other} confirms it"
    )


class Sharing(str, Enum):
    """What makes two graph matches of one robot pair one piece of evidence (``describe_waiting``)."""

    OBJECTS = "matches that found the same objects"
    STRETCHES = "matches along the same straight stretches of both drives"
    CHANCE = "matches too close to chance for the number the pair has tried"


def _listed(sharing: tuple[Sharing, ...]) -> str:
    """The kinds in ``sharing`` as words, in ``Sharing``'s order: "a", "a and b", "a, b and c"."""
    kinds = [k.value for k in Sharing if k in sharing]
    return ", ".join(kinds[:-1]) + " and " + kinds[-1] if len(kinds) > 1 else kinds[0]


def describe_waiting(
    agent: str, partner: str, evidence: int, needed: int, matches: int, others: tuple[str, ...] = (),
    sharing: tuple[Sharing, ...] = (),
) -> str:  # fmt: skip
    """One line for users: why ``agent`` is not placed although ``matches`` graph matches with placed
    ``partner`` gave accepted closures: they are ``evidence`` independent pieces of evidence, fewer than the
    ``needed`` (``backend.min_closures_to_anchor``); ``sharing``: what tied these matches together (every kind
    listed when not given); ``others``: further placed robots with accepted matches, which did not make
    independent, agreeing pieces together with ``partner``'s (``cross_evidence``)."""
    pieces = "one piece of evidence" if evidence == 1 else f"{evidence} independent pieces of evidence"
    these = f"{matches} accepted graph match{'es' if matches != 1 else ''} with {partner}"
    verb = "are" if matches != 1 else "is"
    if matches == 1:
        why = ""
    elif sharing:
        why = f" (here: {_listed(sharing)} count once)"
    else:
        why = f" ({', '.join(k.value for k in Sharing)}, count once)"
    return (
        f"{agent} is not placed in the shared frame: its {these} {verb} {pieces}{why}, and a robot "
        f"enters it once {needed} independent matches agree (backend.min_closures_to_anchor; 1 trusts single "
        "matches and reports them provisional) or one match carries their evidence alone (backend.decisive_match)"
    ) + (
        f"; its accepted matches with {', '.join(others)} do not count as another piece: they lie on the same "
        "straight stretch of its drive, rest on the same objects or disagree on its place"
        if others
        else ""
    )
