"""The sort-based replacements of np.unique give np.unique's results."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.arrays import first_indices, unique_first, unique_sorted


@pytest.mark.parametrize("size", [0, 1, 7, 300, 2000])
def test_unique_helpers_equal_np_unique(size):
    rng = np.random.default_rng(size)
    for high in (3, 50, 10**6):
        values = rng.integers(-high, high, size)
        expected = np.unique(values, return_index=True, return_inverse=True)
        for got, want in zip(unique_first(values), expected, strict=True):
            np.testing.assert_array_equal(got, np.asarray(want).reshape(-1))
        np.testing.assert_array_equal(unique_sorted(values), np.unique(values))
        np.testing.assert_array_equal(first_indices(values), expected[1])
