"""Scoring of the localization benchmark: random test transforms, pose errors, good matches, PR curves.

Every simulated graph lives in the one world frame, so the ground-truth ``T_a_b`` is identity. A test
moves graph B by a random rigid transform ``T_b'_b`` (yaw + translation for ground robots, a full
rotation for the UAV case) and asks the matcher for ``T_a_b'``, whose truth is ``inverse(T_b'_b)``.

Errors: the rotation error is the angle of ``T_true^-1 T_est``; the translation error is measured
where it matters, at the centroid of B's nodes (``|T_est c - T_true c|``), so it does not depend on
the arbitrary origin of the random frame. A localization is *correct* when that error is below
``CORRECT_M`` (20 m, the paper's T_p); a correspondence is a *good match* when its two nodes are
within ``GOOD_MATCH_M`` (10 m, the paper's halved threshold) under the ground truth.

Precision-recall (Fig. 5, as the paper and X-view define it): each query reports its best hypothesis
and that hypothesis' inlier count n_q (RANSAC inliers or re-checked clique inliers). At threshold
T_r a query is *accepted* when n_q > T_r; it is a true positive when accepted and correct.
precision(T_r) = TP / accepted, recall(T_r) = TP / queries (every query overlaps the reference map,
so every query could be localized). The success rate at recall 0.35 is the interpolated precision
there: the best precision among thresholds reaching recall >= 0.35.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.geometry.se3 import inverse, make_pose, pose_error, rot_z
from shgm_slam.matching import MatchResult
from shgm_slam.types import GraphArrays

CORRECT_M = 20.0
"""A localization is correct when its translation error is below this (paper: T_p = 20 m)."""

GOOD_MATCH_M = 10.0
"""A correspondence is good when its nodes are this close under the ground truth (paper: 10 m)."""

OPERATING_RECALL = 0.35
"""Recall of the paper's (and X-view's) operating point."""


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation drawn uniformly from SO(3) (normalised Gaussian quaternion)."""
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def random_transform(rng: np.random.Generator, full_rotation: bool, max_translation_m: float = 300.0) -> np.ndarray:
    """(4, 4) random rigid ``T_b'_b``: a uniform yaw about world z (or a uniform 3D rotation) and a
    translation uniform in [-max, max] horizontally (vertically +-5 m for ground robots, +-max otherwise)."""
    R = random_rotation(rng) if full_rotation else rot_z(rng.uniform(-np.pi, np.pi))
    t = rng.uniform(-max_translation_m, max_translation_m, 3)
    if not full_rotation:
        t[2] = rng.uniform(-5.0, 5.0)
    return make_pose(R, t)


@dataclass
class Localization:
    """One scored match: the verdict, the hypothesis' errors and the evidence.

    Attributes:
        success: the matcher accepted the match.
        correct: the best hypothesis (accepted or not) is within ``CORRECT_M`` of the truth.
        trans_err_m, rot_err_deg: errors of the best hypothesis (inf when there is none).
        num_inliers: inliers of the best hypothesis (the PR-curve score).
        candidates: candidate correspondences after descriptor matching.
        timings_ms: the matcher's stage timings.
    """

    success: bool
    correct: bool
    trans_err_m: float
    rot_err_deg: float
    num_inliers: int
    candidates: int
    timings_ms: dict[str, float]

    @property
    def false_success(self) -> bool:
        return self.success and not self.correct

    def to_json(self) -> dict:
        finite = np.isfinite(self.trans_err_m)
        return {
            "success": self.success, "correct": self.correct,
            "trans_err_m": round(float(self.trans_err_m), 3) if finite else None,
            "rot_err_deg": round(float(self.rot_err_deg), 3) if finite else None,
            "num_inliers": self.num_inliers, "candidates": self.candidates,
            "total_ms": round(self.timings_ms.get("total", 0.0), 3),
        }  # fmt: skip


