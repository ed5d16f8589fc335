"""The localization benchmark: its scoring functions against hand-computed values, the X-view per-pair
baseline against the vectorised random-walk scores, and a smoke run on tiny worlds (one descriptor)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shgm_slam.bench.localization import BenchMode, BenchOptions, overlap_fraction, run_localization_benchmark
from shgm_slam.bench.localization_metrics import (
    CORRECT_M,
    precision_recall,
    random_transform,
    score_match,
    true_transform,
)
from shgm_slam.bench.xview_baseline import pairwise_walk_similarity, walk_maps
from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors import compute_descriptors, similarity
from shgm_slam.geometry.se3 import make_pose, rot_z
from shgm_slam.matching import MatchResult
from shgm_slam.types import GraphArrays


def _graph(seed: int = 0, n: int = 40) -> GraphArrays:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 60, (n, 3))
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.nonzero(np.triu(d < 15.0, 1))
    return GraphArrays(np.arange(n), rng.choice([2, 5, 8, 13], n), pos, np.ones(n), np.stack([i, j], 1))


def test_precision_recall_matches_hand_counts():
    scores = np.array([20, 15, 12, 9, 5, 3])
    correct = np.array([True, True, False, True, False, False])
    pr = precision_recall(scores, correct)
    t = pr["thresholds"]
    # accept n > T: at T = 12 -> {20, 15} both correct; at T = 9 -> {20, 15, 12}: 2 of 3
    k = t.index(12.0)
    assert pr["precision"][k] == 1.0 and pr["recall"][k] == pytest.approx(2 / 6, abs=1e-4)
    k = t.index(9.0)
    assert pr["precision"][k] == pytest.approx(2 / 3, abs=1e-4)
    # recall 0.35 needs 3 true positives of 6 -> T = 5 (accepts 4, 3 correct): precision 0.75
    assert pr["precision_at_recall"] == pytest.approx(0.75) and pr["threshold_at_recall"] == 5.0
    assert pr["max_recall"] == pytest.approx(0.5)
    assert 0 < pr["best_f1"] <= 1


def test_random_transforms_are_rigid_and_yaw_only_when_asked():
    rng = np.random.default_rng(3)
    for full in (False, True):
        T = random_transform(rng, full)
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        if not full:
            assert np.allclose(R[:, 2], [0, 0, 1]) and abs(T[2, 3]) <= 5.0
    assert np.allclose(true_transform(T) @ T, np.eye(4))


def test_score_match_measures_the_error_at_the_query_centroid():
    b = _graph(1)
    T_true = make_pose(rot_z(0.3), [100.0, -40.0, 2.0])
    c = b.positions_xyz.mean(axis=0)
    # an estimate off by a 25 m shift is wrong; one off by 1 deg about the centroid is right
    shifted = make_pose(np.eye(3), [25.0, 0.0, 0.0]) @ T_true
    about_c = make_pose(np.eye(3), c) @ make_pose(rot_z(np.radians(1.0)), np.zeros(3)) @ make_pose(np.eye(3), -c)
    for T_est, correct in ((shifted, False), (T_true @ about_c, True)):
        result = MatchResult(True, T_est, np.zeros((0, 2), np.int64), 10, num_inliers=7, T_a_b_hypothesis=T_est)
        loc = score_match(result, T_true, b)
        assert loc.correct is correct and (loc.trans_err_m < CORRECT_M) is correct
        assert loc.false_success is (not correct)
    none = score_match(MatchResult.failure("no candidates"), T_true, b)
    assert not none.correct and not np.isfinite(none.trans_err_m)


def test_xview_per_pair_scores_equal_the_vectorised_random_walk_scores():
    a, b = _graph(2), _graph(3)
    cfg = DescriptorConfig(kind=DescriptorKind.RANDOM_WALK, num_walks=50, seed=4)
    per_pair = pairwise_walk_similarity(a, b, walk_maps(a, 50, 3, 4), walk_maps(b, 50, 3, 4))
    vectorised = similarity(compute_descriptors(a, cfg), compute_descriptors(b, cfg))
    assert per_pair.nnz > 0
    assert abs(per_pair - vectorised).max() < 1e-12
    assert all(sum(m.values()) == 50 for m in walk_maps(a, 50, 3, 4))


def test_overlap_fraction_counts_same_label_neighbours():
    a = _graph(5)
    assert overlap_fraction(a, a) == 1.0
    far = a.transformed(make_pose(np.eye(3), [1000.0, 0, 0]))
    assert overlap_fraction(a, far) == 0.0
    relabelled = GraphArrays(a.node_ids, (a.label_ids + 1) % 19, a.positions_xyz, a.sizes, a.edges)
    assert overlap_fraction(a, relabelled) < 0.5


def test_smoke_run_on_tiny_worlds(tmp_path):
    options = BenchOptions.quick_options(
        runs=2, resolution=(160, 48), cache_dir=tmp_path / "cache", kinds=(DescriptorKind.HISTOGRAM,),
        modes=(BenchMode.ROBUST,), window_stride=30, depth_noise_levels=(), label_noise_levels=(),
    )
    messages: list[str] = []
    results = run_localization_benchmark(tmp_path / "out", options, progress=messages.append)
    assert messages and any("Table II" in m for m in messages)
    saved = json.loads((tmp_path / "out" / "localization.json").read_text())
    assert saved["benchmark"] == "localization" and saved["options"]["runs"] == 2
    md = (tmp_path / "out" / "localization.md").read_text()
    for title in ("Table II", "Fig. 5", "Table I", "Fig. 8", "Partial overlap", "Disjoint", "Targets"):
        assert title in md
    assert (tmp_path / "out" / "pr_curve.png").stat().st_size > 1000
    for row in results["table2"]:
        assert row["queries"] == 2 and 0 <= row["good_match_rate"] <= 1
        assert row["successes"] == row["correct_successes"] + row["false_successes"]
    for row in results["figure5"]:
        pr = row["pr"]
        assert all(0 <= p <= 1 for p in pr["precision"]) and all(0 <= r <= 1 for r in pr["recall"])
        assert pr["recall"] == sorted(pr["recall"], reverse=True)  # thresholds increase
    assert {r["group"] for r in results["ablations"]} >= {"connectivity", "path length", "label matching"}
    assert results["disjoint"][0]["whole_runs"] == 2
    # the rendered keyframes are cached: a second scene load reuses them
    assert any(p.name == "meta.json" for p in (tmp_path / "cache").rglob("meta.json"))
