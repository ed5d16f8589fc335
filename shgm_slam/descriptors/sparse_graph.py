"""Sparse linear algebra of a semantic graph: adjacency, one-hot labels, directed edges.

Every descriptor is built from these matrices with sparse products, so no descriptor loops over
nodes or paths in Python. Rows are the graph's row indices (not node ids).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from shgm_slam.arrays import unique_first, unique_sorted
from shgm_slam.errors import GraphError
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.types import GraphArrays

CsrArrays = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(indptr, indices, data) of a CSR matrix, without scipy's per-object overhead."""


def check_labels(graph: GraphArrays, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """The graph's (N,) int64 label ids, validated to lie in ``[0, num_classes)``.

    Raises:
        GraphError: a label is outside the label space (e.g. 255 = ignore slipped into the graph).
    """
    labels = np.asarray(graph.label_ids, dtype=np.int64)
    if labels.size and (labels.min() < 0 or labels.max() >= num_classes):
        bad = labels[(labels < 0) | (labels >= num_classes)][0]
        raise GraphError(
            f"graph node label {bad} is outside the {num_classes} Cityscapes train ids; "
            "drop ignore/unknown labels (255) before building descriptors"
        )
    return labels


def adjacency_matrix(graph: GraphArrays) -> sp.csr_matrix:
    """Symmetric binary (N, N) float64 CSR adjacency from ``graph.edges`` (duplicates merged).

    Raises:
        GraphError: an edge references a row outside ``[0, N)`` or is a self loop.
    """
    indptr, indices, data = adjacency_arrays(graph)
    return sp.csr_matrix((data, indices, indptr), shape=(len(graph), len(graph)))  # canonical: sorted rows


def adjacency_arrays(graph: GraphArrays) -> CsrArrays:
    """The CSR arrays of ``adjacency_matrix`` (int64 indices, each row's columns ascending), without scipy's
    per-matrix overhead.

    Raises:
        GraphError: an edge references a row outside ``[0, N)`` or is a self loop.
    """
    n = len(graph)
    edges = np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2)
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise GraphError(f"graph edge references row {int(edges.max())} but the graph has {n} nodes")
    if edges.size and np.any(edges[:, 0] == edges[:, 1]):
        raise GraphError("graph has a self-loop edge (i, i); edges must join two different nodes")
    keys = unique_sorted(np.concatenate([edges[:, 0] * n + edges[:, 1], edges[:, 1] * n + edges[:, 0]]))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // max(n, 1), minlength=n))])
    return indptr, keys % max(n, 1), np.ones(keys.size)


def csr_arrays(M: sp.csr_matrix) -> CsrArrays:
    """The (indptr, indices, data) arrays of a CSR matrix."""
    return M.indptr, M.indices, M.data


def sparse_product(A: CsrArrays, X: CsrArrays, n_rows: int, width: int) -> CsrArrays:
    """``A @ X`` of (n_rows, M) and (M, width) CSR arrays, bit-identical to scipy's product, without its
    per-product overhead (descriptors and scores of small graphs are dominated by it).

    scipy walks each row of A in stored order and, for each entry, X's row in stored order, adding each
    product to its column's sum; ``np.bincount`` adds in the same (input) order, so even float sums are the
    same to the last bit, and exact zeros are dropped as scipy drops them. The entries are listed as scipy
    lists them (each row's columns in reverse order of first touch): a row's order is the summation order
    of any later product with it.
    """
    a_indptr, a_indices, a_data = A
    x_indptr, x_indices, x_data = X
    lengths = np.diff(x_indptr)[a_indices]  # X entries reached through each entry of A
    rows = np.repeat(np.repeat(np.arange(n_rows), np.diff(a_indptr)), lengths)
    within = np.arange(rows.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    src = np.repeat(x_indptr[:-1][a_indices], lengths) + within  # (T,) X entries in traversal order
    keys = rows * width + x_indices[src]
    unique, first, inverse = unique_first(keys)
    products = np.repeat(a_data, lengths) * x_data[src]
    sums = np.bincount(inverse, weights=products, minlength=unique.size)
    out_rows = unique // max(width, 1)
    order = np.argsort(out_rows * keys.size - first)  # by row, then last touched first (unique keys)
    order = order[sums[order] != 0]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(out_rows[order], minlength=n_rows))])
    return indptr, unique[order] % max(width, 1), sums[order]


