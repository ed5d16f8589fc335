"""Network-like depth errors: exact when off, each part as described, AbsRel as calibrated."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import SimulationError
from shgm_slam.sim.depth_errors import (
    ErrorFieldSequence,
    NetworkDepthErrors,
    abs_rel,
    apply_network_errors,
    bleed_edges,
    calibrate_amplitude,
)


def street_depth(h: int = 96, w: int = 320, near_box: bool = True) -> np.ndarray:
    """A ground plane (depth grows toward the horizon), sky above, optionally a near box in front."""
    v = np.arange(h, dtype=np.float32)[:, None]
    depth = np.where(v > h / 2, 1.6 * 184.0 / np.maximum(v - h / 2, 1e-3), 0.0) * np.ones((1, w), np.float32)
    depth = np.minimum(depth, 80.0).astype(np.float32)
    depth[: h // 2, :] = 0.0
    depth[h // 4 : h // 2, : w // 3] = 30.0  # a facade on the left
    if near_box:
        depth[h // 3 : 3 * h // 4, w // 2 : w // 2 + 40] = 6.0
    return depth


def test_no_amplitude_no_bleeding_is_the_identity():
    d = street_depth()
    e = NetworkDepthErrors(amplitude=0.0, bleed_px=0.0)
    out = apply_network_errors(d, ErrorFieldSequence(d.shape, e).field(0), e)
    np.testing.assert_allclose(out, d, rtol=1e-6)
    assert abs_rel(d, out) < 1e-6


def test_bleeding_pulls_background_toward_the_nearer_surface_only():
    d = street_depth()
    out = bleed_edges(d, 1)
    box = d == 6.0
    np.testing.assert_array_equal(out[box], d[box])  # the foreground keeps its depth
    changed = (out != d) & (d > 0)
    assert changed.any() and np.all(out[changed] < d[changed])  # the background comes nearer
    assert np.all(out[d == 0] == 0)  # sky stays invalid and does not spread (valid-aware mean)
    far_from_edges = np.zeros_like(box)
    far_from_edges[-5:, -50:] = True  # ground far from any edge: unchanged except the plane's own curvature
    assert np.allclose(out[far_from_edges], d[far_from_edges], rtol=0.02)


def test_fields_are_unit_smooth_and_random_access():
    e = NetworkDepthErrors(seed=3)
    seq = ErrorFieldSequence((96, 320), e)
    late = seq.field(7)
    again = ErrorFieldSequence((96, 320), e)
    np.testing.assert_array_equal(again.field(7), late)  # frame 7's field depends only on (seed, 7)
    np.testing.assert_array_equal(seq.field(2), again.field(2))
    f = seq.field(0)
    assert 0.5 < f.std() < 1.5
    assert np.corrcoef(f[:, :-1].ravel(), f[:, 1:].ravel())[0, 1] > 0.95  # low frequency across the image
    with pytest.raises(SimulationError):
        seq.field(-1)


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_temporal_correlation_is_the_flicker_parameter(rho):
    seq = ErrorFieldSequence((24, 80), NetworkDepthErrors(temporal_correlation=rho, seed=1))
    fields = np.stack([seq.field(k) for k in range(400)])
    lag1 = np.corrcoef(fields[:-1].ravel(), fields[1:].ravel())[0, 1]
    assert abs(lag1 - rho) < 0.1


def test_error_grows_with_range():
    d = np.tile(np.linspace(2.0, 80.0, 320, dtype=np.float32), (96, 1))
    e = NetworkDepthErrors(amplitude=0.1, bleed_px=0.0, range_exponent=0.5, seed=2)
    seq = ErrorFieldSequence(d.shape, e)
    near, far = [], []
    for k in range(40):
        log_err = np.log(apply_network_errors(d, seq.field(k), e) / d)
        near.append(np.abs(log_err[:, :40]).mean())
        far.append(np.abs(log_err[:, -40:]).mean())
    assert np.mean(far) > 2.5 * np.mean(near)  # sqrt(80/2) ~ 6x the std, averaged over fields


@pytest.mark.parametrize("target", [0.03, 0.08, 0.12])
def test_calibrated_amplitude_hits_the_target_on_other_frames(target):
    depths = [street_depth(near_box=k % 2 == 0) for k in range(6)]
    e = NetworkDepthErrors(seed=5)
    a = calibrate_amplitude(depths, list(range(6)), e, target)
    ec = e.with_amplitude(a)
    seq = ErrorFieldSequence(depths[0].shape, ec)
    measured = np.mean([abs_rel(street_depth(), apply_network_errors(street_depth(), seq.field(k), ec))
                        for k in range(20, 60)])  # fmt: skip
    assert abs(measured - target) < 0.25 * target


def test_calibration_is_monotone_and_refuses_impossible_targets():
    depths = [street_depth()]
    e = NetworkDepthErrors(seed=5)
    assert calibrate_amplitude(depths, [0], e, 0.05) < calibrate_amplitude(depths, [0], e, 0.1)
    with pytest.raises(SimulationError, match="bleeding alone"):
        calibrate_amplitude(depths, [0], NetworkDepthErrors(bleed_px=8.0), 0.001)
    with pytest.raises(SimulationError):
        calibrate_amplitude([], [], e, 0.05)
    with pytest.raises(SimulationError):
        calibrate_amplitude(depths, [0], e, 1.5)


@pytest.mark.parametrize(
    "kwargs", [{"amplitude": -0.1}, {"global_share": 1.5}, {"temporal_correlation": -0.2}, {"cell_frac": 0.0}]
)
def test_invalid_parameters_raise(kwargs):
    with pytest.raises(SimulationError):
        NetworkDepthErrors(**kwargs)
