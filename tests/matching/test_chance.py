"""The chance model's repeated structure: shifts along any street's heading, the rows' own repeats, the
label chance rate."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.labels import Label
from shgm_slam.matching.chance import (
    CHANCE_PRIOR_OBSERVATIONS,
    MAX_ROW_STEP_M,
    MAX_SHIFT_HEADINGS,
    MIN_ROW_NODES,
    label_chance,
    row_steps,
    shift_headings,
    shift_vectors,
)
from shgm_slam.matching.labelled_tree import LabelledTree

UP_Z = (0.0, 0.0, 1.0)


@pytest.mark.parametrize("radius_m", [1.0, 2.0, 3.0, 5.0])
def test_some_shift_runs_along_a_street_of_any_heading(radius_m):
    """Whatever the street's heading, at every shift distance one shift lands within the radius of the
    along-street shift (so a row repeating along the street is measured by chance)."""
    distances = (6.0, 10.0, 14.0)
    shifts = shift_vectors(np.array(UP_Z), radius_m, distances)
    n = shift_headings(radius_m, distances)
    assert shifts.shape == (n * len(distances), 3) and n % 2 == 0
    assert not shifts.flags.writeable and np.allclose(shifts[:, 2], 0.0)
    theta = np.linspace(0.0, 2.0 * np.pi, 721)
    for d in distances:
        along = d * np.column_stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)])
        gap = np.linalg.norm(along[:, None] - shifts[None], axis=2).min(axis=1)
        assert gap.max() <= radius_m + 1e-9
    assert shift_headings(3.0, distances) == 16  # 8 (45 degrees apart) missed by up to 5.4 m at 14 m
    assert shift_headings(2.0 * 14.0, distances) == 4
    assert shift_headings(1e-3, distances) == MAX_SHIFT_HEADINGS  # a needle radius does not explode the cost


def test_row_steps_are_the_repeats_many_nodes_share():
    """A lamp row every 25 m gives its +-25 m step along the row (horizontal, its label); trees every 10 m are
    within the fixed shifts' reach and give none; scattered signs give none (no step shared by
    ``MIN_ROW_NODES``); a row of three is not a row; the frame's vertical is dropped from every step."""
    rng = np.random.default_rng(0)
    heading = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    lamps = np.arange(8)[:, None] * 25.0 * heading + [0.0, -6.0, 0.0] + np.c_[np.zeros((8, 2)), rng.uniform(3, 5, 8)]
    trees = np.arange(20)[:, None] * 10.0 * heading + [0.0, 7.0, 4.0]
    signs = np.column_stack([rng.uniform(0, 200, 6), rng.uniform(-60, 60, 6), np.full(6, 2.0)])
    three = np.arange(3)[:, None] * 30.0 * heading + [0.0, 40.0, 1.0]
    pos = np.vstack([lamps, trees, signs, three])
    labels = np.concatenate([np.full(8, Label.POLE), np.full(20, Label.VEGETATION), np.full(6, Label.TRAFFIC_SIGN),
                             np.full(3, Label.TRAFFIC_LIGHT)])  # fmt: skip
    steps, owners = row_steps(LabelledTree(pos, labels), np.array(UP_Z), radius_m=3.0, longer_than_m=17.0)
    assert len(steps) >= 2 and set(owners.tolist()) == {int(Label.POLE)}
    assert np.allclose(steps[:, 2], 0.0)
    assert np.allclose(np.linalg.norm(steps, axis=1), 25.0, atol=1.0)
    assert np.allclose(np.abs(steps @ heading), 25.0, atol=1.0)
    none, _ = row_steps(LabelledTree(pos, labels), np.array(UP_Z), radius_m=3.0, longer_than_m=17.0, max_m=20.0)
    assert none.shape == (0, 3)
    assert MIN_ROW_NODES > 3 and MAX_ROW_STEP_M >= 25.0


def _label_chance_per_label(hits, label_ids, inside, prior):
    """``label_chance`` label by label (the definition)."""
    out = prior.copy()
    for label in np.unique(label_ids[inside]):
        rows = np.flatnonzero(inside & (label_ids == label))
        best = np.sort(hits[:, rows].sum(axis=1))[-2]
        m = CHANCE_PRIOR_OBSERVATIONS
        out[rows] = np.maximum(prior[rows], (best + m * prior[rows]) / (rows.size + m))
    return out


def test_label_chance_equals_the_per_label_loop():
    rng = np.random.default_rng(3)
    for trial in range(200):
        n, shifts = int(rng.integers(1, 80)), int(rng.integers(2, 30))
        hits = rng.random((shifts, n)) < rng.random()
        labels = rng.integers(0, 19 if trial % 2 else 3, n)
        inside = rng.random(n) < rng.random()
        prior = rng.random(n) * rng.random()
        expected = _label_chance_per_label(hits, labels, inside, prior)
        np.testing.assert_array_equal(label_chance(hits, labels, inside, prior), expected)
