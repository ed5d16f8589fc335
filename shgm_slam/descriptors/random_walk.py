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


def _walk_steps(
    graph: GraphArrays, num_walks: int, walk_length: int, seed: int, avoid_backtracking: bool
) -> list[np.ndarray]:
    """``walk_length`` arrays of (N * num_walks,) int32 rows; walk w of node i sits at i * num_walks + w."""
    A = adjacency_matrix(graph)
    indptr, neighbors = A.indptr.astype(np.int32), A.indices.astype(np.int32)
    n = len(graph)
    rng = np.random.default_rng(seed)
    current = np.repeat(np.arange(n, dtype=np.int32), num_walks)
    previous: np.ndarray | None = None
    has_isolated = bool(np.any(np.diff(indptr) == 0))
    last_slot = max(neighbors.size - 1, 0)
    steps = []
    for _ in range(walk_length):  # loop over the few steps; all walks advance together
        start = indptr[current]
        degree = indptr[current + 1] - start
        avoid = None
        choices = degree
        if avoid_backtracking and previous is not None:
            avoid = degree > 1
            choices = degree - avoid
        pick = (rng.random(current.size) * np.maximum(choices, 1)).astype(np.int32)
        pick += start
        nxt = neighbors[np.minimum(pick, last_slot)] if neighbors.size else current.copy()
        if avoid is not None:  # uniform over the neighbours other than `previous`: it yields the last slot
            hit = np.flatnonzero(avoid & (nxt == previous))
            nxt[hit] = neighbors[start[hit] + degree[hit] - 1]
        if has_isolated:
            nxt = np.where(degree == 0, current, nxt)
        steps.append(nxt)
        previous, current = current, nxt
    return steps


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
    steps = _walk_steps(graph, num_walks, walk_length, seed, avoid_backtracking)
    return np.stack(steps, axis=-1).astype(np.int64).reshape(len(graph), num_walks, walk_length)


def encode_walks(walks: np.ndarray, label_ids: np.ndarray, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """(..., L) walks of row indices -> (...) int64 label-sequence codes, first step most significant."""
    return _encode([walks[..., k] for k in range(walks.shape[-1])], label_ids, num_classes)


def _encode(steps: list[np.ndarray], label_ids: np.ndarray, num_classes: int) -> np.ndarray:
    labels = np.asarray(label_ids, dtype=np.int64)
    code = labels[steps[0]]
    for step in steps[1:]:
        code *= num_classes
        code += labels[step]
    return code


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
    codes = _encode(_walk_steps(graph, num_walks, walk_length, seed, True), labels, num_classes)
    codes = np.sort(codes.reshape(n, num_walks), axis=1)  # run-length count each node's walk codes
    first = np.ones(codes.shape, dtype=bool)
    first[:, 1:] = codes[:, 1:] != codes[:, :-1]
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, codes.size)).astype(np.float64)
    indptr = np.concatenate([[0], np.cumsum(first.sum(axis=1))])
    return sp.csr_matrix((counts, codes.ravel()[starts], indptr), shape=(n, num_classes**walk_length))


def shared_walk_counts(descriptors_a: sp.csr_matrix, descriptors_b: sp.csr_matrix) -> sp.csr_matrix:
    """(N_a, N_b) number of identical walk pairs between every node of a and every node of b (X-view)."""
    return (sp.csr_matrix(descriptors_a) @ sp.csr_matrix(descriptors_b).T).tocsr()
