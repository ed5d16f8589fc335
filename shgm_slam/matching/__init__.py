"""Graph matching: candidates (Eq. 1), outlier rejection (Alg. 2 RANSAC or max clique), pose (Eq. 2)."""

from __future__ import annotations

from shgm_slam.matching.candidates import Candidates, match_candidates, select_candidates
from shgm_slam.matching.matcher import judge_alignment, match_graphs
from shgm_slam.matching.pose import Alignment
from shgm_slam.matching.result import MatchResult

__all__ = [
    "Alignment",
    "Candidates",
    "MatchResult",
    "judge_alignment",
    "match_candidates",
    "match_graphs",
    "select_candidates",
]
