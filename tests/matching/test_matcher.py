"""End-to-end graph matching: known transforms, clean failures, the JSON result form."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shgm_slam.config import DescriptorConfig, DescriptorKind, MatchingConfig, OutlierMode
from shgm_slam.descriptors import compute_descriptors
from shgm_slam.errors import ConfigError, GraphError
from shgm_slam.geometry.se3 import pose_error, transform_points
from shgm_slam.matching import match_graphs
from shgm_slam.matching.matcher import transform_points_each
from shgm_slam.matching.result import TIMING_KEYS
from shgm_slam.types import GraphArrays

from .synthetic import city_pair

MODES = [OutlierMode.CLIQUE, OutlierMode.RANSAC]


def _displacement_m(T_est: np.ndarray, T_true: np.ndarray, b: GraphArrays) -> float:
    """Mean distance between B's nodes mapped by the estimate and by the truth (metres)."""
    p = b.positions_xyz
    return float(np.linalg.norm(transform_points(T_est, p) - transform_points(T_true, p), axis=1).mean())


@pytest.fixture(scope="module")
def overlapping():
    return city_pair(seed=0, overlap=True)


@pytest.mark.parametrize("mode", MODES)
def test_overlapping_graphs_match_with_the_true_transform(overlapping, mode):
    a, b, T_a_b = overlapping
    r = match_graphs(a, b, DescriptorConfig(), MatchingConfig(outlier_mode=mode))
    assert r.success, r.reason
    _, dr = pose_error(r.T_a_b, T_a_b)
    assert dr < 1.0 and _displacement_m(r.T_a_b, T_a_b, b) < 1.0  # node noise: 0.3 m per axis and graph
    assert r.inliers.shape[1] == 2 and r.inliers.shape[0] == r.num_inliers >= 20
    true_pair = r.inliers[:, 1] - 100_000 == r.inliers[:, 0]  # city_pair ids: b = a + 100000
    assert true_pair.mean() > (0.95 if mode is OutlierMode.CLIQUE else 0.8)  # RANSAC: 10 m admits neighbours
    assert r.rmse_m < (1.0 if mode is OutlierMode.CLIQUE else 3.0) and r.spread_m > 20
    assert r.llr > r.llr_threshold and r.expected_chance < r.num_inliers / 4  # far beyond chance
    assert r.overlap_a >= r.num_inliers and r.overlap_b >= r.num_inliers
    assert set(r.timings_ms) == set(TIMING_KEYS)
    assert r.timings_ms["total"] >= r.timings_ms["ransac"] >= 0


@pytest.mark.parametrize("kind", [DescriptorKind.NEIGHBOR_VECTOR, DescriptorKind.RANDOM_WALK])
def test_baseline_descriptors_run_end_to_end(overlapping, kind):
    a, b, T_a_b = overlapping
    r = match_graphs(a, b, DescriptorConfig(kind=kind), MatchingConfig())
    assert r.candidates > 0
    if r.success:  # the baselines may fail, but must never succeed wrongly
        assert _displacement_m(r.T_a_b, T_a_b, b) < 1.0


@pytest.mark.parametrize("mode", MODES)
def test_graphs_of_different_places_do_not_match(mode):
    for seed in range(3):
        a, b, _ = city_pair(seed=10 + seed, overlap=False)
        r = match_graphs(a, b, DescriptorConfig(), MatchingConfig(outlier_mode=mode))
        assert not r.success, f"seed {seed}: wrong success with {r.num_inliers} inliers"
        assert r.T_a_b is None and r.inliers.shape == (0, 2) and r.reason


def _tiny(n: int, edges) -> GraphArrays:
    return GraphArrays(np.arange(n), np.full(n, 13), np.arange(3 * n, dtype=float).reshape(n, 3) * 3,
                       np.ones(n), np.asarray(edges, dtype=np.int64).reshape(-1, 2))  # fmt: skip


@pytest.mark.parametrize(
    ("graph", "reason"),
    [(_tiny(0, []), "0 node"), (_tiny(2, [[0, 1]]), "2 node"), (_tiny(5, []), "no edges")],
)
def test_unusable_graphs_fail_cleanly(overlapping, graph, reason):
    a, _, _ = overlapping
    for first, second in ((graph, a), (a, graph)):
        r = match_graphs(first, second, DescriptorConfig(), MatchingConfig())
        assert not r.success and reason in r.reason
        assert json.loads(json.dumps(r.to_json_dict()))["T_a_b"] is None


