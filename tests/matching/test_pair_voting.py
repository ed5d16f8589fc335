"""Pair voting: the true gravity-aligned alignment is among the most-voted cells where descriptors fail;
deterministic; cheap on city-sized graphs; nothing to vote on gives nothing."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import DescriptorConfig, MatchingConfig
from shgm_slam.geometry.se3 import inverse, make_pose, pose_error, rot_y, transform_points
from shgm_slam.labels import Label
from shgm_slam.matching import match_graphs, pair_voting
from shgm_slam.matching.pair_voting import pair_vote_hypotheses

from .synthetic import graph_of

UP = np.array([0.0, -1.0, 0.0])  # KITTI camera frame
LABELS = np.array([Label.VEGETATION, Label.POLE, Label.TRAFFIC_SIGN, Label.TRAFFIC_LIGHT, Label.BUILDING])


def _street_objects(rng: np.random.Generator, length_m: float = 250.0, num: int = 90):
    """Map-class objects along a street running along x (ground plane x-z, y = -height)."""
    x = rng.uniform(0.0, length_m, num)
    z = rng.choice([-1.0, 1.0], num) * rng.uniform(4.0, 25.0, num)
    pos = np.column_stack([x, -rng.uniform(2.0, 8.0, num), z])
    return pos, rng.choice(LABELS, num, p=[0.45, 0.2, 0.15, 0.05, 0.15]).astype(np.int64)


def _map(pos, labels, rng, miss: float, noise_m: float, T_robot_world: np.ndarray, id_offset: int):
    """A robot's sparse map: ``miss`` of the objects missed, ``noise_m`` of horizontal centroid noise per axis."""
    keep = np.flatnonzero(rng.random(len(pos)) >= miss)
    noise = rng.normal(0.0, noise_m, (keep.size, 3)) * [1.0, 0.3, 1.0]
    p = transform_points(T_robot_world, pos[keep] + noise)
    return graph_of(p, labels[keep], np.ones(keep.size), keep + id_offset)


def _pair(seed: int, miss: float = 0.45, noise_m: float = 1.0):
    rng = np.random.default_rng(seed)
    pos, labels = _street_objects(rng)
    T_b_world = make_pose(rot_y(rng.uniform(-np.pi, np.pi)), np.r_[rng.uniform(-150, 150), 0.5, rng.uniform(-150, 150)])
    a = _map(pos, labels, rng, miss, noise_m, np.eye(4), 0)
    b = _map(pos, labels, rng, miss, noise_m, T_b_world, 100_000)
    return a, b, inverse(T_b_world)


def _error_at(T: np.ndarray, T_true: np.ndarray, points_b: np.ndarray) -> float:
    """Where B's centroid lands under T against the truth, metres."""
    c = points_b.mean(axis=0, keepdims=True)
    return float(np.linalg.norm(transform_points(T, c) - transform_points(T_true, c)))


@pytest.mark.parametrize("seed", range(6))
def test_the_true_alignment_is_among_the_most_voted(seed):
    """Sparse noisy maps of one street (45 % missed, 1 m of noise per axis): among the four most-voted cells
    one lands B's centroid within 3 m and its heading within 5 degrees of the truth."""
    a, b, T_true = _pair(seed)
    hyps = pair_vote_hypotheses(b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, UP,
                                tolerance_m=3.0, count=4)  # fmt: skip
    assert 1 <= len(hyps) <= 4
    for T in hyps:  # each a rotation about up and a translation
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(T[:3, :3] @ UP, UP, atol=1e-9)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    errors = [(_error_at(T, T_true, b.positions_xyz), pose_error(T, T_true)[1]) for T in hyps]
    assert any(dt < 3.0 and dr < 5.0 for dt, dr in errors), errors


def test_votes_are_deterministic_and_independent_of_node_order():
    """The same graphs give the same hypotheses; shuffled node order gives the same cells (to rounding)."""
    a, b, _ = _pair(3)
    args = dict(tolerance_m=3.0, count=4)
    first = pair_vote_hypotheses(b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, UP, **args)
    again = pair_vote_hypotheses(b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, UP, **args)
    for x, y in zip(first, again, strict=True):
        np.testing.assert_array_equal(x, y)
    perm_a = np.random.default_rng(0).permutation(len(a))
    perm_b = np.random.default_rng(1).permutation(len(b))
    shuffled = pair_vote_hypotheses(b.positions_xyz[perm_b], b.label_ids[perm_b], a.positions_xyz[perm_a],
                                    a.label_ids[perm_a], UP, **args)  # fmt: skip
    np.testing.assert_allclose(np.stack(shuffled)[:1], np.stack(first)[:1], atol=1e-6)


