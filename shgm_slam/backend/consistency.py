"""Pairwise consistency of inter-robot closures and their maximum consistent set (PCM-style).

Two closures between the same robots, ``T_ai_bj`` (keyframe i of robot a to keyframe j of b) and
``T_ak_bl``, are consistent when the loop they close with both robots' odometry is near identity:

    E = T_ai_bj · T_bj_bl · T_bl_ak · T_ak_ai ≈ I,   T_bj_bl, T_ak_ai from odometry, T_bl_ak = T_ak_bl⁻¹.

The tolerances grow with the odometry distance inside the loop (drift). Correct closures agree with
each other; wrong ones (perceptual aliasing) agree with nothing in particular, so the largest
mutually consistent subset (a maximum clique of the consistency graph) is kept. "Largest" counts
independent evidence first: the closures one graph match is cut into (one per stretch of overlap) agree
with each other by construction, so a set counts its *sources* (matches) before its closures; otherwise
one wrong match over a long stretch of an aliased street outvotes an earlier, independent right one
(airsim-like RGB tuning seed 16: car2 merged 193 m off). Matches are independent only when they rest on
different objects (``independent_sources``): the matches of consecutive steps that find the same aliased
trees, lamps and cars again agree with each other by construction too (synthia-like RGB tuning seed 10:
four submap matches 31 m off, each sharing 23-52 objects with the others), so a set counts the largest
group of its matches whose objects are mutually disjoint (greedy, and exact for two), not its distinct
matches. The objects may include pseudo-objects: the pose graph adds the pair of straight stretches a
closure lies on (``backend/stretches.py``), so one robot's matches along one street pair count once.
A *decisive* match (alone as far beyond chance as the matches a robot needs to enter the shared frame,
``backend.decisive_match``) counts as that many pieces of evidence here too, as it does for anchoring:
every right match of a pair re-finds the same true objects, so without it a set of right matches counted
one piece however strong they were, and two alias matches on disjoint objects kept a robot 310 m off
against a final look at the whole overlap with 141 partners and a likelihood ratio three times its
threshold (airsim-like files, seed 569).

The set is maintained incrementally per robot pair (``PairConsistency``): a new closure is tested
against the pair's other closures only (O(n)); it joins the current set when it agrees with all of it,
and only when it agrees with at least as many closures as the set holds can a larger set containing it
exist, which a bounded branch-and-bound search (degree peeling, greedy start, ``INCREMENTAL_BUDGET``)
decides. A pair keeps at most ``MAX_CLOSURES_PER_PAIR`` voting closures.

Loop closures of one robot (a = b) use the same test with both odometries the robot's own; each must
first agree with that odometry alone (``consistent_with_odometry``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.errors import BackendError
from shgm_slam.geometry.se3 import inverse, rotation_angle

CLIQUE_BUDGET = 1_000_000
"""Work (vertices scanned for pivots) of a full branch-and-bound search (``max_consistent_set``, about
0.3 s) before it settles for the best set found so far (a greedy clique improved by local swaps, or
better)."""

INCREMENTAL_BUDGET = 30_000
"""Work of the bounded search ``PairConsistency.add`` runs when a new closure may start a larger
consistent set than the current one (tens of milliseconds at most)."""

MAX_CLOSURES_PER_PAIR = 500
"""Closures of one robot pair that take part in the consistency vote (``PairConsistency``)."""


@dataclass(frozen=True)
class ConsistencyThresholds:
    """Loop-error tolerances: ``trans_m + trans_per_m·d`` metres, ``rot_deg + rot_deg_per_m·d`` degrees.

    ``d`` is the odometry path length inside the loop (both robots, metres).
    """

    trans_m: float = 5.0
    rot_deg: float = 10.0
    trans_per_m: float = 0.05
    rot_deg_per_m: float = 0.05


def loop_errors(
    T_ai_bj: np.ndarray,
    T_ak_bl: np.ndarray,
    T_ak_ai: np.ndarray,
    T_bj_bl: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) error of the loop closed by two closures and odometry.

    Args:
        T_ai_bj: (4, 4) first closure.
        T_ak_bl: (M, 4, 4) second closures.
        T_ak_ai: (M, 4, 4) odometry of robot a from keyframe i to k (``inv(T_odom_ak) @ T_odom_ai``).
        T_bj_bl: (M, 4, 4) odometry of robot b from keyframe j to l (``inv(T_odom_bj) @ T_odom_bl``).

    Returns:
        trans_m (M,), rot_deg (M,) of ``E = T_ai_bj · T_bj_bl · T_ak_bl⁻¹ · T_ak_ai``.
    """
    E = np.asarray(T_ai_bj, dtype=np.float64) @ T_bj_bl @ inverse(T_ak_bl) @ T_ak_ai
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E))