def test_graphs_without_candidates_fail_cleanly():
    a = _tiny(4, [[0, 1], [1, 2], [2, 3]])
    b = GraphArrays(a.node_ids, np.full(4, 5), a.positions_xyz, a.sizes, a.edges)  # all poles: no same label
    r = match_graphs(a, b, DescriptorConfig(), MatchingConfig())
    assert not r.success and r.candidates == 0 and "candidate" in r.reason


def test_malformed_graph_raises_graph_error(overlapping):
    a, _, _ = overlapping
    bad = GraphArrays(a.node_ids, a.label_ids, a.positions_xyz[:, :2], a.sizes, a.edges)
    with pytest.raises(GraphError, match="disagree"):
        match_graphs(a, bad, DescriptorConfig(), MatchingConfig())
    nan = GraphArrays(a.node_ids, a.label_ids, a.positions_xyz * np.nan, a.sizes, a.edges)
    with pytest.raises(GraphError, match="non-finite"):
        match_graphs(nan, a, DescriptorConfig(), MatchingConfig())


def test_precomputed_descriptors_give_the_same_result(overlapping):
    a, b, _ = overlapping
    cfg_d, cfg_m = DescriptorConfig(), MatchingConfig()
    da, db = compute_descriptors(a, cfg_d), compute_descriptors(b, cfg_d)
    direct = match_graphs(a, b, cfg_d, cfg_m)
    cached = match_graphs(a, b, cfg_d, cfg_m, descriptors_a=da, descriptors_b=db)
    np.testing.assert_array_equal(direct.T_a_b, cached.T_a_b)
    np.testing.assert_array_equal(direct.inliers, cached.inliers)
    with pytest.raises(GraphError, match="precomputed descriptors"):
        match_graphs(a, b, cfg_d, cfg_m, descriptors_a=db)


def test_json_form_is_the_architecture_one(overlapping):
    a, b, _ = overlapping
    doc = match_graphs(a, b, DescriptorConfig(), MatchingConfig()).to_json_dict()
    assert list(doc)[:5] == ["success", "T_a_b", "inliers", "candidates", "timings_ms"]
    text = json.dumps(doc)
    back = json.loads(text)
    assert back["success"] is True
    assert np.asarray(back["T_a_b"]).shape == (4, 4)
    assert all(isinstance(x, int) for pair in back["inliers"] for x in pair)
    assert isinstance(back["candidates"], int)
    assert set(back["timings_ms"]) == set(TIMING_KEYS)


def test_gravity_aligned_matching(overlapping):
    a, b, T_a_b = overlapping
    r = match_graphs(a, b, DescriptorConfig(), MatchingConfig(gravity_aligned=True))
    assert r.success, r.reason
    up = np.array([0.0, -1.0, 0.0])
    np.testing.assert_allclose(r.T_a_b[:3, :3] @ up, up, atol=1e-12)  # a yaw about the shared up axis
    assert _displacement_m(r.T_a_b, T_a_b, b) < 1.0
    with pytest.raises(ValueError, match="up_axis"):  # refused by the config itself
        MatchingConfig(gravity_aligned=True, up_axis=(0.0, 0.0, 0.0))
    unchecked = MatchingConfig(gravity_aligned=True).model_copy(update={"up_axis": (0.0, 0.0, 0.0)})
    with pytest.raises(ConfigError, match="up_axis"):  # and by the matcher, for configs built without checks
        match_graphs(a, b, DescriptorConfig(), unchecked)


def test_transform_points_each_has_the_bits_of_one_transform_at_a_time():
    rng = np.random.default_rng(9)
    for _ in range(200):
        Ts = rng.normal(size=(int(rng.integers(1, 6)), 4, 4)) * 10 ** rng.uniform(-2, 3)
        points = rng.normal(size=(int(rng.integers(1, 160)), 3)) * 10 ** rng.uniform(-1, 4)
        expected = np.stack([transform_points(T, points) for T in Ts])
        np.testing.assert_array_equal(transform_points_each(Ts, points), expected)
