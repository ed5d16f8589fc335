"""The Neighbor Vector baseline: per node, the count of each label among its neighbours.

It equals the semantic histogram with path length 2 and carries no topology beyond one hop, which
is why the paper finds it fast but weak.
"""

from __future__ import annotations

import scipy.sparse as sp

from shgm_slam.descriptors.sparse_graph import adjacency_matrix, check_labels, one_hot
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.types import GraphArrays


def neighbor_vector(graph: GraphArrays, num_classes: int = NUM_CLASSES) -> sp.csr_matrix:
    """(N, C) float64 CSR: entry (i, c) = number of neighbours of node i with label c."""
    labels = check_labels(graph, num_classes)
    return (adjacency_matrix(graph) @ one_hot(labels, num_classes)).tocsr()