def consistent_with(
    T_ai_bj: np.ndarray,
    kf_a: int,
    kf_b: int,
    others_T_a_b: np.ndarray,
    others_kf_a: np.ndarray,
    others_kf_b: np.ndarray,
    T_odom_a: np.ndarray,
    T_odom_b: np.ndarray,
    path_a_m: np.ndarray,
    path_b_m: np.ndarray,
    thresholds: ConsistencyThresholds,
) -> np.ndarray:
    """Which of M earlier closures between robots a and b agree with a new closure.

    Args:
        T_ai_bj: (4, 4) new closure from b's keyframe ``kf_b`` into a's keyframe ``kf_a``.
        others_T_a_b: (M, 4, 4) earlier closures ``T_ak_bl``; others_kf_a, others_kf_b: (M,) their k, l.
        T_odom_a, T_odom_b: (Ka, 4, 4), (Kb, 4, 4) keyframe poses in each robot's odometry frame.
        path_a_m, path_b_m: (Ka,), (Kb,) cumulative odometry path length at each keyframe, metres.
        thresholds: loop-error tolerances.

    Returns:
        (M,) bool, True where the loop error is within the distance-dependent tolerance.
    """
    k = np.asarray(others_kf_a, dtype=np.int64)
    l = np.asarray(others_kf_b, dtype=np.int64)
    if k.size == 0:
        return np.zeros(0, dtype=bool)
    T_ak_ai = inverse(T_odom_a[k]) @ T_odom_a[kf_a]
    T_bj_bl = inverse(T_odom_b[kf_b]) @ T_odom_b[l]
    trans_m, rot_deg = loop_errors(T_ai_bj, np.asarray(others_T_a_b, dtype=np.float64), T_ak_ai, T_bj_bl)
    d = np.abs(path_a_m[k] - path_a_m[kf_a]) + np.abs(path_b_m[l] - path_b_m[kf_b])
    return (trans_m <= thresholds.trans_m + thresholds.trans_per_m * d) & (
        rot_deg <= thresholds.rot_deg + thresholds.rot_deg_per_m * d
    )


def consistent_with_odometry(
    T_ai_aj: np.ndarray,
    kf_i: int,
    kf_j: int,
    T_odom: np.ndarray,
    path_m: np.ndarray,
    thresholds: ConsistencyThresholds,
) -> tuple[bool, float, float]:
    """Whether a loop closure of one robot agrees with that robot's own odometry between its keyframes.

    The odometry itself is the first "closure" a loop closure must be consistent with: the loop
    ``E = T_ai_aj · T_aj_ai(odometry)`` has the tolerance of a loop of ``d = |path_j - path_i|`` metres
    (``ConsistencyThresholds``), the drift the odometry may have accumulated between the two keyframes.

    Args:
        T_ai_aj: (4, 4) the closure: keyframe j's camera frame -> keyframe i's.
        kf_i, kf_j: its two keyframes.
        T_odom: (K, 4, 4) the robot's keyframe poses in its odometry frame.
        path_m: (K,) cumulative odometry path length at each keyframe, metres.
        thresholds: loop-error tolerances.

    Returns:
        (agrees, translation error m, rotation error deg).
    """
    T_aj_ai = inverse(T_odom[kf_j]) @ T_odom[kf_i]
    E = np.asarray(T_ai_aj, dtype=np.float64) @ T_aj_ai
    trans_m = float(np.linalg.norm(E[:3, 3]))
    rot_deg = float(np.degrees(rotation_angle(E[None]))[0])
    d = abs(float(path_m[kf_j]) - float(path_m[kf_i]))
    agrees = trans_m <= thresholds.trans_m + thresholds.trans_per_m * d and (
        rot_deg <= thresholds.rot_deg + thresholds.rot_deg_per_m * d
    )
    return agrees, trans_m, rot_deg


