"""Step fusion: the blend's ends and middle, noise variances recovered by the three-cornered hat, and KISS-ICP's
step blended with the image tracks' by them."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import ConfigError
from shgm_slam.geometry.se3 import make_pose, rot_x, rot_y, rotation_angle
from shgm_slam.odometry.image_rotation import yaw_of
from shgm_slam.odometry.step_fusion import MIN_WEIGHT_SAMPLES, ImageStepBlend, YawNoiseTracker, fuse_steps


def test_blend_ends_are_the_inputs_and_the_middle_is_halfway():
    a = make_pose(rot_y(0.2) @ rot_x(0.05), [0.3, 0.0, 1.2])
    b = make_pose(rot_y(-0.1), [0.0, 0.1, 0.8])
    np.testing.assert_allclose(fuse_steps(a, b, 1.0), a, atol=1e-12)
    np.testing.assert_allclose(fuse_steps(a, b, 0.0), b, atol=1e-12)
    mid = fuse_steps(a, b, 0.5)
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (a[:3, 3] + b[:3, 3]))
    to_a = rotation_angle(mid[:3, :3].T @ a[:3, :3])
    to_b = rotation_angle(mid[:3, :3].T @ b[:3, :3])
    assert to_a == pytest.approx(to_b, abs=1e-9)  # geodesic midpoint
    assert to_a == pytest.approx(0.5 * rotation_angle(a[:3, :3].T @ b[:3, :3]), abs=1e-9)
    np.testing.assert_allclose(fuse_steps(a, b, 7.0), a, atol=1e-12)  # weights are clipped to [0, 1]


@pytest.mark.parametrize(("sigma_a", "sigma_b"), [(0.002, 0.01), (0.01, 0.002), (0.004, 0.004)])
def test_three_cornered_hat_recovers_each_noise(sigma_a, sigma_b):
    rng = np.random.default_rng(0)
    tracker = YawNoiseTracker(window=2000)
    sigma_image = 0.003
    for _ in range(4000):
        truth = rng.normal(0, 0.05)
        tracker.update(truth + rng.normal(0, sigma_a), truth + rng.normal(0, sigma_b),
                       truth + rng.normal(0, sigma_image))  # fmt: skip
    var_a, var_b = tracker.variances_rad2
    assert np.sqrt(var_a) == pytest.approx(sigma_a, rel=0.2)
    assert np.sqrt(var_b) == pytest.approx(sigma_b, rel=0.2)
    w = tracker.weight_a(min_samples=10)
    assert w == pytest.approx(sigma_b**2 / (sigma_a**2 + sigma_b**2), abs=0.1)


def test_no_weight_before_enough_steps_and_steps_without_image_yaw_are_not_counted():
    tracker = YawNoiseTracker()
    for _ in range(5):
        tracker.update(0.01, 0.0, 0.0)
        tracker.update(0.5, 0.0, None)
    assert tracker.samples == 5
    assert tracker.weight_a(min_samples=10) == 0.0
    tracker.reset()
    assert tracker.samples == 0
    with pytest.raises(ConfigError):
        YawNoiseTracker(window=1)


def test_yaw_of_a_fused_step_lies_between():
    a, b = make_pose(rot_y(0.3), [0, 0, 1.0]), make_pose(rot_y(0.1), [0, 0, 1.0])
    assert 0.1 < yaw_of(fuse_steps(a, b, 0.3)) < 0.3


def _noisy_turns(blend: ImageStepBlend, sigma_icp: float, sigma_image_step: float, steps: int, seed: int = 0):
    """Feed ``steps`` turns (radians, 1 m forward) measured by ICP, by the image tracks and by the image's own yaw
    (0.002 rad noise) with the given noise; returns the last (truth, blended) yaw."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        truth = rng.normal(0.0, 0.05)
        icp = make_pose(rot_y(truth + rng.normal(0.0, sigma_icp)), [0.0, 0.0, 1.0])
        image = make_pose(rot_y(truth + rng.normal(0.0, sigma_image_step)), [0.0, 0.0, 1.0])
        kept = blend(icp, image, truth + rng.normal(0.0, 0.002))
    return truth, yaw_of(kept)


def test_the_blend_follows_whichever_step_turns_less_noisily():
    """Noisy depth (ICP's turns 10x noisier than the tracks'): the kept steps follow the image; the other way
    round they follow ICP; the error of the kept turn is below the worse input's either way."""
    for sigma_icp, sigma_image, icp_heavy in ((0.02, 0.002, False), (0.002, 0.02, True)):
        blend = ImageStepBlend(window=200)
        errors = []
        for seed in range(200):
            truth, kept = _noisy_turns(blend, sigma_icp, sigma_image, 1 if seed else 100, seed)
            errors.append(kept - truth)
        assert (blend.icp_weight > 0.9) is icp_heavy and (blend.icp_weight < 0.1) is not icp_heavy
        assert np.sqrt(np.mean(np.square(errors))) < 0.3 * max(sigma_icp, sigma_image)


def test_the_blend_keeps_icps_step_without_tracks_and_the_images_before_it_has_measured():
    blend = ImageStepBlend()
    icp, image = make_pose(rot_y(0.1), [0.0, 0.0, 1.0]), make_pose(rot_y(0.0), [0.0, 0.0, 0.9])
    assert blend(icp, None, 0.05) is icp  # the tracks solved no step
    assert blend.icp_weight is None
    for _ in range(MIN_WEIGHT_SAMPLES - 1):
        np.testing.assert_allclose(blend(icp, image, 0.05), image, atol=1e-12)  # too few turns to weigh ICP
    assert blend.icp_weight == 0.0
    blend(icp, image, 0.0)  # the image agrees with the tracks: ICP's turn is the noisy one
    assert blend.icp_weight is not None and blend.icp_weight < 0.5
    blend.reset()
    assert blend.icp_weight is None and blend.noise.samples == 0
