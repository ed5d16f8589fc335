"""Node descriptors: the paper's semantic histogram (Alg. 1) and the two baselines.

``compute_descriptors`` dispatches on ``DescriptorKind`` through a registry; ``score_entries`` is Eq. 1
(normalised dot product) between all node pairs of two graphs as one sparse matrix product, with
the same-label mask folded into the product (the paper's ``C**L`` layout, see ``histogram.py``), on plain
CSR arrays (scipy's per-matrix overhead dominates at map sizes); ``similarity`` is the same as a matrix.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from shgm_slam.arrays import unique_sorted
from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors.histogram import semantic_histogram
from shgm_slam.descriptors.neighbor_vector import neighbor_vector
from shgm_slam.descriptors.random_walk import random_walk_descriptors
from shgm_slam.descriptors.sparse_graph import (
    CsrArrays,
    check_labels,
    csr_arrays,
    prepend_label_arrays,
    product_with_transpose,
)
from shgm_slam.types import GraphArrays

DescriptorBuilder = Callable[[GraphArrays, DescriptorConfig], sp.csr_matrix]

DESCRIPTOR_BUILDERS: dict[DescriptorKind, DescriptorBuilder] = {
    DescriptorKind.HISTOGRAM: lambda g, c: semantic_histogram(g, c.path_length, c.count_backtracking),
    DescriptorKind.NEIGHBOR_VECTOR: lambda g, c: neighbor_vector(g),
    DescriptorKind.RANDOM_WALK: lambda g, c: random_walk_descriptors(g, c.num_walks, c.walk_length, c.seed),
}
"""Registry of descriptor builders: (graph, config) -> (N, D) float64 CSR raw counts."""


@dataclass
class NodeDescriptors:
    """Descriptors of one graph's nodes, ready for Eq. 1.

    Attributes:
        kind: which descriptor produced ``counts``.
        counts: (N, D) float64 CSR raw counts (rows follow the graph's rows).
        label_ids: (N,) int64 each node's own label (the same-label mask of the matching).
    """

    kind: DescriptorKind
    counts: sp.csr_matrix
    label_ids: np.ndarray
    _unit: CsrArrays | None = field(default=None, init=False, repr=False)
    _unit_by_label: CsrArrays | None = field(default=None, init=False, repr=False)

    def __len__(self) -> int:
        return int(self.counts.shape[0])

    def subset(self, rows: np.ndarray) -> NodeDescriptors:
        """The descriptors of ``rows`` (int indices, in that order): those of a part of the graph, each
        still counting the paths of the whole graph."""
        rows = np.asarray(rows, dtype=np.int64)
        return NodeDescriptors(self.kind, self.counts[rows], self.label_ids[rows])

    @property
    def unit(self) -> CsrArrays:
        """CSR arrays of the (N, D) rows scaled to unit L2 norm (``unit_rows``); cached."""
        if self._unit is None:
            self._unit = unit_row_arrays(csr_arrays(self.counts), self.counts.shape)
        return self._unit

    @property
    def unit_by_label(self) -> CsrArrays:
        """CSR arrays of the (N, C * D) unit rows moved into the block of each node's label (the same-label
        mask, ``sparse_graph.prepend_label``); cached."""
        if self._unit_by_label is None:
            self._unit_by_label = prepend_label_arrays(self.unit, self.label_ids, self.counts.shape[1])
        return self._unit_by_label


def unit_rows(counts: sp.csr_matrix) -> sp.csr_matrix:
    """(N, D) CSR ``counts`` with every row scaled to unit L2 norm; all-zero rows stay empty.

    The same matrix, entry order included, as the product ``diags(1 / norms) @ counts`` (which lists
    each row's entries in reverse): the order of a row's entries is the summation order of the Eq. 1
    products, so it is kept.
    """
    counts = sp.csr_matrix(counts)
    indptr, indices, data = unit_row_arrays(csr_arrays(counts), counts.shape)
    return sp.csr_matrix((data, indices, indptr), shape=counts.shape)


def unit_row_arrays(counts: CsrArrays, shape: tuple[int, int]) -> CsrArrays:
    """``unit_rows`` on the CSR arrays of an (N, D) matrix of the given ``shape``."""
    counts_indptr, counts_indices, counts_data = counts
    n = shape[0]
    lengths = np.diff(counts_indptr)
    row_of = np.repeat(np.arange(n), lengths)
    norms = np.sqrt(np.bincount(row_of, weights=counts_data * counts_data, minlength=n))
    scale = np.divide(1.0, norms, out=np.zeros_like(norms), where=norms > 0)
    keys = row_of * shape[1] + counts_indices
    if unique_sorted(keys).size < keys.size:  # duplicate entries (no builder makes them): the product merges them
        M = sp.csr_matrix(counts[::-1], shape=shape)
        return csr_arrays(sp.csr_matrix(sp.diags(scale) @ M))
    within = np.arange(counts_data.size) - np.repeat(counts_indptr[:-1], lengths)
    reverse = np.repeat(counts_indptr[1:] - 1, lengths) - within  # each row's entries last to first
    data = counts_data[reverse] * scale[row_of]
    keep = data != 0
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row_of[keep], minlength=n))])
    return indptr, counts_indices[reverse][keep], data[keep]


def compute_descriptors(graph: GraphArrays, cfg: DescriptorConfig) -> NodeDescriptors:
    """Descriptors of every node of ``graph`` with the kind and parameters of ``cfg``."""
    labels = check_labels(graph)
    counts = DESCRIPTOR_BUILDERS[cfg.kind](graph, cfg)
    return NodeDescriptors(cfg.kind, counts.tocsr(), labels)


ScoreEntries = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(M,) int64 rows of A, (M,) int64 rows of B and (M,) float64 Eq. 1 scores in (0, 1] of the non-zero scores."""


def score_entries(a: NodeDescriptors, b: NodeDescriptors, same_label_only: bool = True) -> ScoreEntries:
    """Eq. 1 scores of every node pair as one sparse product (``sparse_graph.product_with_transpose``, the
    bits of scipy's ``unit_a @ unit_b.T``), as the entries of the (N_a, N_b) score matrix (by row of A).

    With ``same_label_only`` each unit descriptor is moved into the block of its node's label first,
    so pairs with different labels multiply disjoint blocks and score exactly 0 (not listed).
    Nodes with an all-zero descriptor (isolated nodes) score 0 with everything.
    """
    if a.kind is not b.kind:
        raise ValueError(f"cannot compare {a.kind.value} descriptors with {b.kind.value} descriptors")
    ua, ub = (a.unit_by_label, b.unit_by_label) if same_label_only else (a.unit, b.unit)
    indptr, rows_b, scores = product_with_transpose(ua, ub, len(a), len(b))
    rows_a = np.repeat(np.arange(len(a)), np.diff(indptr))
    return rows_a, rows_b.astype(np.int64), np.minimum(scores, 1.0)  # round-off above 1


def similarity(a: NodeDescriptors, b: NodeDescriptors, same_label_only: bool = True) -> sp.csr_matrix:
    """``score_entries`` as an (N_a, N_b) float64 CSR matrix in [0, 1] (absent = 0)."""
    rows_a, rows_b, scores = score_entries(a, b, same_label_only)
    return sp.csr_matrix((scores, (rows_a, rows_b)), shape=(len(a), len(b)))


__all__ = [
    "DESCRIPTOR_BUILDERS",
    "NodeDescriptors",
    "ScoreEntries",
    "compute_descriptors",
    "score_entries",
    "similarity",
    "unit_row_arrays",
    "unit_rows",
]