def max_consistent_set(
    adjacency: np.ndarray,
    weights: np.ndarray | None = None,
    preferred: np.ndarray | None = None,
    sources: np.ndarray | None = None,
    source_masks: list[int] | None = None,
    source_pieces: list[int] | None = None,
) -> np.ndarray:
    """Maximum clique of a consistency graph by independent evidence, ties broken for stability.

    The clique with the most independent evidence (``independent_sources``) wins, then the one with
    most members, then the one with the most ``preferred`` members (keeps the established set when new
    evidence is only a tie), then the largest total weight, then the one with the earliest members.

    Args:
        adjacency: (n, n) symmetric bool, True where two closures are consistent (diagonal ignored).
        weights: (n,) non-negative evidence per closure (e.g. inlier counts); ones when None.
        preferred: (n,) bool, the currently accepted closures; none when None.
        sources: (n,) int64 id (0, 1, 2, ...) of each closure's source (its graph match); every closure its
            own source when None.
        source_masks: the objects each source rests on as a bit mask, indexed by source id (0: none
            recorded); every distinct source is independent when None.
        source_pieces: each source's pieces of evidence, indexed by source id (a decisive match's: more than
            one); one each when None.

    Returns:
        Sorted int64 indices of the chosen clique (empty only for n = 0). Exact up to
        ``CLIQUE_BUDGET`` branch-and-bound work; beyond that the best clique found so far, at
        least a greedy clique improved by local swaps.
    """
    A = _clean(adjacency)
    n = A.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    pref = np.zeros(n, dtype=bool) if preferred is None else np.asarray(preferred, dtype=bool)
    src = np.arange(n) if sources is None else np.asarray(sources, dtype=np.int64)
    found, _ = best_clique(
        A, w, pref, min_size=1, budget=CLIQUE_BUDGET, sources=src, source_masks=source_masks,
        source_pieces=source_pieces,
    )  # fmt: skip
    return found


def independent_sources(
    sources: np.ndarray, source_masks: list[int] | None = None, source_pieces: list[int] | None = None
) -> int:
    """How many pieces of evidence the distinct ``sources`` give: those that rest on mutually disjoint
    objects, each counted with its pieces (1; a decisive match's, more).

    Greedy, fewest objects first (ties: the lower source id): a source counts when it shares no object
    with the sources counted before it. A source without recorded objects (mask 0) always counts. Two is
    the count that decides (two independent matches agree: a robot enters the shared frame) and greedy
    can miss it (a small source overlapping two disjoint larger ones is taken first), so when greedy
    counts fewer than two, every pair is checked: adding a source never lowers the count below two. With
    pieces, greedy runs a second time with the sources of most pieces first (a decisive match over the
    whole overlap shares objects with every smaller one) and the larger count holds; adding a source never
    lowers it below the most pieces one source has.

    Args:
        sources: (k,) int64 source ids (repeats allowed).
        source_masks: each source id's objects as a bit mask; every distinct source counts when None.
        source_pieces: each source id's pieces of evidence (>= 1); one each when None.
    """
    ids = np.unique(np.asarray(sources, dtype=np.int64)).tolist()
    pieces = [1] * len(ids) if source_pieces is None else [int(source_pieces[s]) for s in ids]
    if source_masks is None:
        return int(sum(pieces))
    by_size = sorted(zip(ids, pieces, strict=True), key=lambda sp: source_masks[sp[0]].bit_count())  # ties: id
    orders = [by_size]
    if max(pieces, default=1) > 1:
        orders.append(sorted(by_size, key=lambda sp: -sp[1]))
    best = 0
    for order in orders:
        taken, count = 0, 0
        for s, n in order:
            if not source_masks[s] & taken:
                taken |= source_masks[s]
                count += n
        best = max(best, count)
    if best < 2:
        masks = [source_masks[s] for s, _ in by_size]
        for i, mask in enumerate(masks):
            if any(not mask & other for other in masks[i + 1:]):
                return 2
    return best


