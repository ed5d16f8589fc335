"""Descriptors of a growing graph, recomputed only around what changed (the map server's cache).

A node's semantic histogram counts label paths of ``path_length - 1`` steps from it (Alg. 1), its
neighbour vector the labels one step away: both depend only on the labels and edges within ``h`` hops
(``locality_hops``). When a keyframe adds or moves nodes, only the nodes within ``h`` hops of a changed
label or edge (in the old or the new graph) can change; they are recomputed on the subgraph within ``h``
more hops of them, which holds every path they count, and every other row is kept. The result equals
``compute_descriptors`` on the whole graph exactly. Random-walk descriptors are random, so they are
always recomputed in full.

Rows follow the graph's rows, and a growing graph only appends rows (``SemanticGraph``: nodes are never
removed or reordered); a graph whose rows were reordered or removed is recomputed in full.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from shgm_slam.config import DescriptorConfig, DescriptorKind
from shgm_slam.descriptors import DESCRIPTOR_BUILDERS, NodeDescriptors, compute_descriptors
from shgm_slam.descriptors.sparse_graph import check_labels
from shgm_slam.types import GraphArrays


def locality_hops(cfg: DescriptorConfig) -> int | None:
    """Hops within which a node's descriptor depends on the graph, or None (not local: random walks)."""
    if cfg.kind is DescriptorKind.HISTOGRAM:
        return cfg.path_length - 1
    if cfg.kind is DescriptorKind.NEIGHBOR_VECTOR:
        return 1
    return None


def _edge_keys(graph: GraphArrays) -> np.ndarray:
    """Sorted (E,) int64 keys ``i << 32 | j`` (i < j) of the graph's edges."""
    e = np.sort(np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2), axis=1)
    return np.unique((e[:, 0] << 32) | e[:, 1])


def _adjacency(n: int, keys: np.ndarray) -> sp.csr_matrix:
    """Symmetric binary (n, n) CSR adjacency of edge keys ``i << 32 | j``."""
    i, j = keys >> 32, keys & 0xFFFFFFFF
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    return sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))


def _ball(A: sp.csr_matrix, seeds: np.ndarray, hops: int) -> np.ndarray:
    """(N,) bool: the nodes within ``hops`` steps of ``seeds`` in adjacency ``A``."""
    inside = np.zeros(A.shape[0], dtype=bool)
    inside[seeds] = True
    frontier = inside.copy()
    for _ in range(hops):
        reached = (A @ frontier.astype(np.float64)) > 0
        frontier = reached & ~inside
        if not frontier.any():
            break
        inside |= frontier
    return inside


class IncrementalDescriptors:
    """``compute_descriptors`` of one growing graph, kept up to date around its changes.

    Args:
        cfg: descriptor kind and parameters.

    ``recomputed_rows`` is how many rows the last ``update`` computed (the whole graph on the first
    call, after a reorder, or for random walks).
    """

    def __init__(self, cfg: DescriptorConfig) -> None:
        self.cfg = cfg
        self.hops = locality_hops(cfg)
        self._labels = np.zeros(0, dtype=np.int64)
        self._node_ids = np.zeros(0, dtype=np.int64)
        self._keys = np.zeros(0, dtype=np.int64)
        self._current: NodeDescriptors | None = None
        self.recomputed_rows = 0

    def update(self, graph: GraphArrays) -> NodeDescriptors:
        """Descriptors of every node of ``graph`` (rows follow the graph's rows), equal to
        ``compute_descriptors(graph, cfg)``.

        Raises:
            GraphError: labels outside the label space or bad edges (as ``compute_descriptors``).
        """
        labels = check_labels(graph)
        keys = _edge_keys(graph)
        n_old = self._labels.shape[0]
        appended = len(graph) >= n_old and np.array_equal(graph.node_ids[:n_old], self._node_ids)
        if self._current is None or self.hops is None or not appended:
            out = compute_descriptors(graph, self.cfg)
            self.recomputed_rows = len(graph)
        else:
            out = self._patch(graph, labels, keys, n_old)
        self._labels, self._node_ids, self._keys, self._current = labels, graph.node_ids.copy(), keys, out
        return out

    def _patch(self, graph: GraphArrays, labels: np.ndarray, keys: np.ndarray, n_old: int) -> NodeDescriptors:
        n = len(graph)
        changed = np.zeros(n, dtype=bool)
        changed[n_old:] = True
        changed[:n_old] = labels[:n_old] != self._labels
        flipped = np.setxor1d(keys, self._keys, assume_unique=True)  # added or removed edges
        changed[flipped >> 32] = True
        changed[flipped & 0xFFFFFFFF] = True
        if not changed.any():
            return self._current
        affected = _ball(_adjacency(n, np.union1d(keys, self._keys)), np.flatnonzero(changed), self.hops)
        support = np.flatnonzero(_ball(_adjacency(n, keys), np.flatnonzero(affected), self.hops))
        sub = graph.subset(support)
        counts_sub = DESCRIPTOR_BUILDERS[self.cfg.kind](sub, self.cfg).tocsr()
        rows_new = np.flatnonzero(affected)
        fresh = counts_sub[np.searchsorted(support, rows_new)]
        kept = np.flatnonzero(~affected[:n_old])
        old_counts = self._current.counts
        stacked = sp.vstack([old_counts[kept], fresh], format="csr")
        order = np.empty(n, dtype=np.int64)
        order[np.concatenate([kept, rows_new])] = np.arange(n)
        self.recomputed_rows = int(rows_new.size)
        return NodeDescriptors(self.cfg.kind, stacked[order].tocsr(), labels)
