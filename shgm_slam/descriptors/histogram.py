"""The semantic histogram descriptor of the paper (Alg. 1) as sparse matrix products.

For node i, Alg. 1 counts the label paths ``l_i - l_m - l_n`` over neighbours m of i and neighbours
n of m (path length 3). Path length L generalises this to walks of L - 1 steps.

Bin layout: node i's own label is the same for every path of i, so the returned histogram keeps only
the labels *after* i: dimension ``C**(L-1)``, bin ``sum_k l_{v_k} * C**(L-1-k)`` for the walk
``i -> v_1 -> ... -> v_{L-1}`` (first step = most significant digit). The paper's ``C**L`` layout is
the same vector placed in block ``l_i`` (:func:`with_own_label`); both give identical Eq. 1 scores
between same-label nodes, and the ``C**L`` layout scores every cross-label pair 0.

Backtracking: the authors' release counts walks that return to the previous-but-one node
(i -> m -> i); ``count_backtracking=False`` counts non-backtracking walks only
(``v_{k+1} != v_{k-1}``, with ``v_0 = i``), via the directed-edge (Hashimoto) recursion.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from shgm_slam.descriptors.sparse_graph import (
    CsrArrays,
    adjacency_arrays,
    adjacency_matrix,
    check_labels,
    directed_edges,
    one_hot,
    prepend_label,
    prepend_label_arrays,
    sparse_product,
)
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.types import GraphArrays


def semantic_histogram(
    graph: GraphArrays,
    path_length: int = 3,
    count_backtracking: bool = True,
    num_classes: int = NUM_CLASSES,
) -> sp.csr_matrix:
    """Alg. 1 histograms of all nodes at once.

    Args:
        graph: N nodes with label ids in ``[0, num_classes)`` and edges as row pairs.
        path_length: labels per path including node i's own (2, 3 = the paper, or 4).
        count_backtracking: count walks i -> m -> i (the authors' release) or not.
        num_classes: label-space size C (Cityscapes train ids: 19).

    Returns:
        (N, C**(path_length-1)) float64 CSR of raw path counts (bin layout in the module docstring).
        Isolated nodes get an all-zero row.
    """
    if not 2 <= path_length <= 6:
        raise ValueError(f"path_length must be in [2, 6], got {path_length}")
    labels = check_labels(graph, num_classes)
    steps = path_length - 1
    if count_backtracking or steps == 1:
        return _walk_histogram(adjacency_arrays(graph), labels, steps, num_classes)
    return _non_backtracking_histogram(adjacency_matrix(graph), labels, steps, num_classes)


def with_own_label(
    histogram: sp.csr_matrix, label_ids: np.ndarray, num_classes: int = NUM_CLASSES
) -> sp.csr_matrix:
    """The paper's ``C**L`` layout: (N, C**(L-1)) histograms moved into the block of each node's label."""
    return prepend_label(histogram, np.asarray(label_ids, dtype=np.int64), num_classes)


def _walk_histogram(A: CsrArrays, labels: np.ndarray, steps: int, num_classes: int) -> sp.csr_matrix:
    """All walks: W_h = A @ prepend(l, W_{h-1}), W_0 = ones (every node ends a 0-step walk once); ``A`` the
    CSR arrays of the (N, N) adjacency."""
    n, dim = labels.shape[0], 1
    W = np.arange(n + 1), np.zeros(n, dtype=np.int64), np.ones(n)  # CSR arrays of an (N, 1) column of ones
    for _ in range(steps):
        W = sparse_product(A, prepend_label_arrays(W, labels, dim), n, dim * num_classes)
        dim *= num_classes
    return sp.csr_matrix(W[::-1], shape=(n, dim))


def _non_backtracking_histogram(
    A: sp.csr_matrix, labels: np.ndarray, steps: int, num_classes: int
) -> sp.csr_matrix:
    """Non-backtracking walks by recursion over directed edges e = (u -> v).

    F_h[e] counts walks of h steps that start with e; S_h[u] = sum of F_h over u's out-edges.
    F_1[u->v] = onehot(l_v);  F_h[u->v] = prepend(l_v, S_{h-1}[v] - F_{h-1}[v->u]).
    """
    n = A.shape[0]
    src, dst, reverse = directed_edges(A)
    out = sp.csr_matrix((np.ones(src.size), (src, np.arange(src.size))), shape=(n, src.size))
    F = one_hot(labels[dst], num_classes)
    S = (out @ F).tocsr()
    for _ in range(steps - 1):
        continuation = (S[dst] - F[reverse]).tocsr()
        continuation.eliminate_zeros()
        F = prepend_label(continuation, labels[dst], num_classes)
        S = (out @ F).tocsr()
    return S
