"""Depth and label corruption: exact when off, statistics as requested, errors where promised."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import SimulationError
from shgm_slam.labels import Label
from shgm_slam.sim.corruption import (
    CONFUSIONS,
    CorruptionLevels,
    apply_corruption,
    corrupt_depth,
    corrupt_labels,
)


def test_depth_noise_scale_and_invalid_pixels():
    rng = np.random.default_rng(0)
    depth = rng.uniform(2, 80, (200, 300)).astype(np.float32)
    depth[:10] = 0.0
    same = corrupt_depth(depth, np.random.default_rng(1))
    np.testing.assert_array_equal(same, depth)
    scaled = corrupt_depth(depth, np.random.default_rng(1), scale_error=0.1)
    np.testing.assert_allclose(scaled, depth * 1.1, rtol=1e-6)
    noisy = corrupt_depth(depth, np.random.default_rng(1), noise_rel=0.05)
    rel = (noisy[10:] - depth[10:]) / depth[10:]
    assert abs(rel.std() - 0.05) < 0.005 and abs(rel.mean()) < 0.005
    assert np.all(noisy[:10] == 0.0)
    again = corrupt_depth(depth, np.random.default_rng(1), noise_rel=0.05)
    np.testing.assert_array_equal(noisy, again)  # deterministic by rng
    smooth = corrupt_depth(depth, np.random.default_rng(1), noise_rel=0.05, correlation_px=4)
    e = (smooth[10:] - depth[10:]) / depth[10:]
    neighbour_corr = np.corrcoef(e[:, :-1].ravel(), e[:, 1:].ravel())[0, 1]
    assert neighbour_corr > 0.8 and abs(e.std() - 0.05) < 0.01


def two_class_labels():
    lab = np.full((60, 80), Label.ROAD, np.uint8)
    lab[:, 40:] = Label.BUILDING
    lab[:10] = Label.SKY
    return lab


def test_label_confusion_relabels_whole_segments_to_confusable_classes():
    lab = two_class_labels()
    segments = (lab.astype(np.int32) * 0 + np.arange(80)[None] // 40).astype(np.int32)  # two objects
    np.testing.assert_array_equal(corrupt_labels(lab, np.random.default_rng(0)), lab)
    out = corrupt_labels(lab, np.random.default_rng(0), confusion_prob=1.0, segments=segments)
    assert np.all(out[lab == Label.SKY] == Label.SKY)  # sky is never confused
    road, bld = out[10:, :40], out[10:, 40:]
    assert np.unique(road).tolist() == [CONFUSIONS[Label.ROAD][0]]  # the whole segment changed
    assert len(np.unique(bld)) == 1 and bld[0, 0] in CONFUSIONS[Label.BUILDING]


def test_label_boundaries_jitter_only_near_boundaries():
    lab = two_class_labels()
    out = corrupt_labels(lab, np.random.default_rng(3), boundary_px=3)
    changed = out != lab
    assert changed.any()
    v, u = np.nonzero(changed)
    near = (np.abs(u - 39.5) <= 3.5) | (np.abs(v - 9.5) <= 3.5)
    assert np.all(near)


def test_levels_validate_and_apply():
    with pytest.raises(SimulationError):
        CorruptionLevels(label_confusion=1.5)
    with pytest.raises(SimulationError):
        CorruptionLevels(depth_noise=-0.1)
    levels = CorruptionLevels.from_levels(depth_noise=0.05, label_noise=0.2)
    assert levels.active and levels.label_boundary_px == 2 and levels.depth_correlation_px > 0
    depth = np.full((20, 30), 10.0, np.float32)
    d, _ = apply_corruption(depth, two_class_labels()[:20, :30], CorruptionLevels(), np.random.default_rng(0))
    assert d is depth  # inactive: untouched
