"""X-view random walks: valid non-backtracking walks, and shared-walk counting on tiny graphs."""

from __future__ import annotations

import numpy as np

from shgm_slam.descriptors.random_walk import (
    encode_walks,
    random_walk_descriptors,
    random_walks,
    shared_walk_counts,
)
from shgm_slam.labels import NUM_CLASSES, Label
from shgm_slam.types import GraphArrays


def _graph(labels, edges) -> GraphArrays:
    n = len(labels)
    return GraphArrays(
        np.arange(n), np.asarray(labels), np.zeros((n, 3)), np.ones(n), np.asarray(edges).reshape(-1, 2)
    )


def test_walks_follow_edges_and_do_not_backtrack():
    rng = np.random.default_rng(0)
    n = 25
    edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.15])
    g = _graph(rng.integers(0, NUM_CLASSES, n), edges)
    adjacency = np.zeros((n, n), dtype=bool)
    adjacency[edges[:, 0], edges[:, 1]] = adjacency[edges[:, 1], edges[:, 0]] = True
    degree = adjacency.sum(axis=1)
    walks = random_walks(g, num_walks=50, walk_length=4, seed=1)
    assert walks.shape == (n, 50, 4)
    full = np.concatenate([np.broadcast_to(np.arange(n)[:, None, None], (n, 50, 1)), walks], axis=2)
    prev, cur = full[..., :-1], full[..., 1:]
    assert np.all(adjacency[prev, cur] | ((degree[prev] == 0) & (prev == cur)))  # follow an edge or stay put
    two_back, mid, after = full[..., :-2], full[..., 1:-1], full[..., 2:]
    assert np.all((after != two_back) | (degree[mid] <= 1))  # back only out of a dead end
    np.testing.assert_array_equal(random_walks(g, 50, 4, seed=1), walks)  # deterministic by seed


def test_descriptor_rows_count_num_walks():
    g = _graph([Label.CAR, Label.POLE, Label.CAR, Label.BUILDING], [[0, 1], [1, 2], [2, 3]])
    D = random_walk_descriptors(g, num_walks=400, walk_length=3, seed=0)
    assert D.shape == (4, NUM_CLASSES**3)
    np.testing.assert_array_equal(np.asarray(D.sum(axis=1)).ravel(), 400)


def test_shared_walk_counts_on_a_path_graph():
    """Path 0-1-2-3: the end nodes' non-backtracking walks are deterministic, node 1 has two kinds."""
    labels = [Label.CAR, Label.POLE, Label.BUILDING, Label.VEGETATION]
    g = _graph(labels, [[0, 1], [1, 2], [2, 3]])
    walks = random_walks(g, num_walks=400, walk_length=3, seed=5)
    assert np.all(walks[0] == [1, 2, 3]) and np.all(walks[3] == [2, 1, 0])
    kinds = {tuple(w) for w in walks[1]}
    assert kinds == {(0, 1, 2), (2, 3, 2)}  # 1->0 bounces back at the dead end, then avoids 0

    D = random_walk_descriptors(g, 400, 3, seed=5)
    shared = shared_walk_counts(D, D).toarray()
    assert shared[0, 0] == 400 * 400  # every pair of node 0's identical walks
    assert shared[0, 3] == 0  # label sequences differ
    codes = encode_walks(walks, g.label_ids)
    for i in range(4):  # brute force: count identical (walk of i, walk of j) pairs
        for j in range(4):
            assert shared[i, j] == np.sum(codes[i][:, None] == codes[j][None, :])
    n_first = int(np.sum(np.all(walks[1] == [0, 1, 2], axis=1)))
    assert 100 < n_first < 300
    assert shared[1, 1] == n_first**2 + (400 - n_first) ** 2


def test_isolated_node_walks_stay_in_place():
    g = _graph([Label.CAR, Label.POLE, Label.SKY], [[0, 1]])
    walks = random_walks(g, 10, 3, seed=0)
    assert np.all(walks[2] == 2)
    assert np.all(walks[0] == [1, 0, 1])  # dead ends force the walk back
