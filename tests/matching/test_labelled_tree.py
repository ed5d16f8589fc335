"""Same-label radius queries through one KD-tree: labels folded into a fourth coordinate never meet."""

from __future__ import annotations

import numpy as np

from shgm_slam.matching.labelled_tree import LabelledTree, nearest_same_label


def test_the_nearest_node_of_the_same_label_within_the_radius_or_none() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    labels = np.array([8, 17, 8, 17])  # trees and poles side by side
    tree = LabelledTree(positions, labels)
    assert len(tree) == 4
    query = np.array([[0.4, 0.0, 0.0], [0.4, 0.0, 0.0], [9.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    d, rows = nearest_same_label(tree, query, np.array([8, 17, 17, 8, 5]), radius_m=3.0)
    # a tree at 0.4 m finds the tree at 0 (not the nearer pole at 0.5); a pole there the pole at 0.5
    assert rows[:2].tolist() == [0, 3] and np.allclose(d[:2], [0.4, 0.1])
    # beyond the radius, or a label the graph lacks: none (inf, len(tree))
    assert np.isinf(d[2:]).all() and rows[2:].tolist() == [4, 4, 4]


def test_the_any_label_tree_sees_every_node() -> None:
    rng = np.random.default_rng(0)
    positions = rng.uniform(0, 100, (200, 3))
    tree = LabelledTree(positions, rng.integers(0, 19, 200))
    counts = tree.any.query_ball_point(positions[:5], 30.0, return_length=True)
    brute = (np.linalg.norm(positions[:5, None] - positions[None], axis=2) <= 30.0).sum(axis=1)
    assert counts.tolist() == brute.tolist()
