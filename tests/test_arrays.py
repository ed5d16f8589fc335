"""The sort-based replacements of np.unique give np.unique's results; a cloud thinned for the viewer."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.arrays import first_indices, thinning_stride, unique_first, unique_sorted


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


@pytest.mark.parametrize("count", [0, 1, 7, 8, 9, 30_720, 30_721])
@pytest.mark.parametrize("at_most", [0, 1, 8, 8000, 20_000])
def test_thinning_stride_is_the_smallest_that_fits_and_thinning_twice_changes_nothing(count: int, at_most: int) -> None:
    rows = np.arange(count)
    step = thinning_stride(count, at_most)
    if at_most < 1:
        assert step == 1
        return
    assert len(rows[::step]) <= at_most
    assert step == 1 or len(rows[:: step - 1]) > at_most  # a smaller stride would keep too many
    assert thinning_stride(len(rows[::step]), at_most) == 1
