"""Match two semantic graphs end to end: descriptors -> candidates (Eq. 1) -> hypotheses -> verification
(whole overlap against chance) -> pose (Eq. 2).

``match_graphs`` is the one library function behind ``shgm-slam match``, the map server's
cross-robot matching and the localization benchmark; pass precomputed descriptors to match one graph
against many cheaply.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from shgm_slam.config import DescriptorConfig, MatchingConfig, OutlierMode
from shgm_slam.descriptors import NodeDescriptors, compute_descriptors
from shgm_slam.errors import ConfigError, GraphError
from shgm_slam.geometry.se3 import transform_points
from shgm_slam.matching.candidates import Candidates, match_candidates
from shgm_slam.matching.chance import row_steps, shift_vectors
from shgm_slam.matching.clique import clique_hypotheses
from shgm_slam.matching.labelled_tree import LabelledTree
from shgm_slam.matching.pair_voting import pair_vote_hypotheses
from shgm_slam.matching.polish import polish_alignment
from shgm_slam.matching.pose import correspondence_weights, fit_pose, padded_correspondence_weights, spread_m
from shgm_slam.matching.precision import alignment_covariance, predicted_error_m
from shgm_slam.matching.ransac import ransac_alignment
from shgm_slam.matching.result import MatchResult
from shgm_slam.matching.verification import Verification, partner_pairs_stack, support_counts, verify_alignments
from shgm_slam.types import MAX_COORDINATE_M, GraphArrays, extent_problem

MIN_NODES = 3
"""Graphs with fewer nodes cannot determine a rigid transform."""

HypothesisGenerator = Callable[
    [np.ndarray, np.ndarray, Candidates, np.ndarray | None, MatchingConfig], list[np.ndarray]
]


def _ransac(
    points_b: np.ndarray,
    points_a: np.ndarray,
    cands: Candidates,
    weights: np.ndarray | None,
    cfg: MatchingConfig,
) -> list[np.ndarray]:
    best = ransac_alignment(
        points_b, points_a, cands.rows_a, cands.rows_b, weights,
        iterations=cfg.ransac_iterations, inlier_threshold_m=cfg.inlier_threshold_m,
        refine_iterations=cfg.refine_iterations,
        gravity_aligned=cfg.gravity_aligned, up=np.asarray(cfg.up_axis), seed=cfg.seed,
    )  # fmt: skip
    return [] if best is None else [best.T_a_b]


def _clique(
    points_b: np.ndarray,
    points_a: np.ndarray,
    cands: Candidates,
    weights: np.ndarray | None,
    cfg: MatchingConfig,
) -> list[np.ndarray]:
    return clique_hypotheses(
        points_b, points_a, cands.rows_a, cands.rows_b, weights,
        consistency_threshold_m=cfg.consistency_threshold_m,
        gravity_aligned=cfg.gravity_aligned, up=np.asarray(cfg.up_axis), max_candidates=cfg.max_candidates,
    )  # fmt: skip


HYPOTHESIS_GENERATORS: dict[OutlierMode, HypothesisGenerator] = {
    OutlierMode.RANSAC: _ransac,
    OutlierMode.CLIQUE: _clique,
}
"""Registry: outlier mode -> (points_b, points_a, candidates, weights, cfg) -> (4, 4) hypotheses."""


def searched_hypotheses(num_hypotheses: int, cfg: MatchingConfig) -> int:
    """How many hypotheses the best one was chosen from (the Bonferroni factor of the decision):
    RANSAC's iterations, or the cliques grown."""
    return cfg.ransac_iterations if cfg.outlier_mode is OutlierMode.RANSAC else max(num_hypotheses, 1)


