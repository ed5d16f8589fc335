"""The extent check of a caller's graphs (degrees of latitude and longitude, ``types.extent_problem``) stays out of
the pipeline's own matching: ``match_graphs`` takes a map server's small windows in metres as they are."""

from __future__ import annotations

import numpy as np

from shgm_slam.config import DescriptorConfig, MatchingConfig
from shgm_slam.matching import match_graphs
from shgm_slam.types import GraphArrays

from .synthetic import city_pair


def test_a_window_of_nodes_close_together_fails_cleanly_not_as_degrees() -> None:
    """A map server's window of a few nodes on one mast (pole, sign, light within a metre) is the pipeline's own
    graph in metres: the extent check for a caller's graphs raised a GraphError from ``match_graphs`` there (its
    docstring: tiny graphs give an unsuccessful result, never an exception), which would end a run."""
    a, _, _ = city_pair(seed=0, overlap=True)
    mast = GraphArrays(np.arange(4), np.array([5, 7, 6, 5]), np.array([[0.0, 0, 0], [0.3, 0.2, 0.1],
                       [0.1, 0.5, 0.4], [0.2, 0.1, 0.6]]), np.ones(4), np.array([[0, 1], [1, 2], [2, 3]]))  # fmt: skip
    for first, second in ((mast, a), (a, mast)):
        r = match_graphs(first, second, DescriptorConfig(), MatchingConfig())
        assert not r.success and r.reason
