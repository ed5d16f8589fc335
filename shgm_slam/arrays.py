"""Small array helpers for the hot paths.

numpy 2's ``np.unique`` is several times slower than one sort on the tens to thousands of integers
the matcher deduplicates per call; these give the same results from one (stable) sort.
"""

from __future__ import annotations

import numpy as np


def run_starts(sorted_values: np.ndarray) -> np.ndarray:
    """(N,) bool: True where a run of equal values of a sorted 1-D array begins."""
    starts = np.empty(sorted_values.shape[0], dtype=bool)
    starts[:1] = True
    np.not_equal(sorted_values[1:], sorted_values[:-1], out=starts[1:])
    return starts


def unique_sorted(values: np.ndarray) -> np.ndarray:
    """``np.unique(values)`` of a 1-D array: its distinct values, ascending."""
    s = np.sort(values)
    return s[run_starts(s)]


def unique_first(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(values, return_index=True, return_inverse=True)`` of a 1-D array.

    Returns:
        (U,) distinct values ascending, (U,) index of each one's first occurrence and (N,) index of each
        value among the distinct ones.
    """
    order = np.argsort(values, kind="stable")
    s = values[order]
    starts = run_starts(s)
    inverse = np.empty(s.shape[0], dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return s[starts], order[starts], inverse


def first_indices(values: np.ndarray) -> np.ndarray:
    """``np.unique(values, return_index=True)[1]``: index of the first occurrence of each distinct value of
    a 1-D array, by ascending value."""
    order = np.argsort(values, kind="stable")
    return order[run_starts(values[order])]


def thinning_stride(count: int, at_most: int) -> int:
    """The smallest stride ``k`` for which ``rows[::k]`` of ``count`` rows keeps at most ``at_most`` of them
    (1 when ``at_most`` < 1: no thinning)."""
    if at_most < 1:
        return 1
    return max(1, -(-int(count) // int(at_most)))