SCIPY_PRODUCT_PAIRS = 100_000
"""``product_with_transpose`` of more row pairs than this runs scipy's product (its dense accumulator beats
sorting the traversal of big graphs; small products are dominated by scipy's per-matrix overhead)."""


def product_with_transpose(A: CsrArrays, B: CsrArrays, n_a: int, n_b: int) -> CsrArrays:
    """``A @ B.T`` of (n_a, D) and (n_b, D) CSR arrays as (n_a, n_b) CSR arrays (each row's entries in any
    order), bit-identical to scipy's product whatever D is: ``sparse_product`` up to ``SCIPY_PRODUCT_PAIRS``
    row pairs, scipy's beyond.

    ``B.T`` is built on the columns B uses only (compacted, ascending); columns of A that B does not use
    point at one extra empty row. Each sum of the product gets one term per shared column, in the order of
    A's row, so the order of ``B.T``'s rows' entries does not change any bit. Rows of B without entries
    are fine; duplicate column indices within a row of A or B are not (Eq. 1's unit rows have none).
    """
    a_indptr, a_indices, a_data = A
    b_indptr, b_indices, b_data = B
    if n_a * n_b > SCIPY_PRODUCT_PAIRS:
        width = int(max(a_indices.max(initial=-1), b_indices.max(initial=-1))) + 1
        a = sp.csr_matrix((a_data, a_indices, a_indptr), shape=(n_a, width))
        b = sp.csr_matrix((b_data, b_indices, b_indptr), shape=(n_b, width))
        return csr_arrays((a @ b.T).tocsr())
    order = np.argsort(b_indices, kind="stable")
    columns = b_indices[order]
    used = unique_sorted(columns)
    t_indptr = np.concatenate([[0], np.searchsorted(columns, used, side="right"), [columns.size]])
    rows_b = np.repeat(np.arange(n_b), np.diff(b_indptr))[order]
    slot = np.searchsorted(used, a_indices)
    found = slot < used.size
    found[found] = used[slot[found]] == a_indices[found]
    slot[~found] = used.size  # the empty row
    return sparse_product((a_indptr, slot, a_data), (t_indptr, rows_b, b_data[order]), n_a, n_b)


def prepend_label_arrays(X: CsrArrays, labels: np.ndarray, dim: int) -> CsrArrays:
    """``prepend_label`` on (R, dim) CSR arrays: column c of row r moves to ``labels[r] * dim + c``."""
    indptr, indices, data = X
    row_of = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    return indptr, indices + labels[row_of] * dim, data


def one_hot(labels: np.ndarray, num_classes: int = NUM_CLASSES) -> sp.csr_matrix:
    """(N, C) float64 CSR with a single 1 per row at the row's label."""
    n = labels.shape[0]
    return sp.csr_matrix((np.ones(n), (np.arange(n), labels)), shape=(n, num_classes))


def prepend_label(counts: sp.csr_matrix, labels: np.ndarray, num_classes: int = NUM_CLASSES) -> sp.csr_matrix:
    """Shift each row's bins into the block of that row's label: (R, D) -> (R, C * D).

    Column ``c`` of row ``r`` moves to ``labels[r] * D + c``: a label path ``s`` becomes the path
    ``(labels[r], s)`` with the prepended label as the most significant digit.
    """
    counts = sp.csr_matrix(counts)
    dim = counts.shape[1]
    row_of = np.repeat(np.arange(counts.shape[0]), np.diff(counts.indptr))
    cols = counts.indices.astype(np.int64) + labels[row_of] * dim
    return sp.csr_matrix((counts.data, cols, counts.indptr), shape=(counts.shape[0], num_classes * dim))


def directed_edges(A: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both directions of every edge of a symmetric adjacency.

    Returns:
        src, dst: (2E,) int64 rows of directed edges u -> v, sorted by (src, dst).
        reverse: (2E,) int64 index of the opposite edge v -> u for each edge.
    """
    n = A.shape[0]
    src = np.repeat(np.arange(n), np.diff(A.indptr))
    dst = A.indices.astype(np.int64)
    key = src * n + dst
    order = np.argsort(key, kind="stable")
    src, dst, key = src[order], dst[order], key[order]
    reverse = np.searchsorted(key, dst * n + src)
    return src, dst, reverse
