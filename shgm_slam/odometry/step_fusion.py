"""Fusing two odometries' frame-to-frame steps with weights measured from the data.

``YawNoiseTracker`` estimates how noisy each of two odometries' turns are from three independent
measurements of every step's yaw, the two odometries and the image motion (``image_rotation``), by
the three-cornered hat: with independent errors, the mean squared difference of a pair is the sum of
their variances, so three pairs give each one's variance. ``fuse_steps`` then blends the two steps by
inverse variance. The turn is what tells good depth from bad: a depth error that differs across the
image turns an ICP-registered cloud, while bearings (and so the image's own yaw) do not depend on it.
``ImageStepBlend`` does this for KISS-ICP's step and the one solved from the image tracks (PnP) on a
depth sensor's noisy depth.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from shgm_slam.errors import ConfigError
from shgm_slam.odometry.image_rotation import yaw_of

MIN_WEIGHT_SAMPLES = 10
"""Steps with an image yaw before odometry A (ICP) gets any weight (the variances need a few samples)."""


class YawNoiseTracker:
    """Running variances of the yaw errors of odometries A and B (three-cornered hat with image yaw).

    Args:
        window: frames of memory (exponential forgetting with weight 1/window per new step).
        floor_rad: smallest standard deviation reported (keeps the weights finite), radians.
    """

    def __init__(self, window: int = 30, floor_rad: float = 1e-4) -> None:
        if window < 2 or floor_rad <= 0:
            raise ConfigError("yaw noise tracker needs window >= 2 and floor_rad > 0")
        self.alpha = 1.0 / window
        self.floor2 = floor_rad**2
        self.samples = 0
        self._ab = self._ai = self._bi = 0.0

    def reset(self) -> None:
        self.samples = 0
        self._ab = self._ai = self._bi = 0.0

    def update(self, yaw_a_rad: float, yaw_b_rad: float, yaw_image_rad: float | None) -> None:
        """Add one step's yaw (radians) from A, B and the image (None: this step is not counted)."""
        if yaw_image_rad is None:
            return
        a = self.alpha if self.samples else 1.0
        self._ab += a * ((yaw_a_rad - yaw_b_rad) ** 2 - self._ab)
        self._ai += a * ((yaw_a_rad - yaw_image_rad) ** 2 - self._ai)
        self._bi += a * ((yaw_b_rad - yaw_image_rad) ** 2 - self._bi)
        self.samples += 1

    @property
    def variances_rad2(self) -> tuple[float, float]:
        """(var A, var B) of the per-step yaw error, radians squared (each at least the floor)."""
        var_a = max(0.5 * (self._ab + self._ai - self._bi), self.floor2)
        var_b = max(0.5 * (self._ab + self._bi - self._ai), self.floor2)
        return var_a, var_b

    def weight_a(self, min_samples: int) -> float:
        """Inverse-variance weight of A in [0, 1]; 0 (trust B) before ``min_samples`` steps."""
        if self.samples < min_samples:
            return 0.0
        var_a, var_b = self.variances_rad2
        return var_b / (var_a + var_b)


def fuse_steps(step_a: np.ndarray, step_b: np.ndarray, weight_a: float) -> np.ndarray:
    """Blend two estimates of one frame-to-frame step: ``weight_a`` of A, the rest of B.

    Args:
        step_a, step_b: (4, 4) motion of this frame in the previous camera frame, metres.
        weight_a: A's weight in [0, 1].

    Returns:
        (4, 4) the step whose rotation lies ``weight_a`` of the way from B's to A's (geodesic) and
        whose translation is the weighted mean of theirs.
    """
    w = float(np.clip(weight_a, 0.0, 1.0))
    a, b = np.asarray(step_a, dtype=np.float64), np.asarray(step_b, dtype=np.float64)
    out = np.eye(4)
    rel = Rotation.from_matrix(b[:3, :3].T @ a[:3, :3]).as_rotvec()
    out[:3, :3] = b[:3, :3] @ Rotation.from_rotvec(w * rel).as_matrix()
    out[:3, 3] = (1.0 - w) * b[:3, 3] + w * a[:3, 3]
    return out


def step_yaw(step: np.ndarray) -> float:
    """Yaw (about the camera's y axis) of a (4, 4) step, radians."""
    return yaw_of(step)


class ImageStepBlend:
    """KISS-ICP's step blended with the step solved from the image tracks (``flow_check.pnp_step``), A and B of a
    ``YawNoiseTracker`` with the images' own turn as the third.

    On noisy depth ICP's steps suffer and the tracks' do not: PnP's turn comes from bearings, its length from
    ~150 tracked points at once. Measured per step against the truth at 2 % depth noise (tuning seed 10, 10 Hz,
    synthia-like backward camera): ICP's roll / pitch / yaw 0.18 / 0.09 / 0.09 deg rms and 0.12 m along the
    road, PnP's 0.03 / 0.03 / 0.04 deg and 0.03 m; KISS-ICP alone 12.8 m ATE, blended 2.9 m. On perfect depth ICP
    is the better one where it matters (an airsim-like UAV's pitch: 0.03 deg against PnP's 0.06, biased, and
    its blend 0.4 -> 2.3 m ATE), so the blend is only on where the depth's noise measures above 0; and a camera
    that sees only the ground keeps ICP's steps on noisy depth too (PnP on a narrow view of one distant plane
    trades pitch for sideways motion: the UAVs of tuning seeds 10 and 11 at 2 % noise, 3.7 / 2.6 m alone,
    4.8 / 3.4 m blended) (``OdometryConfig.image_step_blend``; ``scene_scale.derived_values``).

    Args:
        window: frames of memory of the yaw noise estimates.
    """

    def __init__(self, window: int = 30) -> None:
        self.noise = YawNoiseTracker(window)
        self.icp_weight: float | None = None  # the last blend's weight of ICP's step

    def reset(self) -> None:
        self.noise.reset()
        self.icp_weight = None

    def __call__(self, icp_step: np.ndarray, image_step: np.ndarray | None, yaw_image_rad: float | None) -> np.ndarray:
        """The step to keep: ICP's and the image tracks' ((4, 4) each, this frame's camera in the previous one)
        blended by inverse variance of their turns (``fuse_steps``; all image before ``MIN_WEIGHT_SAMPLES`` steps
        with an image yaw); ICP's own where the tracks solved none (None). ``yaw_image_rad``: the images' turn
        for this step, radians (None: not measured, the variances are not updated)."""
        if image_step is None:
            return icp_step
        self.noise.update(step_yaw(icp_step), step_yaw(image_step), yaw_image_rad)
        self.icp_weight = self.noise.weight_a(MIN_WEIGHT_SAMPLES)
        return fuse_steps(icp_step, image_step, self.icp_weight)
