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
        success: True when enough consistent, well-spread inliers with a small residual were found.
        T_a_b: (4, 4) float64 mapping B's coordinates into A's frame, or None when not successful.
        inliers: (M, 2) int64 node-id pairs (id_a, id_b) supporting ``T_a_b`` (empty when not successful).
        candidates: number of candidate correspondences after descriptor matching.
        timings_ms: stage timings in milliseconds, keys ``TIMING_KEYS``.
        rmse_m: inlier residual RMSE of the best hypothesis, metres (inf when there is none).
        num_inliers: inliers of the best hypothesis, also when it was rejected (a PR-curve threshold).
        spread_m: spread of the best hypothesis' inliers (``pose.spread_m``).
        support: outlier-stage evidence of the best hypothesis (RANSAC inlier count or clique size).
        rival_support: the same for the best hypothesis among the candidates the winner does not
            explain: the chance level, or a competing alignment when the scene is ambiguous.
        T_a_b_hypothesis: (4, 4) best hypothesis, also when rejected (diagnostics), or None.
        reason: why the match failed (empty on success).
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

    @staticmethod
    def failure(reason: str, candidates: int = 0, timings_ms: dict[str, float] | None = None) -> MatchResult:
        """An unsuccessful result without any hypothesis."""
        timings = {key: 0.0 for key in TIMING_KEYS} | (timings_ms or {})
        return MatchResult(False, None, np.zeros((0, 2), dtype=np.int64), candidates, timings, reason=reason)

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
            "reason": self.reason,
        }
