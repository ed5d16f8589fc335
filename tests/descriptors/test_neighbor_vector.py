"""Neighbor Vector baseline: per-node label counts of the neighbours."""

from __future__ import annotations

import numpy as np

from shgm_slam.descriptors.neighbor_vector import neighbor_vector
from shgm_slam.labels import NUM_CLASSES, Label
from shgm_slam.types import GraphArrays


def test_neighbor_vector_counts_neighbour_labels():
    labels = np.array([Label.CAR, Label.CAR, Label.POLE, Label.BUILDING, Label.CAR])
    edges = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [2, 3]])
    g = GraphArrays(np.arange(5), labels, np.zeros((5, 3)), np.ones(5), edges)
    V = neighbor_vector(g).toarray()
    assert V.shape == (5, NUM_CLASSES)
    expected0 = np.zeros(NUM_CLASSES)
    expected0[[Label.CAR, Label.POLE, Label.BUILDING]] = [2, 1, 1]
    np.testing.assert_array_equal(V[0], expected0)
    np.testing.assert_array_equal(V.sum(axis=1), [4, 1, 2, 2, 1])  # = node degrees
    assert V[2, Label.CAR] == 1 and V[2, Label.BUILDING] == 1