def check_graph(graph: GraphArrays, name: str) -> None:
    """Refuse a ``GraphArrays`` that matching cannot read (a caller's own arrays are checked here, before any use).

    Raises:
        GraphError: not numpy arrays, lengths or shapes that disagree, node ids that repeat (results name nodes
            by id), labels that are not integers, positions or sizes that are not numbers (an object or bool array
            reached ``np.isfinite``'s TypeError), non-finite positions or positions beyond ``MAX_COORDINATE_M`` of
            the origin (1e200 m ended in numpy's "Eigenvalues did not converge"), positions that cannot be metres
            (``types.extent_problem``: degrees of latitude and longitude), negative or non-finite sizes,
            edges that are not (E, 2) integer row indices into the nodes.
    """
    fields = ("node_ids", "label_ids", "positions_xyz", "sizes", "edges")
    loose = [f for f in fields if not isinstance(getattr(graph, f, None), np.ndarray)]
    if loose:
        raise GraphError(f"graph {name}: {', '.join(loose)} must be numpy arrays (np.asarray them), "
                         f"got {', '.join(type(getattr(graph, f, None)).__name__ for f in loose)}")  # fmt: skip
    for what in ("positions_xyz", "sizes"):
        values = getattr(graph, what)
        if values.size and not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
            raise GraphError(f"graph {name}: {what} must be numbers, got {values.dtype} (np.asarray(..., float) them)")
    n = graph.node_ids.shape[0] if graph.node_ids.ndim == 1 else -1
    if n < 0 or graph.positions_xyz.shape != (n, 3) or graph.label_ids.shape != (n,) or graph.sizes.shape != (n,):
        raise GraphError(
            f"graph {name}: node arrays disagree (ids {graph.node_ids.shape}, labels {graph.label_ids.shape}, "
            f"positions {graph.positions_xyz.shape}, sizes {graph.sizes.shape}; need (N,), (N,), (N, 3), (N,))"
        )
    for what, a in (("node ids", graph.node_ids), ("label ids", graph.label_ids), ("edges", graph.edges)):
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise GraphError(f"graph {name}: {what} must be integers, got {a.dtype}")
    if np.unique(graph.node_ids).size != n:
        raise GraphError(f"graph {name}: node ids repeat; give every node its own id (matches name nodes by id)")
    if not np.all(np.isfinite(graph.positions_xyz)):
        row = int(np.argmin(np.isfinite(graph.positions_xyz).all(axis=1)))
        raise GraphError(f"graph {name} has non-finite node positions (row {row})")
    if n and (far := float(np.abs(graph.positions_xyz).max())) > MAX_COORDINATE_M:
        raise GraphError(f"graph {name}: a node lies {far:.3g} m from the origin, beyond the {MAX_COORDINATE_M:g} m "
                         "a match computes with; give positions in metres in a local frame")  # fmt: skip
    if (problem := extent_problem(graph.positions_xyz)) is not None:
        raise GraphError(f"graph {name}: {problem}")
    if np.any(~np.isfinite(graph.sizes)) or np.any(graph.sizes < 0):
        raise GraphError(f"graph {name} has negative or non-finite node sizes")
    e = graph.edges
    if e.size and (e.ndim != 2 or e.shape[1] != 2):
        raise GraphError(f"graph {name}: edges must be an (E, 2) array of row indices, got shape {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= n):
        bad = int(e.min()) if e.min() < 0 else int(e.max())
        raise GraphError(f"graph {name}: an edge references row {bad}, outside the {n} nodes (edges are row "
                         "indices into the node arrays, not node ids)")  # fmt: skip


def unusable_reason(graph: GraphArrays, name: str) -> str:
    """Why ``graph`` cannot be matched ('' when it can): too few nodes or no edges.

    Raises:
        GraphError: the arrays are inconsistent (lengths, non-finite positions, negative sizes; a caller's own
            arrays get all of ``check_graph`` first, its extent check included: a map server's window of a few
            nodes on one mast may span under a metre and is matched, not refused).
    """
    n = len(graph)
    if graph.positions_xyz.shape != (n, 3) or graph.label_ids.shape != (n,) or graph.sizes.shape != (n,):
        raise GraphError(
            f"graph {name}: node arrays disagree (ids {n}, labels {graph.label_ids.shape}, "
            f"positions {graph.positions_xyz.shape}, sizes {graph.sizes.shape})"
        )
    if not np.all(np.isfinite(graph.positions_xyz)):
        raise GraphError(f"graph {name} has non-finite node positions")
    if np.any(~np.isfinite(graph.sizes)) or np.any(graph.sizes < 0):
        raise GraphError(f"graph {name} has negative or non-finite node sizes")
    if n < MIN_NODES:
        return f"graph {name} has {n} node(s); matching needs at least {MIN_NODES}"
    if graph.num_edges == 0:
        return f"graph {name} has no edges (nodes farther apart than the connectivity threshold?)"
    return ""


def _descriptors(
    graph: GraphArrays, given: NodeDescriptors | None, cfg: DescriptorConfig, name: str
) -> NodeDescriptors:
    if given is None:
        return compute_descriptors(graph, cfg)
    if len(given) != len(graph):
        raise GraphError(
            f"precomputed descriptors of graph {name} have {len(given)} rows but the graph has {len(graph)} "
            "nodes; compute them from this graph"
        )
    return given


def match_graphs(
    a: GraphArrays,
    b: GraphArrays,
    descriptor_cfg: DescriptorConfig,
    matching_cfg: MatchingConfig,
    *,
    descriptors_a: NodeDescriptors | None = None,
    descriptors_b: NodeDescriptors | None = None,
    evidence_free_labels: tuple[int, ...] = (),
) -> MatchResult:
    """Find ``T_a_b`` (B's frame -> A's frame) from the semantic graphs of two robots.

    Candidates (Eq. 1, filled with further same-label pairs for sparse maps) give hypotheses (max-clique
    fits or Alg. 2 RANSAC); the ``verified_hypotheses`` with most supporting nodes are refined on their
    whole-overlap partners and judged by ``verification`` (a likelihood ratio of the alignment against
    chance, over every node in the other robot's observed area). Success needs (1) that ratio above
    ``hypotheses searched / false_alarm_rate``, (2) at least ``min_inliers`` partner pairs, (3) an RMSE
    of at most ``max_rmse_m``, (4) partners spanning at least ``min_spread_m`` (``pose.spread_m``) and (5) no
    rival that places B elsewhere beyond chance too unless the best leads it by ``log(1 / false_alarm_rate)``
    (``_ambiguity_reason``).
    Empty, tiny or edgeless graphs give an unsuccessful result with a reason, never an exception.

    Args:
        a, b: the two graphs (positions in each robot's world frame, metres).
        descriptor_cfg: descriptor kind and parameters (ignored for graphs whose descriptors are given).
        matching_cfg: candidate selection, hypotheses and the verification's parameters.
        descriptors_a, descriptors_b: precomputed ``compute_descriptors`` results (same kind) or None.
        evidence_free_labels: train ids whose nodes neither support nor contradict in the verification (they
            still pair up): the map server passes ``viewpoint_dependent_labels`` between robots that look from
            very different heights (``server/viewpoints.py``).

    Raises:
        GraphError: malformed graph arrays or descriptors that do not fit their graph.
        ConfigError: a gravity-aligned match with a zero ``up_axis``.
    """
    cfg = matching_cfg
    if cfg.gravity_aligned and not np.linalg.norm(cfg.up_axis) > 0:
        raise ConfigError(f"matching.up_axis {cfg.up_axis} must be non-zero (KITTI camera frame: [0, -1, 0])")
    timings = {"descriptors": 0.0, "matching": 0.0, "ransac": 0.0, "pose": 0.0, "total": 0.0}
    t_start = time.perf_counter()

    def lap(key: str, since: float) -> float:
        now = time.perf_counter()
        timings[key] = (now - since) * 1e3
        timings["total"] = (now - t_start) * 1e3
        return now

    reason = unusable_reason(a, "A") or unusable_reason(b, "B")
    if reason:
        return MatchResult.failure(reason, 0, timings)
    da = _descriptors(a, descriptors_a, descriptor_cfg, "A")
    db = _descriptors(b, descriptors_b, descriptor_cfg, "B")
    t = lap("descriptors", t_start)

    cands = match_candidates(da, db, cfg, a.label_ids, b.label_ids)
    t = lap("matching", t)
    if len(cands) < MIN_NODES:
        reason = f"only {len(cands)} candidate(s) scored above {cfg.score_threshold}"
        return MatchResult.failure(reason, len(cands), timings)

    points_a, points_b = a.positions_xyz[cands.rows_a], b.positions_xyz[cands.rows_b]
    weights = None
    if cfg.weighted_pose:
        weights = correspondence_weights(a.sizes[cands.rows_a], b.sizes[cands.rows_b])
    hypotheses = HYPOTHESIS_GENERATORS[cfg.outlier_mode](points_b, points_a, cands, weights, cfg)
    if cfg.gravity_aligned and cfg.vote_hypotheses:
        hypotheses = list(hypotheses) + pair_vote_hypotheses(
            b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, np.asarray(cfg.up_axis),
            tolerance_m=cfg.consistency_threshold_m, count=cfg.vote_hypotheses,
        )  # fmt: skip
    t = lap("ransac", t)
    if not hypotheses:
        reason = f"no consistent hypothesis among {len(cands)} candidates"
        return MatchResult.failure(reason, len(cands), timings)

    tree_a, tree_b = LabelledTree(a.positions_xyz, a.label_ids), LabelledTree(b.positions_xyz, b.label_ids)
    refined = np.stack(_refined(np.stack(hypotheses), a, b, tree_a, cfg))
    shifts, shift_labels = _shifts(tree_a, tree_b, refined, cfg)
    verified = _verify(tree_a, tree_b, refined, cfg, shifts, shift_labels, evidence_free_labels)
    scored = list(zip(refined, verified, strict=True))
    best, rival = _best_and_rival(scored, b, cfg.verification_radius_m)
    T, v = best
    rows_a, rows_b = v.pairs[:, 0], v.pairs[:, 1]
    res = np.linalg.norm(transform_points(T, b.positions_xyz[rows_b]) - a.positions_xyz[rows_a], axis=1)
    rmse = float(np.sqrt(np.mean(res**2))) if res.size else math.inf
    up = np.asarray(cfg.up_axis)
    spread = spread_m(a.positions_xyz[rows_a], cfg.gravity_aligned, up)
    threshold = math.log(searched_hypotheses(len(hypotheses), cfg) / cfg.false_alarm_rate)
    reason = _rejection_reason(v, threshold, rmse, spread, cfg) or _ambiguity_reason(best, rival, b, threshold, cfg)
    if not reason and cfg.polish:  # the decision is made; only the accepted transform is refitted
        T = polish_alignment(T, a, b, tree_a, cfg.verification_radius_m, gravity_aligned=cfg.gravity_aligned, up=up)
    covariance, centroid_sigma = None, math.nan
    if not reason:  # how precisely the accepted alignment is known, from its partners (reported, not decided on)
        placed_b = transform_points(T, b.positions_xyz[rows_b])
        covariance = alignment_covariance(placed_b, a.positions_xyz[rows_a], gravity_aligned=cfg.gravity_aligned,
                                          up=up)  # fmt: skip
        if covariance is not None:
            centroid = transform_points(T, b.positions_xyz.mean(axis=0, keepdims=True))[0]
            centroid_sigma = predicted_error_m(covariance, centroid, gravity_aligned=cfg.gravity_aligned, up=up)
    lap("pose", t)

    pairs = np.stack([a.node_ids[rows_a], b.node_ids[rows_b]], axis=1).astype(np.int64)
    return MatchResult(
        success=not reason,
        T_a_b=None if reason else T,
        inliers=np.zeros((0, 2), dtype=np.int64) if reason else pairs,
        candidates=len(cands),
        timings_ms=timings,
        rmse_m=rmse,
        num_inliers=v.support,
        spread_m=spread,
        support=v.support,
        rival_support=0 if rival is None else rival[1].support,
        T_a_b_hypothesis=T,
        reason=reason,
        expected_chance=v.expected_chance,
        overlap_a=v.overlap_a,
        overlap_b=v.overlap_b,
        contradictions=v.contradictions,
        llr=v.llr,
        llr_threshold=threshold,
        rival_llr=-math.inf if rival is None else rival[1].llr,
        hypotheses=len(hypotheses),
        covariance=covariance,
        centroid_sigma_m=centroid_sigma,
    )


def judge_alignment(
    a: GraphArrays, b: GraphArrays, T_a_b: np.ndarray, cfg: MatchingConfig, evidence_free_labels: tuple[int, ...] = ()
) -> Verification:
    """What ``match_graphs`` would make of one given alignment had its search proposed it: (4, 4) ``T_a_b``
    (B's frame -> A's) and its refinement on the whole-overlap partners are each judged by the likelihood
    ratio against chance, and the better counts. Benchmarks score the *true* alignment this way: whether a
    miss lacked the evidence (the truth itself stays below the threshold) or the search (it would clear it).

    Args:
        a, b: the two graphs (positions in each robot's frame, metres).
        T_a_b: (4, 4) the alignment to judge.
        cfg: the matching stage (refinement, verification radius, chance model).
        evidence_free_labels: as ``match_graphs``.
    """
    tree_a, tree_b = LabelledTree(a.positions_xyz, a.label_ids), LabelledTree(b.positions_xyz, b.label_ids)
    given = np.asarray(T_a_b, dtype=np.float64)[None]
    stack = np.concatenate([given, np.stack(_refined(given, a, b, tree_a, cfg))])
    shifts, shift_labels = _shifts(tree_a, tree_b, stack, cfg)
    verified = _verify(tree_a, tree_b, stack, cfg, shifts, shift_labels, evidence_free_labels)
    return max(verified, key=lambda v: v.llr)


def _shifts(
    tree_a: LabelledTree, tree_b: LabelledTree, T_stack: np.ndarray, cfg: MatchingConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(H, S, 3) shifts of the chance model in A's frame for each of (H, 4, 4) hypotheses, and (S,) the label
    each measures (-1: every label): ``shift_vectors`` along every heading, then the repeats of both graphs'
    own rows beyond their reach (``row_steps``; B's turned into A's frame by each hypothesis)."""
    up, radius = np.asarray(cfg.up_axis, dtype=np.float64), cfg.verification_radius_m
    shifts = shift_vectors(up, radius)
    reach = float(np.linalg.norm(shifts, axis=1).max()) + radius
    steps_a, owners_a = row_steps(tree_a, up, radius_m=radius, longer_than_m=reach)
    steps_b, owners_b = row_steps(tree_b, up, radius_m=radius, longer_than_m=reach)
    fixed = np.vstack([shifts, steps_a])
    turned = np.einsum("hij,sj->hsi", T_stack[:, :3, :3], steps_b)  # B's rows in A's frame, per hypothesis
    stack = np.concatenate([np.broadcast_to(fixed, (len(T_stack), *fixed.shape)), turned], axis=1)
    labels = np.concatenate([np.full(len(shifts), -1, dtype=np.int64), owners_a, owners_b])
    return stack, labels


def _verify(
    tree_a: LabelledTree, tree_b: LabelledTree, T_stack: np.ndarray, cfg: MatchingConfig, shifts_m: np.ndarray,
    shift_labels: np.ndarray, evidence_free_labels: tuple[int, ...] = (),
) -> list[Verification]:
    return verify_alignments(
        tree_a, tree_b, T_stack, radius_m=cfg.verification_radius_m, coverage_m=cfg.coverage_radius_m,
        density_radius_m=cfg.density_radius_m, partner_probability=cfg.partner_probability, shifts_m=shifts_m,
        shift_labels=shift_labels, evidence_free_labels=evidence_free_labels, confusions=cfg.confusion_evidence,
    )  # fmt: skip


def _refined(
    hypotheses: np.ndarray, a: GraphArrays, b: GraphArrays, tree_a: LabelledTree, cfg: MatchingConfig
) -> list[np.ndarray]:
    """Screen (H, 4, 4) hypotheses by their supporting nodes of B (``_screened``), then refine them together:
    alternate partner selection (``verification.partner_pairs``, the whole graphs) and one batched Eq. 2 fit
    on each one's partners, ``refine_iterations`` times; a hypothesis stops when its partners are stable or
    would shrink."""
    radius = cfg.verification_radius_m
    counts = support_counts(tree_a, b.positions_xyz, b.label_ids, hypotheses, radius)
    Ts = hypotheses[_screened(hypotheses, np.argsort(-counts, kind="stable"), b.positions_xyz, radius,
                              cfg.verified_hypotheses)].copy()  # fmt: skip

    def partners(T_stack: np.ndarray) -> list[np.ndarray]:
        if not len(T_stack):
            return []
        mapped = transform_points_each(T_stack, b.positions_xyz)
        return [p for p, _ in partner_pairs_stack(tree_a, mapped, b.label_ids, radius)]

    pairs = partners(Ts)
    active = [k for k in range(len(Ts)) if pairs[k].shape[0] >= MIN_NODES]
    for _ in range(cfg.refine_iterations):
        if not active:
            break
        rows_a, rows_b, lengths = _padded_pairs([pairs[k] for k in active])
        if cfg.weighted_pose:
            w = padded_correspondence_weights(a.sizes[rows_a], b.sizes[rows_b], lengths)
        else:
            w = (np.arange(rows_a.shape[1])[None, :] < lengths[:, None]).astype(np.float64)
        up = np.asarray(cfg.up_axis)
        fits = fit_pose(b.positions_xyz[rows_b], a.positions_xyz[rows_a], w, cfg.gravity_aligned, up)
        still = []
        for i, (k, new) in enumerate(zip(active, partners(fits), strict=True)):
            if new.shape[0] < pairs[k].shape[0]:
                continue
            stable = np.array_equal(new, pairs[k])
            Ts[k], pairs[k] = fits[i], new
            if not stable:
                still.append(k)
        active = still
    return list(Ts)


_SCREEN_CHUNK = 8
"""``_screened`` looks for the hypothesis elsewhere this many at a time."""


def _screened(
    hypotheses: np.ndarray, order: np.ndarray, points_b: np.ndarray, radius_m: float, count: int
) -> np.ndarray:
    """Indices of the hypotheses to refine: the first ``count`` in ``order`` (best first), and the first after
    them that places B elsewhere than all of those (some node of B lands more than ``radius_m`` apart from
    where each of them puts it). A well-supported place is often proposed many times and can fill every
    slot (near-duplicates are worth refining: they settle on different optima); the extra slot makes sure
    the best *other* place is verified too, so that a second place just as supported (a block built twice,
    a street seen reversed) is seen and the ambiguity rule (``_ambiguity_reason``) can refuse the match.

    Args:
        hypotheses: (H, 4, 4) ``T_a_b`` hypotheses.
        order: (H,) their indices, best first.
        points_b: (N, 3) B's nodes in B's frame, metres.
        radius_m: the verification radius, metres.
        count: hypotheses refined before the extra one (``verified_hypotheses``).
    """
    top = order[:count]
    if len(order) == len(top):
        return top
    placed = transform_points_each(hypotheses[top], points_b)  # (k, N, 3)
    for start in range(len(top), len(order), _SCREEN_CHUNK):  # the first one elsewhere is usually early
        rest = order[start : start + _SCREEN_CHUNK]
        mapped = transform_points_each(hypotheses[rest], points_b)
        apart = np.linalg.norm(mapped[:, None] - placed[None], axis=3).max(axis=2)  # (chunk, k)
        elsewhere = np.flatnonzero((apart > radius_m).all(axis=1))
        if elsewhere.size:
            return np.append(top, rest[elsewhere[0]])
    return top


def transform_points_each(T_stack: np.ndarray, points_xyz: np.ndarray) -> np.ndarray:
    """(H, N, 3) ``transform_points`` of (N, 3) points by each of (H, 4, 4) transforms, as one batched
    matrix product (each batch is the same BLAS product as one ``transform_points``: the same bits)."""
    return np.matmul(points_xyz, T_stack[:, :3, :3].transpose(0, 2, 1)) + T_stack[:, None, :3, 3]


def _padded_pairs(pairs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """B lists of (M_i, 2) row pairs (row_a, row_b) as (B, max M_i) int64 rows of A and of B, each padded
    with row 0, and the (B,) lengths M_i."""
    lengths = np.array([p.shape[0] for p in pairs], dtype=np.int64)
    filled = np.arange(lengths.max())[None, :] < lengths[:, None]  # row-major: the pairs' concatenated order
    flat = np.concatenate(pairs)
    rows_a, rows_b = np.zeros(filled.shape, dtype=np.int64), np.zeros(filled.shape, dtype=np.int64)
    rows_a[filled], rows_b[filled] = flat[:, 0], flat[:, 1]
    return rows_a, rows_b, lengths


def _best_and_rival(
    scored: list[tuple[np.ndarray, Verification]], b: GraphArrays, radius_m: float
) -> tuple[tuple[np.ndarray, Verification], tuple[np.ndarray, Verification] | None]:
    """The hypothesis with the largest likelihood ratio, and the best one that places B elsewhere
    (B's centroid more than twice the verification radius away) or None."""
    order = sorted(range(len(scored)), key=lambda i: -scored[i][1].llr)
    best = scored[order[0]]
    c = b.positions_xyz.mean(axis=0, keepdims=True)
    at = transform_points(best[0], c)
    for i in order[1:]:
        if np.linalg.norm(transform_points(scored[i][0], c) - at) > 2.0 * radius_m:
            return best, scored[i]
    return best, None


def _ambiguity_reason(
    best: tuple[np.ndarray, Verification],
    rival: tuple[np.ndarray, Verification] | None,
    b: GraphArrays,
    threshold: float,
    cfg: MatchingConfig,
) -> str:
    """'' unless a rival that places B elsewhere is beyond chance too and the best does not lead it by
    ``log(1 / false_alarm_rate)`` nats, else why the match is ambiguous.

    Two alignments that exclude each other cannot both be right: when the rival clears the chance threshold
    as well, the chance model has failed for one of them (a repeated street, a layout symmetric under a half
    turn), so the rival is the measured alias level of this pair and the best must beat it by the margin it
    must beat chance by (one false alarm in ``1 / false_alarm_rate``)."""
    if rival is None or rival[1].llr < threshold:
        return ""
    lead = best[1].llr - rival[1].llr
    margin = math.log(1.0 / cfg.false_alarm_rate)
    if lead >= margin:
        return ""
    c = b.positions_xyz.mean(axis=0, keepdims=True)
    apart = float(np.linalg.norm(transform_points(best[0], c) - transform_points(rival[0], c)))
    return (
        f"ambiguous: an alignment that places B {apart:.0f} m elsewhere is beyond chance too (log likelihood "
        f"ratio {rival[1].llr:.1f} against {best[1].llr:.1f}, threshold {threshold:.1f}); the best leads by "
        f"{lead:.1f}, less than log(1/false_alarm_rate) = {margin:.1f}"
    )


def _rejection_reason(v: Verification, threshold: float, rmse: float, spread: float, cfg: MatchingConfig) -> str:
    """'' when the alignment is accepted, else why not (the success criteria of ``match_graphs``)."""
    if v.llr < threshold:
        return (
            f"not beyond chance: {v.support} partner(s); of the {v.overlap_a}/{v.overlap_b} overlapping nodes that "
            f"give evidence (A/B) {v.contradictions} without partner, {v.expected_chance:.1f} of B's expected to "
            "find one by chance; "
            f"log likelihood ratio {v.llr:.1f} below {threshold:.1f}"
        )
    if v.support < cfg.min_inliers:
        return f"{v.support} partner(s), fewer than min_inliers={cfg.min_inliers}"
    if rmse > cfg.max_rmse_m:
        return f"partner RMSE {rmse:.2f} m above max_rmse_m={cfg.max_rmse_m}"
    if spread < cfg.min_spread_m:
        return f"partners span only {spread:.1f} m (degenerate), below min_spread_m={cfg.min_spread_m}"
    return ""