def score_match(result: MatchResult, T_true_a_b: np.ndarray, graph_b: GraphArrays) -> Localization:
    """Score ``result`` against the true ``T_a_b`` (4, 4); errors at the centroid of ``graph_b``'s nodes."""
    T = result.T_a_b_hypothesis
    if T is None:
        trans, rot = np.inf, np.inf
    else:
        c = graph_b.positions_xyz.mean(axis=0) if len(graph_b) else np.zeros(3)
        trans = float(np.linalg.norm((T[:3, :3] @ c + T[:3, 3]) - (T_true_a_b[:3, :3] @ c + T_true_a_b[:3, 3])))
        rot = float(pose_error(T, T_true_a_b)[1])
    return Localization(
        bool(result.success), bool(trans < CORRECT_M), trans, rot, int(result.num_inliers),
        int(result.candidates), dict(result.timings_ms),
    )  # fmt: skip


def good_matches(graph_a: GraphArrays, graph_b: GraphArrays, rows_a: np.ndarray, rows_b: np.ndarray,
                 T_true_a_b: np.ndarray) -> int:
    """How many correspondences (rows_a[k], rows_b[k]) are within ``GOOD_MATCH_M`` under the truth."""
    if len(rows_a) == 0:
        return 0
    pb = graph_b.positions_xyz[rows_b] @ T_true_a_b[:3, :3].T + T_true_a_b[:3, 3]
    return int(np.sum(np.linalg.norm(graph_a.positions_xyz[rows_a] - pb, axis=1) < GOOD_MATCH_M))


def true_transform(T_moved_b: np.ndarray) -> np.ndarray:
    """The true ``T_a_b'`` after B was moved by ``T_b'_b`` (the simulated ``T_a_b`` is identity)."""
    return inverse(T_moved_b)


def precision_recall(scores: np.ndarray, correct: np.ndarray) -> dict:
    """PR curve over the acceptance threshold on per-query scores (module docstring).

    Args:
        scores: (Q,) inlier counts n_q.
        correct: (Q,) bool, the query's hypothesis is correct.

    Returns:
        ``thresholds`` (accept n_q > T_r), ``precision``, ``recall`` (lists, increasing threshold),
        ``precision_at_recall`` (interpolated at ``OPERATING_RECALL``, None when never reached),
        ``threshold_at_recall``, ``best_f1`` and its threshold, ``max_recall``.
    """
    scores = np.asarray(scores, dtype=float)
    correct = np.asarray(correct, dtype=bool)
    q = scores.size
    thresholds = np.unique(np.concatenate([[-1.0], scores]))[:-1] if q else np.zeros(0)
    accepted = scores[None, :] > thresholds[:, None]
    tp = (accepted & correct[None, :]).sum(axis=1)
    n_acc = accepted.sum(axis=1)
    precision = np.where(n_acc > 0, tp / np.maximum(n_acc, 1), 1.0)
    recall = tp / max(q, 1)
    f1 = np.where(tp > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    reach = recall >= OPERATING_RECALL
    p_at = t_at = None
    if reach.any():
        i = int(np.flatnonzero(reach)[np.argmax(precision[reach])])
        p_at, t_at = float(precision[i]), float(thresholds[i])
    best = int(np.argmax(f1)) if f1.size else 0
    return {
        "thresholds": thresholds.tolist(),
        "precision": np.round(precision, 4).tolist(),
        "recall": np.round(recall, 4).tolist(),
        "precision_at_recall": p_at,
        "threshold_at_recall": t_at,
        "best_f1": float(f1[best]) if f1.size else 0.0,
        "best_f1_threshold": float(thresholds[best]) if f1.size else None,
        "max_recall": float(recall.max()) if recall.size else 0.0,
    }


def mean_std(values: list[float] | np.ndarray) -> tuple[float | None, float | None]:
    """Mean and standard deviation of the finite values (None, None when there are none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None, None
    return float(v.mean()), float(v.std())
