"""Alg. 1 semantic histograms against hand counts and a brute-force path enumeration."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.descriptors.histogram import semantic_histogram, with_own_label
from shgm_slam.descriptors.neighbor_vector import neighbor_vector
from shgm_slam.errors import GraphError
from shgm_slam.labels import NUM_CLASSES, Label
from shgm_slam.types import GraphArrays

C = NUM_CLASSES


def _graph(labels, edges, positions=None) -> GraphArrays:
    n = len(labels)
    pos = np.zeros((n, 3)) if positions is None else positions
    return GraphArrays(
        np.arange(n) + 10, np.asarray(labels), pos, np.ones(n), np.asarray(edges).reshape(-1, 2)
    )


# 0 building - 1 pole; 1 - 2 vegetation; 1 - 3 car; 2 - 3
HAND = _graph([Label.BUILDING, Label.POLE, Label.VEGETATION, Label.CAR], [[0, 1], [1, 2], [1, 3], [2, 3]])
B, P, V, K = Label.BUILDING, Label.POLE, Label.VEGETATION, Label.CAR

HAND_COUNTS = {  # (path_length, backtracking) -> {node: {labels after node i: count}}
    (2, True): {0: {(P,): 1}, 1: {(B,): 1, (V,): 1, (K,): 1}},
    (3, True): {
        0: {(P, B): 1, (P, V): 1, (P, K): 1},
        1: {(B, P): 1, (V, P): 1, (V, K): 1, (K, P): 1, (K, V): 1},
    },
    (3, False): {0: {(P, V): 1, (P, K): 1}, 1: {(V, K): 1, (K, V): 1}},
    (4, True): {0: {(P, B, P): 1, (P, V, P): 1, (P, V, K): 1, (P, K, P): 1, (P, K, V): 1}},
    (4, False): {0: {(P, V, K): 1, (P, K, V): 1}},
}


def _bin(labels: tuple[int, ...]) -> int:
    code = 0
    for label in labels:
        code = code * C + int(label)
    return code


@pytest.mark.parametrize("key", sorted(HAND_COUNTS))
def test_histogram_equals_hand_counts(key):
    path_length, backtracking = key
    H = semantic_histogram(HAND, path_length, backtracking).toarray()
    assert H.shape == (4, C ** (path_length - 1))
    for node, counts in HAND_COUNTS[key].items():
        expected = np.zeros(C ** (path_length - 1))
        for labels, count in counts.items():
            expected[_bin(labels)] += count
        np.testing.assert_array_equal(H[node], expected)


def _brute_force(graph: GraphArrays, path_length: int, backtracking: bool) -> np.ndarray:
    """Enumerate every walk i -> v1 -> ... explicitly (the loops of Alg. 1)."""
    neighbors = {i: set() for i in range(len(graph))}
    for i, j in graph.edges:
        neighbors[int(i)].add(int(j))
        neighbors[int(j)].add(int(i))
    H = np.zeros((len(graph), C ** (path_length - 1)))

    def walk(start: int, path: list[int]) -> None:
        if len(path) == path_length:
            H[start, _bin(tuple(graph.label_ids[v] for v in path[1:]))] += 1
            return
        for m in neighbors[path[-1]]:
            if backtracking or len(path) < 2 or m != path[-2]:
                walk(start, [*path, m])

    for i in range(len(graph)):
        walk(i, [i])
    return H


@pytest.mark.parametrize("path_length", [2, 3, 4])
@pytest.mark.parametrize("backtracking", [True, False])
def test_histogram_equals_brute_force_on_random_graphs(path_length, backtracking):
    rng = np.random.default_rng(path_length + 10 * backtracking)
    for _ in range(3):
        n = 12
        edges = [(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.3]
        g = _graph(rng.integers(0, C, n), edges)
        H = semantic_histogram(g, path_length, backtracking)
        assert H.dtype == np.float64
        np.testing.assert_array_equal(H.toarray(), _brute_force(g, path_length, backtracking))


def test_isolated_node_has_empty_histogram_and_duplicate_edges_count_once():
    g = _graph([Label.CAR, Label.POLE, Label.BUILDING], [[0, 1], [0, 1], [1, 0]])
    H = semantic_histogram(g).toarray()
    assert H[2].sum() == 0
    assert H[0].sum() == 1  # 0 -> 1 -> 0 only


def _radius_graph(labels, pos, radius_m=12.0) -> GraphArrays:
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.nonzero(np.triu(d < radius_m, k=1))
    return _graph(labels, np.stack([i, j], axis=1), pos)


def test_histogram_is_invariant_to_rigid_motion_and_permutation():
    """Edges rebuilt from moved / permuted positions give the same (permuted) histograms."""
    rng = np.random.default_rng(3)
    n = 30
    pos = rng.uniform(0, 40, (n, 3))
    labels = rng.integers(0, C, n)
    H = semantic_histogram(_radius_graph(labels, pos)).toarray()
    assert H.sum() > 0
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    moved = pos @ R.T + np.array([100.0, -5.0, 30.0])
    np.testing.assert_array_equal(semantic_histogram(_radius_graph(labels, moved)).toarray(), H)
    perm = rng.permutation(n)
    np.testing.assert_array_equal(
        semantic_histogram(_radius_graph(labels[perm], moved[perm])).toarray(), H[perm]
    )


def test_path_length_two_is_the_neighbor_vector():
    np.testing.assert_array_equal(semantic_histogram(HAND, 2).toarray(), neighbor_vector(HAND).toarray())


def test_with_own_label_is_the_papers_layout():
    H = semantic_histogram(HAND, 3)
    full = with_own_label(H, HAND.label_ids).toarray()
    assert full.shape == (4, C**3)
    block = C**2
    for i, label in enumerate(HAND.label_ids):
        np.testing.assert_array_equal(full[i, label * block : (label + 1) * block], H.toarray()[i])
        assert full[i].sum() == H[i].sum()


def test_bad_labels_and_edges_raise_graph_error():
    with pytest.raises(GraphError, match="255"):
        semantic_histogram(_graph([0, 255, 2], [[0, 1]]))
    with pytest.raises(GraphError, match="row 7"):
        semantic_histogram(_graph([0, 1, 2], [[0, 7]]))
    with pytest.raises(GraphError, match="self-loop"):
        semantic_histogram(_graph([0, 1, 2], [[1, 1]]))