def clique_score(
    members: np.ndarray,
    weights: np.ndarray,
    preferred: np.ndarray,
    sources: np.ndarray,
    source_masks: list[int] | None = None,
    source_pieces: list[int] | None = None,
) -> tuple:
    """Rank of a clique (larger is better): (independent evidence, members, preferred members, total weight,
    earliest members first), for the (k,) int ``members`` of (m,) ``weights``, ``preferred`` and ``sources``
    (``independent_sources`` with ``source_masks`` and ``source_pieces``)."""
    mem = np.sort(np.asarray(members, dtype=np.int64))
    return (
        independent_sources(sources[mem], source_masks, source_pieces), int(mem.size), int(preferred[mem].sum()),
        float(weights[mem].sum()), tuple(-int(i) for i in mem),
    )  # fmt: skip


def _most_pieces(source_pieces: list[int] | None) -> int:
    """The most pieces of evidence one source gives (1 without pieces): members bound evidence by this factor."""
    return max(source_pieces or [1])


def best_clique(
    adjacency: np.ndarray,
    weights: np.ndarray,
    preferred: np.ndarray,
    min_size: int,
    budget: int,
    start: np.ndarray | None = None,
    sources: np.ndarray | None = None,
    source_masks: list[int] | None = None,
    source_pieces: list[int] | None = None,
) -> tuple[np.ndarray | None, bool]:
    """Best clique of at least ``min_size`` vertices by ``clique_score`` (independent evidence, size,
    preferred members, weight, earliest).

    Degree peeling first drops vertices that cannot be in such a clique, greedy cliques (from the
    highest degree and from ``start``, improved by 1-for-2 swaps) give the first bound, then branch
    and bound (Bron-Kerbosch with pivoting on bitsets) runs until ``budget`` vertices were scanned
    for pivots.

    Args:
        adjacency: (m, m) symmetric bool with a False diagonal.
        weights: (m,) evidence per vertex; preferred: (m,) bool.
        min_size: smallest clique of interest (>= 1).
        budget: branch-and-bound work (vertices scanned for pivots).
        start: (m,) bool clique to grow the second greedy clique from (e.g. the current set's members).
        sources: (m,) int64 source id of each vertex; each vertex its own when None.
        source_masks: each source id's objects as a bit mask (``independent_sources``); None: every
            distinct source is independent.
        source_pieces: each source id's pieces of evidence (``independent_sources``); one each when None.

    Returns:
        (sorted int64 indices or None when no clique reaches ``min_size``, whether the search was exact).
    """
    A = adjacency
    m = A.shape[0]
    src_all = np.arange(m) if sources is None else np.asarray(sources, dtype=np.int64)
    alive = _peel(A, np.ones(m, dtype=bool), min_size)
    if alive.sum() < min_size:
        return None, True

    def rank(mask: np.ndarray) -> tuple:
        return clique_score(np.flatnonzero(mask), weights, preferred, src_all, source_masks, source_pieces)

    greedy = _improve(A, _greedy(A, alive), alive)
    if start is not None and (start := start & alive).any():
        grown = _improve(A, _greedy(A, alive, start), alive)
        if rank(grown) > rank(greedy):
            greedy = grown
    # a clique ranked above the greedy one has at least as much independent evidence, so at least that many
    # members over the most pieces one source gives
    most = _most_pieces(source_pieces)
    best_evidence = max(min_size, rank(greedy)[0])
    best_size = max(min_size, -(-best_evidence // most))
    alive = _peel(A, alive, best_size)
    idx = np.flatnonzero(alive)
    if idx.size < best_size:  # cannot happen for a clique found inside alive; be safe
        return (np.flatnonzero(greedy) if greedy.sum() >= min_size else None), True
    sub = A[np.ix_(idx, idx)]
    nbr = [int.from_bytes(r.tobytes(), "little") for r in np.packbits(sub, axis=1, bitorder="little")]
    w, pref, src = weights[idx], preferred[idx], src_all[idx]

    def score(bits: int) -> tuple:
        return clique_score(np.array(_members(bits), dtype=np.int64), w, pref, src, source_masks, source_pieces)

    g = greedy[idx]
    best_bits = _to_bits(g) if g.sum() >= min_size else 0
    best = score(best_bits) if best_bits else (best_evidence - 1,)
    left = budget
    stack: list[list] = []

    def push(R: int, P: int, X: int) -> None:
        nonlocal left, best_bits, best
        if most * (R.bit_count() + P.bit_count()) < best[0]:  # members bound the evidence from above
            return
        left -= 1 + (P | X).bit_count()  # the pivot choice scans P and X
        if P == 0:
            if X == 0 and R.bit_count() >= min_size:
                s = score(R)
                if s > best:
                    best_bits, best = R, s
            return
        pivot = max(_members(P | X), key=lambda u: (P & nbr[u]).bit_count())
        stack.append([R, P, X, _members(P & ~nbr[pivot]), 0])

    push(0, (1 << idx.size) - 1, 0)
    while stack and left > 0:
        frame = stack[-1]
        R, P, X, todo, i = frame
        if i == len(todo) or most * (R.bit_count() + P.bit_count()) < best[0]:
            stack.pop()
            continue
        v = todo[i]
        frame[4] = i + 1
        bit = 1 << v
        frame[1], frame[2] = P & ~bit, X | bit
        push(R | bit, P & nbr[v], X & nbr[v])
    if not best_bits:
        return None, not stack
    return idx[_members(best_bits)].astype(np.int64), not stack


@dataclass(frozen=True, eq=False)
class PairVote:
    """One robot pair's consistency vote as arrays (``PairConsistency.vote``; a map server's snapshot).

    ``ids`` (n,) int64 voting closure ids in insertion order; ``adjacency`` (n, n) bool pairwise
    consistency; ``weights`` (n,) evidence; ``chosen`` (n,) bool the current maximum consistent set;
    ``exact`` False once a bounded search ran out of budget; ``searches`` bounded searches run so far.
    """

    ids: np.ndarray
    adjacency: np.ndarray
    weights: np.ndarray
    chosen: np.ndarray
    exact: bool
    searches: int


@dataclass
class PairConsistency:
    """Incremental maximum consistent set of one robot pair's closures, bounded in size.

    Keeps the pair's voting closures (at most ``capacity``), their consistency adjacency, their
    sources (the graph match each was cut from), the objects each rests on and the chosen set. A source's
    objects are those of all its voting closures. ``add`` costs O(n) when the new closure joins the set or
    cannot change it; only when its consistent neighbours could form a set ranked above the current one
    (``clique_score``: more independent sources, then more closures) a bounded search over them runs.
    Semantics are those of ``max_consistent_set`` with the current set preferred: a better-ranked
    consistent set replaces the current one, a tie does not.

    When the pair is full, the oldest closure outside the set leaves the vote (it stays rejected);
    when every closure is in the set, the oldest one leaves (it stays accepted).
    """

    capacity: int = MAX_CLOSURES_PER_PAIR
    budget: int = INCREMENTAL_BUDGET
    ids: list[int] = field(default_factory=list)
    exact: bool = True  # False once a search ran out of budget (the set may then not be maximum)
    searches: int = 0  # bounded searches run so far
    _A: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    _w: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _chosen: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    _src: list = field(default_factory=list)  # each voting closure's source (hashable), in ``ids`` order
    _mask: list[int] = field(default_factory=list)  # each voting closure's objects as a bit mask (``_bit``)
    _pieces: list[int] = field(default_factory=list)  # each voting closure's pieces of evidence (its match's)
    _bit: dict = field(default_factory=dict)  # object (hashable) -> its bit

    def __post_init__(self) -> None:
        if self.capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {self.capacity}")

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def chosen_ids(self) -> list[int]:
        """Closure ids in the current maximum consistent set, in insertion order."""
        return [self.ids[i] for i in np.flatnonzero(self._chosen[: len(self.ids)])]

    def chosen_mask(self) -> np.ndarray:
        """(n,) bool over ``ids``: in the current set."""
        return self._chosen[: len(self.ids)].copy()

    def evidence(self) -> int:
        """Independent sources (``independent_sources``, one piece each) of the current set: the matches on
        mutually disjoint objects it rests on (a decisive one anchors by its own rule)."""
        n = len(self.ids)
        src, masks, _ = self._sources(n)
        return independent_sources(src[self._chosen[:n]], masks)

    def vote(self) -> PairVote:
        """The pair's vote as arrays (copies)."""
        n = len(self.ids)
        return PairVote(np.asarray(self.ids, dtype=np.int64), self._A[:n, :n].copy(), self._w[:n].copy(),
                        self._chosen[:n].copy(), self.exact, self.searches)  # fmt: skip

    @classmethod
    def from_vote(
        cls, vote: PairVote, capacity: int = MAX_CLOSURES_PER_PAIR, sources: list | None = None,
        supports: list | None = None, pieces: list[int] | None = None,
    ) -> PairConsistency:
        """Rebuild a pair from ``vote()``, its closures' ``sources`` (in ``vote.ids`` order; each closure its
        own when None), the objects each rests on (``supports``, same order; none when None) and the pieces
        of evidence each one's match gives (``pieces``; one each when None); it then votes on new closures
        exactly as the original would.

        Raises:
            BackendError: the arrays are inconsistent (shapes, an asymmetric adjacency, more closures
                than ``capacity``).
        """
        try:
            ids = np.asarray(vote.ids, dtype=np.int64).reshape(-1)
            n = ids.size
            A = np.asarray(vote.adjacency, dtype=bool).reshape(n, n)
            w = np.asarray(vote.weights, dtype=np.float64).reshape(n)
            chosen = np.asarray(vote.chosen, dtype=bool).reshape(n)
        except (TypeError, ValueError) as exc:
            raise BackendError(f"consistency vote arrays do not fit together: {exc}") from None
        if n > capacity or (A != A.T).any() or A.diagonal().any() or not np.isfinite(w).all():
            raise BackendError(
                f"consistency vote is inconsistent ({n} closures for capacity {capacity}, or an asymmetric "
                "adjacency, or non-finite weights)"
            )
        src = [("closure", int(i)) for i in ids] if sources is None else list(sources)
        sup = [()] * n if supports is None else list(supports)
        pcs = [1] * n if pieces is None else [int(p) for p in pieces]
        if len(src) != n or len(sup) != n or len(pcs) != n or any(p < 1 for p in pcs):
            raise BackendError(
                f"consistency vote has {n} closures but {len(src)} sources, {len(sup)} supports, {len(pcs)} "
                "pieces (each >= 1)"
            )
        pair = cls(capacity, ids=ids.tolist(), exact=bool(vote.exact), searches=int(vote.searches),
                   _A=A.copy(), _w=w.copy(), _chosen=chosen.copy(), _src=src, _pieces=pcs)  # fmt: skip
        pair._mask = [pair._objects_mask(objects) for objects in sup]
        return pair

    def add(
        self, closure_id: int, consistent: np.ndarray, weight: float = 1.0, source: object = None,
        support: Iterable = (), pieces: int = 1,
    ) -> tuple[int, bool] | None:
        """Add a closure given its consistency with the current ``ids`` (an (n,) bool row), its evidence
        ``weight``, its ``source`` (hashable: the graph match it was cut from; the closure itself when None),
        its ``support`` (hashable objects it rests on, e.g. ``(agent, node id)``: two sources that share
        one are not independent evidence) and the ``pieces`` of evidence its match gives (1; a decisive
        match's more: the set ranking counts them, ``independent_sources``).

        Returns:
            The closure that left the vote to make room, with whether it was in the set, or None.
        """
        row = np.asarray(consistent, dtype=bool).reshape(-1)
        n = len(self.ids)
        if row.size != n:
            raise ValueError(f"consistency row has {row.size} entries for {n} closures")
        evicted = None
        if n == self.capacity:
            out = self._chosen[:n]
            victim = int(np.argmin(out)) if not out.all() else 0  # oldest outside the set, else oldest
            evicted = (self.ids[victim], bool(out[victim]))
            self._remove(victim)
            row = np.delete(row, victim)
            n -= 1
        self._grow(n + 1)
        self._A[n, :n] = self._A[:n, n] = row
        self._A[n, n] = False
        self._w[n] = float(weight)
        self._chosen[n] = False
        self.ids.append(int(closure_id))
        self._src.append(("closure", int(closure_id)) if source is None else source)
        self._mask.append(self._objects_mask(support))
        self._pieces.append(max(1, int(pieces)))
        self._select(n, row)
        return evicted

    def _objects_mask(self, objects: Iterable) -> int:
        """``objects`` as a bit mask (new objects get the next bits)."""
        mask = 0
        for obj in objects:
            mask |= 1 << self._bit.setdefault(obj, len(self._bit))
        return mask

    def _sources(self, n: int) -> tuple[np.ndarray, list[int], list[int]]:
        """(n,) int64 the first ``n`` voting closures' sources numbered densely (first seen first), each
        source number's objects (the union of its closures' bit masks) and its pieces of evidence (the most
        any of its closures carries)."""
        number: dict = {}
        src = np.array([number.setdefault(x, len(number)) for x in self._src[:n]], dtype=np.int64)
        masks, pieces = [0] * len(number), [1] * len(number)
        for s, mask, p in zip(src.tolist(), self._mask[:n], self._pieces[:n], strict=True):
            masks[s] |= mask
            pieces[s] = max(pieces[s], p)
        return src, masks, pieces

    def _select(self, v: int, row: np.ndarray) -> None:
        S = self._chosen[:v]
        if not S.any():
            self._chosen[v] = True
            return
        joins = bool(row[S].all())  # a closure consistent with the whole set adds to it
        # that is the best set through v too when its match is new to the set; when the match is in the set
        # already, a set through v without some of the set's closures can have more independent evidence
        # (v brings its match to a set that lacked it) or more closures: then the search below decides
        if joins and self._src[v] not in {self._src[i] for i in np.flatnonzero(S)}:
            self._chosen[v] = True
            return
        src, masks, pieces = self._sources(v + 1)
        incumbent = np.r_[S, joins]
        w, pref = self._w[: v + 1], np.r_[S, False]
        current = clique_score(np.flatnonzero(incumbent), w, pref, src, masks, pieces)
        # every clique through v lies in v's consistent neighbourhood: it cannot rank above S when even all
        # of the neighbourhood's distinct sources (independent or not, with their pieces) and members could not
        cand = np.r_[np.flatnonzero(row), v]
        if (sum(pieces[s] for s in np.unique(src[cand]).tolist()), cand.size) <= current[:2]:
            self._chosen[: v + 1] = incumbent
            return
        self.searches += 1
        sub = self._A[np.ix_(cand, cand)].copy()
        sub[-1, :-1] = sub[:-1, -1] = True  # v agrees with each of its neighbours
        found, exact = best_clique(
            sub, w[cand], pref[cand], -(-current[0] // _most_pieces(pieces)), self.budget, start=pref[cand],
            sources=src[cand], source_masks=masks, source_pieces=pieces,
        )  # fmt: skip
        self.exact &= exact
        self._chosen[: v + 1] = incumbent
        if found is not None and clique_score(cand[found], w, pref, src, masks, pieces) > current:
            self._chosen[: v + 1] = False
            self._chosen[cand[found]] = True

    def _grow(self, n: int) -> None:
        cap = self._A.shape[0]
        if n <= cap:
            return
        new = min(max(2 * cap, 16), self.capacity)
        A = np.zeros((new, new), dtype=bool)
        A[:cap, :cap] = self._A
        self._A = A
        self._w = np.r_[self._w, np.zeros(new - cap)]
        self._chosen = np.r_[self._chosen, np.zeros(new - cap, dtype=bool)]

    def _remove(self, i: int) -> None:
        n = len(self.ids)
        self._A[i : n - 1, :n] = self._A[i + 1 : n, :n]
        self._A[:n, i : n - 1] = self._A[:n, i + 1 : n]
        self._A[n - 1, :n] = self._A[:n, n - 1] = False
        self._w[i : n - 1] = self._w[i + 1 : n]
        self._chosen[i : n - 1] = self._chosen[i + 1 : n]
        self._chosen[n - 1] = False
        del self.ids[i]
        del self._src[i]
        del self._mask[i]
        del self._pieces[i]


def _clean(adjacency: np.ndarray) -> np.ndarray:
    A = np.array(adjacency, dtype=bool)
    np.fill_diagonal(A, False)
    return A


def _to_bits(mask: np.ndarray) -> int:
    return int.from_bytes(np.packbits(np.asarray(mask, dtype=bool), bitorder="little").tobytes(), "little")


def _members(bits: int) -> list[int]:
    """Set bit positions of ``bits``, ascending."""
    out = []
    while bits:
        low = bits & -bits
        out.append(low.bit_length() - 1)
        bits ^= low
    return out


def _peel(A: np.ndarray, alive: np.ndarray, size: int) -> np.ndarray:
    """Drop vertices with fewer than ``size - 1`` live neighbours until none is left (a k-core)."""
    alive = alive.copy()
    deg = A[:, alive].sum(axis=1)
    while True:
        drop = alive & (deg < size - 1)
        if not drop.any():
            return alive
        alive &= ~drop
        deg -= A[:, drop].sum(axis=1)


def _greedy(A: np.ndarray, alive: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """(m,) bool maximal clique inside ``alive`` (containing the clique ``start`` when given): repeatedly
    take the candidate with most candidate neighbours (ties: the earliest)."""
    if start is None:
        clique = np.zeros(A.shape[0], dtype=bool)
        cand = np.flatnonzero(alive)
    else:
        clique = start.copy()
        cand = np.flatnonzero(alive & ~clique & A[:, clique].all(axis=1))
    while cand.size:
        sub = A[np.ix_(cand, cand)]
        v = int(np.argmax(sub.sum(axis=1)))
        clique[cand[v]] = True
        cand = cand[sub[v]]
    return clique


def _improve(A: np.ndarray, clique: np.ndarray, alive: np.ndarray, rounds: int = 50) -> np.ndarray:
    """Local search on a clique: add vertices adjacent to all members, or swap one member for two
    mutually consistent vertices adjacent to all other members; at most ``rounds`` moves."""
    clique = clique.copy()
    for _ in range(rounds):
        members = np.flatnonzero(clique)
        count = A[:, members].sum(axis=1)
        count[~alive | clique] = -1
        full = np.flatnonzero(count == members.size)
        if full.size:
            clique[full[0]] = True
            continue
        near = np.flatnonzero(count == members.size - 1)
        if near.size < 2:
            break
        missing = members[np.argmin(A[np.ix_(near, members)], axis=1)]
        for u in np.unique(missing):
            group = near[missing == u]
            pairs = np.argwhere(np.triu(A[np.ix_(group, group)]))
            if pairs.size:
                clique[u] = False
                clique[group[pairs[0]]] = True
                break
        else:
            break
    return clique
