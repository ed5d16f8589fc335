"""Traces of confused labels: a node without a same-label partner that has another label's node within the
radius (a pole mapped as a sign, a tree as a building) — evidence for an alignment as far as such traces are
beyond chance (``confusion_llrs``, a log Bayes factor floored at 0)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.arrays import run_starts, unique_first
from shgm_slam.matching.chance import label_chance, shares_first
from shgm_slam.matching.labelled_tree import LabelledTree


def confusion_llrs(
    unpartnered: np.ndarray, points: list[np.ndarray], label_ids: np.ndarray, other: LabelledTree,
    usable: np.ndarray, shifts_m: np.ndarray | None, same_near: tuple[np.ndarray, np.ndarray], *,
    radius_m: float, density_radius_m: float,
) -> np.ndarray:  # fmt: skip
    """(H,) log Bayes factor, >= 0, of the *traces of confused labels* among one side's nodes under H hypotheses.

    A node inside the other's area without a same-label partner is either an object the other robot did not map,
    or one it mapped under another label (a pole taken for a sign, a tree for a building): then another label's
    node lies within ``radius_m``. Under a wrong alignment that happens at the chance of another label's node
    nearby: the density of other labels within ``density_radius_m`` (as ``p0``), raised, as the same label's
    chance is (``label_chance``), to what the hypothesis shifted by ``shifts_m`` finds (rows of other objects
    line up under a shifted street too). The rate under the right alignment is unknown (the maps' confusion rate);
    the Bayes factor integrates it over a uniform prior, a proper likelihood ratio (no parameter fitted to the
    data it judges), floored at 1: the traces can rescue the support a confused label lost, never count against
    an alignment. Without it, each confused object of the overlap is a lost partner on both sides (10 % of labels
    confused per robot cost a fifth of the sparse benchmark's localizations).

    Args:
        unpartnered: (H, N) bool, the side's nodes inside the other's area, giving evidence, without a partner.
        points: H arrays (N, 3): the side's nodes placed in the other graph's frame by each hypothesis.
        label_ids: (N,) the side's labels.
        other: the other graph's nodes.
        usable: (M,) bool, the other graph's nodes whose labels give evidence.
        shifts_m: (H, S, 3) shifts of the nodes in the other's frame (the chance model's) or None.
        same_near: (H, N) counts of the other graph's nodes of each node's own label within ``radius_m`` and (H, N)
            within ``density_radius_m`` (the verification has them).
        radius_m, density_radius_m: the verification's radii, metres.
    """
    h, n = unpartnered.shape
    flat = np.flatnonzero(unpartnered.reshape(-1))  # (hypothesis, node) keys k * N + row
    if flat.size == 0 or not usable.any():
        return np.zeros(h)
    hyp, rows = flat // n, flat % n
    placed = np.stack(points).reshape(-1, 3)[flat]
    counted = other.any if usable.all() else cKDTree(other.positions_xyz[usable])

    def other_labels_within(r: float, same: np.ndarray) -> np.ndarray:
        # every usable node within r less those of the node's own label (a usable label: the node gives evidence)
        return counted.query_ball_point(placed, r, return_length=True) - same.reshape(-1)[flat]

    same_r, same_density = same_near
    trace = other_labels_within(radius_m, same_r) > 0
    if not trace.any():  # no trace anywhere: every factor is below 1
        return np.zeros(h)
    q0 = 1.0 - np.exp(-other_labels_within(density_radius_m, same_density) * (radius_m / density_radius_m) ** 2)
    bound = _confusion_factors(np.clip(q0, 1e-3, 1.0 - 1e-3), trace, hyp, h)
    live = (bound > 0.0)[hyp]  # the shifted chance only raises q0, and a higher q0 only lowers the factor
    if shifts_m is None or not shifts_m.size or not live.any():
        return bound
    reach = max(density_radius_m, float(np.linalg.norm(shifts_m, axis=-1).max()) + radius_m)
    # the other graph is one for every hypothesis (its own frame): the pairs of each live node are those of its
    # hypothesis alone
    sel = np.flatnonzero(live)
    near = cKDTree(placed[sel]).sparse_distance_matrix(other.any, reach, output_type="ndarray")
    i, j = near["i"].astype(np.int64), near["j"].astype(np.int64)
    keep = usable[j] & (other.label_ids[j] != label_ids[rows[sel[i]]])
    i, j = i[keep], j[keep]
    hits = _shifted_hits(other.positions_xyz[j] - placed[sel[i]], i, sel.size, shifts_m, hyp[sel[i]], radius_m)
    groups = hyp[sel] * (n + 1) + _label_index(label_ids)[rows[sel]]
    q0[sel] = label_chance(hits, groups, np.ones(sel.size, bool), q0[sel])
    return _confusion_factors(np.clip(q0, 1e-3, 1.0 - 1e-3), trace, hyp, h)


def _label_index(label_ids: np.ndarray) -> np.ndarray:
    """(N,) index of each node's label among the distinct labels."""
    return unique_first(np.asarray(label_ids))[2]


def _shifted_hits(
    offsets: np.ndarray, rows: np.ndarray, n: int, shifts_m: np.ndarray, hypotheses: np.ndarray, radius_m: float
) -> np.ndarray:
    """(S, n) bool: row r finds a node within ``radius_m`` once shifted by shift s, from the (P, 3) offsets (node -
    row) of its pairs within reach, (H, S, 3) shifts per hypothesis and (P,) each pair's hypothesis. |o - s|^2 =
    |o|^2 - 2 o.s + |s|^2, the products one matrix product per shift set (one for all the hypotheses whose shifts
    equal the first's: those that do not turn with the hypothesis)."""
    hits = np.zeros((shifts_m.shape[1], n), dtype=bool)
    sq_off = np.einsum("pi,pi->p", offsets, offsets)
    set_of = np.where(shares_first(shifts_m), 0, np.arange(len(shifts_m)))
    of_pair = set_of[hypotheses]
    sets = [(np.flatnonzero(of_pair == k), shifts_m[k]) for k in np.unique(of_pair).tolist()]
    for pairs, shifts in sets:
        sq_s = np.einsum("si,si->s", shifts, shifts)
        cross = np.einsum("pi,si->ps", offsets[pairs], shifts)  # einsum, not BLAS: no threads for a 3-term sum
        close = sq_off[pairs, None] - 2.0 * cross + sq_s[None, :] < radius_m**2  # (P_k, S)
        p_idx, s_idx = np.nonzero(close)
        hits[s_idx, rows[pairs[p_idx]]] = True
    return hits


_CONFUSION_RATES = np.linspace(0.0, 1.0, 129)
"""Grid of the confused share ``c`` over which ``_confusion_factors`` integrates."""

_TRAPEZOID_WEIGHTS = np.r_[0.5, np.ones(_CONFUSION_RATES.size - 2), 0.5] * (_CONFUSION_RATES[1] - _CONFUSION_RATES[0])
"""The trapezoid rule's weights on ``_CONFUSION_RATES`` (they sum to 1)."""


def _confusion_factors(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """(H,) log Bayes factors, floored at 0, of (N,) trace outcomes grouped by (N,) hypothesis: under the alignment
    a node shows a trace with probability ``q0 + (1 - q0) c`` (chance, plus the confused share c of the objects the
    other robot mapped under another label), under chance ``q0``; c uniform in [0, 1] (trapezoid rule). c = 0 is
    chance itself, so a factor exceeds 1 only where there are more traces than chance gives.

    The log-likelihood ratio ``g(c) = sum log(1 + c lift) + n_without log(1 - c)`` is concave with g(0) = 0, so
    where its slope at 0 (``sum lift - n_without``) is not positive, g <= 0 for every c and the factor is 0
    exactly: only the other hypotheses are integrated (most wrong ones are at or below chance)."""
    rising = _rising(q0, trace, hypotheses, h)
    out = np.zeros(h)
    if rising.any():
        keep = rising[hypotheses]
        index = np.cumsum(rising) - 1  # the rising hypotheses renumbered 0..R-1
        out[rising] = _integrated_factors(q0[keep], trace[keep], index[hypotheses[keep]], int(rising.sum()))
    return out


def _integrated_factors(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """``_confusion_factors`` by the trapezoid rule over ``_CONFUSION_RATES``, every hypothesis integrated."""
    c = _CONFUSION_RATES
    without = np.bincount(hypotheses[~trace], minlength=h)
    order = np.argsort(hypotheses[trace], kind="stable")  # each hypothesis' traces summed alone, in node order
    lift = ((1.0 - q0[trace]) / q0[trace])[order]
    owner = hypotheses[trace][order]
    log_f = np.zeros((c.size, h))  # (C, H)
    if lift.size:
        starts = np.flatnonzero(run_starts(owner))
        log_f[:, owner[starts]] = np.add.reduceat(np.log1p(np.outer(c, lift)), starts, axis=1)
    log_f[:-1] += np.outer(np.log1p(-c[:-1]), without)
    log_f[-1, without > 0] = -np.inf  # (1 - c)^n at c = 1 (0^0 = 1 where every node shows a trace)
    top = log_f.max(axis=0)
    return np.maximum(0.0, top + np.log(_TRAPEZOID_WEIGHTS @ np.exp(log_f - top)))


def _rising(q0: np.ndarray, trace: np.ndarray, hypotheses: np.ndarray, h: int) -> np.ndarray:
    """(H,) bool: the log-likelihood ratio of ``_confusion_factors`` rises from c = 0 (its slope there,
    ``sum (1 - q0) / q0`` over the traces less the nodes without one, is positive); where it does not, the
    concave ratio stays <= 0 for every c and the factor is 0."""
    lift = (1.0 - q0[trace]) / q0[trace]
    return np.bincount(hypotheses[trace], weights=lift, minlength=h) > np.bincount(hypotheses[~trace], minlength=h)
