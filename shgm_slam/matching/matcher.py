"""Match two semantic graphs end to end: descriptors -> candidates (Eq. 1) -> outliers -> pose (Eq. 2).

``match_graphs`` is the one library function behind ``shgm-slam match``, the map server's
cross-robot matching and the localization benchmark; pass precomputed descriptors to match one graph
against many cheaply.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from shgm_slam.config import DescriptorConfig, MatchingConfig, OutlierMode
from shgm_slam.descriptors import NodeDescriptors, compute_descriptors
from shgm_slam.errors import ConfigError, GraphError
from shgm_slam.matching.candidates import Candidates, match_candidates
from shgm_slam.matching.clique import clique_alignment, recheck_threshold_m
from shgm_slam.matching.pose import Alignment, correspondence_weights, refine_alignment, spread_m
from shgm_slam.matching.ransac import ransac_alignment
from shgm_slam.matching.result import MatchResult
from shgm_slam.types import GraphArrays

MIN_NODES = 3
"""Graphs with fewer nodes cannot determine a rigid transform."""

OutlierRejector = Callable[
    [np.ndarray, np.ndarray, Candidates, np.ndarray | None, MatchingConfig], Alignment | None
]


def _ransac(
    points_b: np.ndarray,
    points_a: np.ndarray,
    cands: Candidates,
    weights: np.ndarray | None,
    cfg: MatchingConfig,
) -> Alignment | None:
    return ransac_alignment(
        points_b, points_a, cands.rows_a, cands.rows_b, weights,
        iterations=cfg.ransac_iterations, inlier_threshold_m=cfg.inlier_threshold_m,
        refine_iterations=cfg.refine_iterations,
        gravity_aligned=cfg.gravity_aligned, up=np.asarray(cfg.up_axis), seed=cfg.seed,
    )  # fmt: skip


def _clique(
    points_b: np.ndarray,
    points_a: np.ndarray,
    cands: Candidates,
    weights: np.ndarray | None,
    cfg: MatchingConfig,
) -> Alignment | None:
    return clique_alignment(
        points_b, points_a, cands.rows_a, cands.rows_b, weights,
        consistency_threshold_m=cfg.consistency_threshold_m, refine_iterations=cfg.refine_iterations,
        gravity_aligned=cfg.gravity_aligned, up=np.asarray(cfg.up_axis), max_candidates=cfg.max_candidates,
    )  # fmt: skip


OUTLIER_REJECTORS: dict[OutlierMode, OutlierRejector] = {
    OutlierMode.RANSAC: _ransac,
    OutlierMode.CLIQUE: _clique,
}
"""Registry: outlier mode -> (points_b, points_a, candidates, weights, cfg) -> hypothesis with inliers."""


def inlier_threshold_m(cfg: MatchingConfig) -> float:
    """Residual below which a candidate supports the final pose: Alg. 2's T_R, or 2 eps for cliques."""
    if cfg.outlier_mode is OutlierMode.RANSAC:
        return cfg.inlier_threshold_m
    return recheck_threshold_m(cfg.consistency_threshold_m)


