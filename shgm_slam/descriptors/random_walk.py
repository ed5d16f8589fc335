"""The X-view random-walk baseline (Gawel et al., RA-L 2018), vectorised over all nodes and walks.

Each node gets ``num_walks`` (X-view: 400) random walks of ``walk_length`` (X-view: 3) steps. The next
node is drawn uniformly from the current node's neighbours, avoiding the node the walk just came
from (X-view's non-backtracking walks) unless it is the only neighbour; an isolated node stays in
place (as X-view's walker does). A walk is the label sequence of the visited nodes *after* the start
node, encoded as the integer ``sum_k l_k * C**(L-1-k)``; a node's descriptor is the (N, C**L) count
matrix of its walk codes (X-view's "walk map" with multiplicities).

Similarity: X-view counts identical walks between two descriptors, i.e. every pair (walk of a, walk
of b) with the same label sequence, which is ``sum_code count_a * count_b`` = the dot product of the
count rows (:func:`shared_walk_counts`). X-view divides by the constant ``num_walks**2``; the matcher
uses Eq. 1 (the same dot product divided by the L2 norms) for every descriptor kind so that one
score threshold applies to all of them.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from shgm_slam.descriptors.sparse_graph import adjacency_matrix, check_labels
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.types import GraphArrays


def random_walks(
    graph: GraphArrays,
    num_walks: int = 400,
    walk_length: int = 3,
    seed: int = 0,
    avoid_backtracking: bool = True,
) -> np.ndarray:
    """Sample all walks of all nodes at once.

    Returns:
        (N, num_walks, walk_length) int64 row indices of the nodes visited after each start node.
    """
    A = adjacency_matrix(graph)
    indptr, neighbors = A.indptr.astype(np.int64), A.indices.astype(np.int64)
    n = len(graph)
    rng = np.random.default_rng(seed)
    current = np.repeat(np.arange(n, dtype=np.int64), num_walks)
    previous = np.full_like(current, -1)
    walks = np.empty((current.size, walk_length), dtype=np.int64)
    last_slot = max(neighbors.size - 1, 0)
    for step in range(walk_length):  # loop over the few steps; all walks advance together
        start, degree = indptr[current], indptr[current + 1] - indptr[current]
        avoid = (previous >= 0) & (degree > 1) if avoid_backtracking else np.zeros(current.size, bool)
        choices = np.maximum(degree - avoid, 1)
        pick = (rng.random(current.size) * choices).astype(np.int64)
        nxt = neighbors[np.minimum(start + pick, last_slot)] if neighbors.size else current.copy()
        # uniform over the neighbours other than `previous`: a draw of `previous` takes the last slot
        hit_previous = avoid & (nxt == previous)
        nxt[hit_previous] = neighbors[start[hit_previous] + degree[hit_previous] - 1]
        nxt = np.where(degree == 0, current, nxt)
        walks[:, step] = nxt
        previous, current = current, nxt
    return walks.reshape(n, num_walks, walk_length)


def encode_walks(walks: np.ndarray, label_ids: np.ndarray, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """(..., L) walks of row indices -> (...) int64 codes of their label sequences."""
    place = num_classes ** np.arange(walks.shape[-1] - 1, -1, -1, dtype=np.int64)
    return (np.asarray(label_ids, dtype=np.int64)[walks] * place).sum(axis=-1)


def random_walk_descriptors(
    graph: GraphArrays,
    num_walks: int = 400,
    walk_length: int = 3,
    seed: int = 0,
    num_classes: int = NUM_CLASSES,
) -> sp.csr_matrix:
    """X-view descriptors: (N, C**walk_length) float64 CSR walk-code counts (each row sums to num_walks)."""
    labels = check_labels(graph, num_classes)
    n = len(graph)
    codes = encode_walks(random_walks(graph, num_walks, walk_length, seed), labels, num_classes)
    rows = np.repeat(np.arange(n), num_walks)
    return sp.csr_matrix(
        (np.ones(rows.size), (rows, codes.ravel())), shape=(n, num_classes**walk_length)
    )


def shared_walk_counts(descriptors_a: sp.csr_matrix, descriptors_b: sp.csr_matrix) -> sp.csr_matrix:
    """(N_a, N_b) number of identical walk pairs between every node of a and every node of b (X-view)."""
    return (sp.csr_matrix(descriptors_a) @ sp.csr_matrix(descriptors_b).T).tocsr()