def test_too_few_or_unlike_nodes_give_no_hypothesis():
    """No segment long enough, or no same-label segment of matching length: nothing to vote on."""
    near = np.array([[0.0, 0, 0], [2.0, 0, 0], [4.0, 0, 1.0]])
    labels = np.full(3, Label.POLE, dtype=np.int64)
    assert pair_vote_hypotheses(near, labels, near, labels, UP, tolerance_m=3.0, count=4) == []
    far = np.array([[0.0, 0, 0], [20.0, 0, 0]])
    poles, trees = np.full(2, Label.POLE, dtype=np.int64), np.full(2, Label.VEGETATION, dtype=np.int64)
    assert pair_vote_hypotheses(far, poles, far, trees, UP, tolerance_m=3.0, count=4) == []
    assert pair_vote_hypotheses(far, poles, far, poles, UP, tolerance_m=3.0, count=0) == []


def test_the_vote_budget_thins_segments_and_still_finds_the_truth(monkeypatch):
    """With the votes capped far below what the graphs cast, B's segments are thinned evenly and the true
    cell still wins (it collects votes from every pair of true partners)."""
    a, b, T_true = _pair(1, miss=0.2, noise_m=0.5)
    full = pair_vote_hypotheses(b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, UP, tolerance_m=3.0,
                                count=1)  # fmt: skip
    monkeypatch.setattr(pair_voting, "MAX_VOTES", 2000)
    thinned = pair_vote_hypotheses(b.positions_xyz, b.label_ids, a.positions_xyz, a.label_ids, UP,
                                   tolerance_m=3.0, count=1)  # fmt: skip
    for T in (full[0], thinned[0]):
        assert _error_at(T, T_true, b.positions_xyz) < 3.0


def test_matching_uses_the_votes_only_when_asked():
    """``vote_hypotheses`` adds hypotheses to the search (counted in the chance threshold); 0 leaves the
    matcher as it was; the result is right either way on an easy pair."""
    a, b, T_true = _pair(2, miss=0.3, noise_m=0.5)
    cfg = MatchingConfig(gravity_aligned=True, up_axis=tuple(UP))
    with_votes = match_graphs(a, b, DescriptorConfig(), cfg)
    without = match_graphs(a, b, DescriptorConfig(), cfg.model_copy(update={"vote_hypotheses": 0}))
    assert with_votes.hypotheses == without.hypotheses + cfg.vote_hypotheses
    assert with_votes.llr_threshold > without.llr_threshold
    for r in (with_votes, without):
        assert r.success, r.reason
        assert _error_at(r.T_a_b, T_true, b.positions_xyz) < 2.0


@pytest.mark.parametrize("rows", [1, 2, 3, 8, 9])
def test_column_medians_are_numpys_to_the_bit(rows):
    values = np.random.default_rng(rows).normal(0.0, 50.0, (rows, 3))
    np.testing.assert_array_equal(pair_voting._column_medians(values), np.median(values, axis=0))


def test_each_vote_carries_the_mean_rise_of_its_two_ends():
    rng = np.random.default_rng(3)
    points = rng.uniform(-40.0, 40.0, (30, 3)) * np.array([1.0, 1.0, 0.1])
    labels = rng.integers(0, 3, 30)
    seg_b = pair_voting._Segments.of(points, labels, ordered=False)
    seg_a = pair_voting._Segments.of(points + np.array([0.0, 0.0, 2.0]), labels, ordered=True)
    rows_b, rows_a, rise = pair_voting._agreeing(seg_b, seg_a, 3.0)
    assert rows_b.size > 0
    expected = np.column_stack([seg_a.heights[k][rows_a] - seg_b.heights[k][rows_b] for k in (0, 1)]).mean(axis=1)
    np.testing.assert_allclose(rise, expected, rtol=0, atol=0)
