"""The result of matching two semantic graphs (what ``shgm-slam match --json`` prints)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

TIMING_KEYS = ("descriptors", "matching", "ransac", "pose", "total")
"""Keys of ``MatchResult.timings_ms``; "ransac" is the outlier-rejection stage in either mode."""


@dataclass
class MatchResult:
    """Outcome of ``match_graphs``: a transform only when the evidence is sufficient.

    Attributes:
        success: True when the alignment's evidence is far beyond chance (``verification``) and its
            partners are enough, well spread and with a small residual.
        T_a_b: (4, 4) float64 mapping B's coordinates into A's frame, or None when not successful.
        inliers: (M, 2) int64 node-id pairs (id_a, id_b) supporting ``T_a_b``: same-label partners within the
            verification radius, one-to-one (empty when not successful).
        candidates: number of candidate correspondences after descriptor matching.
        timings_ms: stage timings in milliseconds, keys ``TIMING_KEYS``.
        rmse_m: partner residual RMSE of the best hypothesis, metres (inf when there is none).
        num_inliers: partners of the best hypothesis, also when it was rejected (a PR-curve threshold).
        spread_m: spread of the best hypothesis' partners (``pose.spread_m``).
        support: partner pairs of the best hypothesis (= ``num_inliers``).
        rival_support: partner pairs of the best hypothesis that places B elsewhere (0 without one).
        T_a_b_hypothesis: (4, 4) best hypothesis, also when rejected (diagnostics), or None.
        reason: why the match failed (empty on success).
        expected_chance: B's overlapping nodes expected to find a partner by chance (local label density).
        overlap_a, overlap_b: nodes of A (B) inside the area the other robot observed.
        contradictions: overlapping nodes (both sides) without a partner.
        llr: log likelihood ratio, alignment against chance (nats; the smaller of both directions).
        llr_threshold: ``log(hypotheses searched / false_alarm_rate)``; success needs ``llr`` above it.
        rival_llr: ``llr`` of the rival hypothesis (-inf without one).
        hypotheses: alignment hypotheses generated (cliques, or 1 for RANSAC).
        covariance: (K, K) covariance of an accepted ``T_a_b`` (``precision.alignment_covariance``: the left
            perturbation in A's frame, (theta about the up axis, tx, ty, tz) gravity-aligned, else (wx, wy, wz,
            tx, ty, tz); rad and metres), or None.
        centroid_sigma_m: the RMS error that covariance predicts at B's node centroid (mapped into A), metres
            (NaN without one): a small turn fitted on a short overlap moves B's far end most.
    """

    success: bool
    T_a_b: np.ndarray | None
    inliers: np.ndarray
    candidates: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    rmse_m: float = math.inf
    num_inliers: int = 0
    spread_m: float = 0.0
    support: int = 0
    rival_support: int = 0
    T_a_b_hypothesis: np.ndarray | None = None
    reason: str = ""
    expected_chance: float = 0.0
    overlap_a: int = 0
    overlap_b: int = 0
    contradictions: int = 0
    llr: float = -math.inf
    llr_threshold: float = math.inf
    rival_llr: float = -math.inf
    hypotheses: int = 0
    covariance: np.ndarray | None = None
    centroid_sigma_m: float = math.nan

    @staticmethod
    def failure(reason: str, candidates: int = 0, timings_ms: dict[str, float] | None = None) -> MatchResult:
        """An unsuccessful result without any hypothesis."""
        timings = {key: 0.0 for key in TIMING_KEYS} | (timings_ms or {})
        return MatchResult(False, None, np.zeros((0, 2), dtype=np.int64), candidates, timings, reason=reason)

    def evidence_bar(self, tried: int = 1) -> float:
        """The log likelihood ratio a match must reach to count as one piece of evidence, nats: its chance
        threshold plus the log of the matches tried between the same two robots (the one being decided
        included; 1 for a single ``shgm-slam match``)."""
        return self.llr_threshold + math.log(max(int(tried), 1))

    def is_marginal(self, tried: int = 1) -> bool:
        """Whether this match's log likelihood ratio stays below ``evidence_bar(tried)``: it clears its threshold
        by less than the log of the matches tried (computed as the map server always has, margin against log)."""
        return self.llr - self.llr_threshold < math.log(max(int(tried), 1))

    def is_decisive(self, pieces: int, tried: int = 1) -> bool:
        """Whether this match alone is as unlikely under chance as ``pieces`` independent ones together: its
        log likelihood ratio reaches ``pieces`` times ``evidence_bar(tried)`` (``backend.decisive_match``; the
        map server asks with ``backend.min_closures_to_anchor`` pieces, the number that places a robot)."""
        return self.success and pieces > 1 and self.llr >= pieces * self.evidence_bar(tried)

    def to_json_dict(self) -> dict[str, Any]:
        """The ARCHITECTURE.md match JSON: success, T_a_b, inliers, candidates, timings_ms, then extras."""
        return {
            "success": bool(self.success),
            "T_a_b": None if self.T_a_b is None else np.asarray(self.T_a_b, dtype=float).tolist(),
            "inliers": np.asarray(self.inliers, dtype=np.int64).reshape(-1, 2).tolist(),
            "candidates": int(self.candidates),
            "timings_ms": {key: round(float(value), 4) for key, value in self.timings_ms.items()},
            "num_inliers": int(self.num_inliers),
            "rmse_m": None if not math.isfinite(self.rmse_m) else round(float(self.rmse_m), 4),
            "spread_m": round(float(self.spread_m), 4),
            "support": int(self.support),
            "rival_support": int(self.rival_support),
            "verification": {
                "expected_chance": round(float(self.expected_chance), 3),
                "overlap_a": int(self.overlap_a),
                "overlap_b": int(self.overlap_b),
                "contradictions": int(self.contradictions),
                "llr": _finite(self.llr),
                "llr_threshold": _finite(self.llr_threshold),
                "rival_llr": _finite(self.rival_llr),
                "hypotheses": int(self.hypotheses),
            },
            "precision": {
                "covariance": None if self.covariance is None else np.round(self.covariance, 9).tolist(),
                "centroid_sigma_m": _finite(self.centroid_sigma_m),
            },
            "reason": self.reason,
        }


def _finite(x: float) -> float | None:
    """JSON-safe: rounded, None when not finite."""
    return round(float(x), 3) if math.isfinite(x) else None
