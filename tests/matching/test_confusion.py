"""Confused labels' traces: the Bayes factor's integral and the shared shift products."""

from __future__ import annotations

import numpy as np

from shgm_slam.matching.confusion import _confusion_factors, _integrated_factors, _shifted_hits


def test_the_traces_integral_is_skipped_only_where_it_is_zero():
    """Hypotheses whose likelihood ratio falls from chance (slope <= 0 at c = 0) are not integrated: their factor is 0,
    as the integral gives; the others are integrated as on their own."""
    rng = np.random.default_rng(5)
    h, n = 40, 600
    owner = rng.integers(0, h, n)
    q0 = rng.uniform(0.05, 0.6, n)
    rate = rng.uniform(0.0, 0.5, h)  # some hypotheses far beyond chance, most at or below it
    trace = rng.random(n) < np.minimum(1.0, q0 + rate[owner] * (1.0 - q0) - 0.1)
    fast = _confusion_factors(q0, trace, owner, h)
    full = _integrated_factors(q0, trace, owner, h)
    np.testing.assert_allclose(fast, full, rtol=1e-12, atol=1e-12)
    assert (fast > 0.0).sum() >= 5 and (fast == 0.0).sum() >= 5


def test_shifted_hits_shared_shift_sets_as_one_at_a_time():
    """Hypotheses whose shifts are the first's share one product; the hits are those of each hypothesis alone."""
    rng = np.random.default_rng(6)
    fixed = rng.normal(0, 8, (10, 3))
    shifts = np.stack([fixed, fixed, fixed + np.array([0.5, 0.0, 0.0]), fixed])  # hypothesis 2 turns its own way
    offsets = rng.normal(0, 8, (300, 3))
    owner = rng.integers(0, 4, 300)
    rows = rng.integers(0, 50, 300)
    together = _shifted_hits(offsets, rows, 50, shifts, owner, 3.0)
    alone = np.zeros_like(together)
    for k in range(4):
        mine = owner == k
        alone |= _shifted_hits(offsets[mine], rows[mine], 50, shifts[k : k + 1], np.zeros(mine.sum(), int), 3.0)
    assert together.any() and np.array_equal(together, alone)