def unusable_reason(graph: GraphArrays, name: str) -> str:
    """Why ``graph`` cannot be matched ('' when it can): too few nodes or no edges.

    Raises:
        GraphError: the arrays are inconsistent (lengths, non-finite positions, negative sizes).
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
) -> MatchResult:
    """Find ``T_a_b`` (B's frame -> A's frame) from the semantic graphs of two robots.

    Success needs (1) an unambiguous hypothesis: its support (clique size or RANSAC inliers) at least
    ``min_support_ratio`` times that of the best hypothesis among the candidates it does not explain
    (chance level or a competing alignment), (2) at least ``min_inliers`` one-to-one inliers, (3) an
    inlier RMSE of at most ``max_rmse_m`` and (4) inliers spanning at least ``min_spread_m``
    (``pose.spread_m``). Empty, tiny or edgeless graphs give an unsuccessful result with a reason,
    never an exception.

    Args:
        a, b: the two graphs (positions in each robot's world frame, metres).
        descriptor_cfg: descriptor kind and parameters (ignored for graphs whose descriptors are given).
        matching_cfg: candidate selection, outlier rejection and success criteria.
        descriptors_a, descriptors_b: precomputed ``compute_descriptors`` results (same kind) or None.

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

    cands = match_candidates(da, db, cfg)
    t = lap("matching", t)
    if len(cands) < MIN_NODES:
        reason = f"only {len(cands)} candidate(s) scored above {cfg.score_threshold}"
        return MatchResult.failure(reason, len(cands), timings)

    points_a, points_b = a.positions_xyz[cands.rows_a], b.positions_xyz[cands.rows_b]
    weights = None
    if cfg.weighted_pose:
        weights = correspondence_weights(a.sizes[cands.rows_a], b.sizes[cands.rows_b])
    hypothesis = OUTLIER_REJECTORS[cfg.outlier_mode](points_b, points_a, cands, weights, cfg)
    t = lap("ransac", t)
    if hypothesis is None:
        reason = f"no consistent hypothesis among {len(cands)} candidates"
        return MatchResult.failure(reason, len(cands), timings)

    up = np.asarray(cfg.up_axis)
    # pose (Sec. III-D): the Eq. 2 weighted fit on the hypothesis' inliers, inliers re-selected once more
    final = refine_alignment(
        hypothesis.T_a_b, points_b, points_a, cands.rows_a, cands.rows_b, weights,
        inlier_threshold_m(cfg), 1, cfg.gravity_aligned, up,
    )  # fmt: skip
    spread = spread_m(points_a[final.inliers], cfg.gravity_aligned, up)
    lap("pose", t)

    reason = _rejection_reason(final, spread, hypothesis, cfg)
    rows_a, rows_b = cands.rows_a[final.inliers], cands.rows_b[final.inliers]
    pairs = np.stack([a.node_ids[rows_a], b.node_ids[rows_b]], axis=1)
    return MatchResult(
        success=not reason,
        T_a_b=None if reason else final.T_a_b,
        inliers=np.zeros((0, 2), dtype=np.int64) if reason else pairs.astype(np.int64),
        candidates=len(cands),
        timings_ms=timings,
        rmse_m=final.rmse_m,
        num_inliers=final.num_inliers,
        spread_m=spread,
        support=hypothesis.support,
        rival_support=hypothesis.rival_support,
        T_a_b_hypothesis=final.T_a_b,
        reason=reason,
    )


def _rejection_reason(final: Alignment, spread: float, hypothesis: Alignment, cfg: MatchingConfig) -> str:
    """'' when the alignment is accepted, else why not (the success criteria of ``match_graphs``)."""
    if _ambiguous(hypothesis, cfg):
        return (
            f"ambiguous: support {hypothesis.support} (refined inliers {hypothesis.inlier_support}) is less "
            f"than {cfg.min_support_ratio:g}x the {hypothesis.rival_support} "
            f"({hypothesis.rival_inlier_support}) of the best rival hypothesis"
        )
    if final.num_inliers < cfg.min_inliers:
        return f"{final.num_inliers} inlier(s), fewer than min_inliers={cfg.min_inliers}"
    if final.rmse_m > cfg.max_rmse_m:
        return f"inlier RMSE {final.rmse_m:.2f} m above max_rmse_m={cfg.max_rmse_m}"
    if spread < cfg.min_spread_m:
        return f"inliers span only {spread:.1f} m (degenerate), below min_spread_m={cfg.min_spread_m}"
    return ""


def _ambiguous(h: Alignment, cfg: MatchingConfig) -> bool:
    """True unless the hypothesis clearly beats its rival (``min_support_ratio``) in support (clique size
    or RANSAC inliers), or in refined inlier count while also beating it by ``min_clique_ratio`` in support.

    The second way exists because clique sizes are biased against large graphs (see ``clique``); the
    support guard keeps chance hypotheses whose refit merely collects chance inliers over a large area out.
    For RANSAC the refined counts are the support, so the second way adds nothing.
    """
    if h.support >= cfg.min_support_ratio * h.rival_support:
        return False
    refined_margin = h.inlier_support >= cfg.min_support_ratio * h.rival_inlier_support
    return not (h.inlier_support > 0 and refined_margin and h.support >= cfg.min_clique_ratio * h.rival_support)
