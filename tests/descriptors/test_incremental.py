"""Incremental descriptors equal a full recomputation after every kind of change a growing graph sees."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors import compute_descriptors
from shgm_slam.descriptors.incremental import IncrementalDescriptors, locality_hops
from shgm_slam.graph.semantic_graph import edges_within_radius
from shgm_slam.types import GraphArrays


def _graph(positions: np.ndarray, labels: np.ndarray, radius_m: float = 10.0) -> GraphArrays:
    n = len(labels)
    return GraphArrays(np.arange(n, dtype=np.int64), labels.astype(np.int64), positions, np.ones(n),
                       edges_within_radius(positions, radius_m))  # fmt: skip


def _drive(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes along a 2-D drive with a revisit: positions (n, 3) metres and labels (n,)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 600.0, n)
    xy = np.stack([150 * np.cos(s / 100), 150 * np.sin(s / 100)], axis=1) + rng.normal(0, 6, (n, 2))
    return np.c_[xy, rng.normal(0, 1, n)], rng.integers(0, 19, n)


@pytest.mark.parametrize("kind, path_length", [(DescriptorKind.HISTOGRAM, 3), (DescriptorKind.HISTOGRAM, 4),
                                               (DescriptorKind.NEIGHBOR_VECTOR, 3)])  # fmt: skip
def test_growing_moving_and_relabelled_graph_matches_full_recomputation(kind, path_length):
    cfg = DescriptorConfig(kind=kind, path_length=path_length)
    pos, labels = _drive(700, seed=3)
    rng = np.random.default_rng(4)
    inc = IncrementalDescriptors(cfg)
    n = 0
    recomputed = []
    while n < len(labels):
        n = min(len(labels), n + int(rng.integers(3, 12)))  # a keyframe's new nodes
        moved = rng.choice(n, size=3, replace=False)  # merges move a few nodes (edges change)...
        pos[moved, :2] += rng.normal(0, 4, (3, 2))
        labels[rng.integers(0, n)] = rng.integers(0, 19)  # ...and a label may change
        g = _graph(pos[:n].copy(), labels[:n].copy())
        got = inc.update(g)
        want = compute_descriptors(g, cfg)
        assert (got.counts != want.counts).nnz == 0
        np.testing.assert_array_equal(got.label_ids, want.label_ids)
        recomputed.append(inc.recomputed_rows)
    assert recomputed[0] == len(_graph(pos[: recomputed[0]], labels[: recomputed[0]]))
    assert np.median(recomputed[len(recomputed) // 2:]) < 0.25 * len(labels)  # local, not the whole graph


def test_unchanged_graph_costs_nothing_and_a_reordered_one_is_recomputed():
    cfg = DescriptorConfig()
    pos, labels = _drive(200, seed=5)
    g = _graph(pos, labels)
    inc = IncrementalDescriptors(cfg)
    inc.update(g)
    again = inc.update(g)
    assert (again.counts != compute_descriptors(g, cfg).counts).nnz == 0
    order = np.random.default_rng(0).permutation(len(labels))
    s = _graph(pos[order], labels[order])
    shuffled = GraphArrays(g.node_ids[order], s.label_ids, s.positions_xyz, s.sizes, s.edges)
    got = inc.update(shuffled)
    assert inc.recomputed_rows == len(labels)
    assert (got.counts != compute_descriptors(shuffled, cfg).counts).nnz == 0


def test_random_walks_are_not_local():
    assert locality_hops(DescriptorConfig(kind=DescriptorKind.RANDOM_WALK)) is None
    cfg = DescriptorConfig(kind=DescriptorKind.RANDOM_WALK, num_walks=20)
    pos, labels = _drive(120, seed=6)
    inc = IncrementalDescriptors(cfg)
    inc.update(_graph(pos[:100], labels[:100]))
    got = inc.update(_graph(pos, labels))
    assert inc.recomputed_rows == 120
    assert (got.counts != compute_descriptors(_graph(pos, labels), cfg).counts).nnz == 0


def test_subset_keeps_the_rows_asked_for():
    pos, labels = _drive(50, seed=7)
    d = compute_descriptors(_graph(pos, labels), DescriptorConfig())
    rows = np.array([5, 2, 40])
    sub = d.subset(rows)
    assert len(sub) == 3 and (sub.counts != d.counts[rows]).nnz == 0
    np.testing.assert_array_equal(sub.label_ids, d.label_ids[rows])
