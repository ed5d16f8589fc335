"""Node descriptors: the paper's semantic histogram (Alg. 1) and the two baselines.

``compute_descriptors`` dispatches on ``DescriptorKind`` through a registry; ``similarity`` is Eq. 1
(normalised dot product) between all node pairs of two graphs as one sparse matrix product, with
the same-label mask folded into the product (the paper's ``C**L`` layout, see ``histogram.py``).
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
from shgm_slam.descriptors.sparse_graph import check_labels, prepend_label
from shgm_slam.labels import NUM_CLASSES
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
    _unit: sp.csr_matrix | None = field(default=None, init=False, repr=False)
    _unit_by_label: sp.csr_matrix | None = field(default=None, init=False, repr=False)

    def __len__(self) -> int:
        return int(self.counts.shape[0])

    def subset(self, rows: np.ndarray) -> NodeDescriptors:
        """The descriptors of ``rows`` (int indices, in that order): those of a part of the graph, each
        still counting the paths of the whole graph."""
        rows = np.asarray(rows, dtype=np.int64)
        return NodeDescriptors(self.kind, self.counts[rows], self.label_ids[rows])

    @property
    def unit(self) -> sp.csr_matrix:
        """(N, D) rows scaled to unit L2 norm (all-zero rows stay zero); cached."""
        if self._unit is None:
            self._unit = unit_rows(self.counts)
        return self._unit

    @property
    def unit_by_label(self) -> sp.csr_matrix:
        """(N, C * D) unit rows moved into the block of each node's label (the same-label mask); cached."""
        if self._unit_by_label is None:
            self._unit_by_label = prepend_label(self.unit, self.label_ids, NUM_CLASSES)
        return self._unit_by_label


def unit_rows(counts: sp.csr_matrix) -> sp.csr_matrix:
    """(N, D) CSR ``counts`` with every row scaled to unit L2 norm; all-zero rows stay empty.

    The same matrix, entry order included, as the product ``diags(1 / norms) @ counts`` (which lists
    each row's entries in reverse): the order of a row's entries is the summation order of the Eq. 1
    products, so it is kept.
    """
    counts = sp.csr_matrix(counts)
    n = counts.shape[0]
    lengths = np.diff(counts.indptr)
    row_of = np.repeat(np.arange(n), lengths)
    norms = np.sqrt(np.bincount(row_of, weights=counts.data * counts.data, minlength=n))
    scale = np.divide(1.0, norms, out=np.zeros_like(norms), where=norms > 0)
    keys = row_of * counts.shape[1] + counts.indices
    if unique_sorted(keys).size < keys.size:  # duplicate entries (no builder makes them): the product merges them
        return sp.csr_matrix(sp.diags(scale) @ counts)
    within = np.arange(counts.data.size) - np.repeat(counts.indptr[:-1], lengths)
    reverse = np.repeat(counts.indptr[1:] - 1, lengths) - within  # each row's entries last to first
    data = counts.data[reverse] * scale[row_of]
    keep = data != 0
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row_of[keep], minlength=n))])
    return sp.csr_matrix((data[keep], counts.indices[reverse][keep], indptr), shape=counts.shape)


def compute_descriptors(graph: GraphArrays, cfg: DescriptorConfig) -> NodeDescriptors:
    """Descriptors of every node of ``graph`` with the kind and parameters of ``cfg``."""
    labels = check_labels(graph)
    counts = DESCRIPTOR_BUILDERS[cfg.kind](graph, cfg)
    return NodeDescriptors(cfg.kind, counts.tocsr(), labels)


def similarity(a: NodeDescriptors, b: NodeDescriptors, same_label_only: bool = True) -> sp.csr_matrix:
    """Eq. 1 scores of every node pair as one sparse product: (N_a, N_b) float64 CSR in [0, 1].

    With ``same_label_only`` each unit descriptor is moved into the block of its node's label first,
    so pairs with different labels multiply disjoint blocks and score exactly 0 (not stored).
    Nodes with an all-zero descriptor (isolated nodes) score 0 with everything.
    """
    if a.kind is not b.kind:
        raise ValueError(f"cannot compare {a.kind.value} descriptors with {b.kind.value} descriptors")
    ua, ub = (a.unit_by_label, b.unit_by_label) if same_label_only else (a.unit, b.unit)
    scores = (ua @ ub.T).tocsr()
    scores.data = np.minimum(scores.data, 1.0)  # round-off above 1
    scores.eliminate_zeros()
    return scores


__all__ = [
    "DESCRIPTOR_BUILDERS",
    "NodeDescriptors",
    "compute_descriptors",
    "similarity",
    "unit_rows",
]
