"""What every odometry source returns and the helpers several of them share.

``OdometryEstimate`` is one frame's pose (``T_odom_cam``: the camera in the robot's odometry frame, the camera
frame of its first frame) with its diagnostics; ``OdometrySource`` the protocol every source implements
(``sources.make_odometry`` builds one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import inverse
from shgm_slam.odometry.clouds import sampling_spacing_m
from shgm_slam.odometry.image_rotation import yaw_of
from shgm_slam.types import Frame, Intrinsics


@dataclass(frozen=True)
class OdometryEstimate:
    """Pose of one frame. ``ok`` is False when the pose is a prediction (e.g. a degenerate cloud).

    The optional diagnostics feed ``health.OdometryHealthMonitor``: ``threshold_m`` is the source's
    registration threshold after this frame (KISS-ICP's adaptive σ, metres), ``rotation_disagreement_deg``
    how far the source's rotation of this step is from the rotation measured from image motion;
    ``planar_turn`` whether the step's turn came from a ground vehicle's planar motion (visual odometry),
    ``road_step`` whether its length and direction came from the road's image motion (visual odometry),
    ``image_step`` whether ICP slipped against the image motion and the step solved from image tracks was
    kept (KISS-ICP, ``flow_check``), ``image_window`` whether the step also corrects the pose by the motion
    of the last second solved from image tracks (KISS-ICP, ``window_check``: the step then holds that
    correction, not one frame's motion); ``new_reference`` whether the frame became the visual odometry's
    tracking reference, ``levelled`` whether that reference's tilt was turned towards level (the ground in
    view: a UAV's camera); ``map_misfit`` how badly the frame's cloud fits the source's local map under the step
    kept, where the source measured it (KISS-ICP on noise-free depth: ``Registration.map_misfit``).
    """

    T_odom_cam: np.ndarray
    ok: bool
    note: str = ""
    threshold_m: float | None = None
    rotation_disagreement_deg: float | None = None
    planar_turn: bool = False
    road_step: bool = False
    image_step: bool = False
    image_window: bool = False
    new_reference: bool = False
    levelled: bool = False
    map_misfit: float | None = None


@runtime_checkable
class OdometrySource(Protocol):
    """Anything that turns frames (and their camera-frame clouds) into ``T_odom_cam`` poses."""

    def update(
        self, frame: Frame, points_cam: np.ndarray, depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
    ) -> OdometryEstimate:
        """Pose of ``frame``.

        Args:
            frame: the frame (its image, intrinsics, and ground truth when the source needs them).
            points_cam: (N, 3) its pseudo-LiDAR cloud in the camera frame, metres.
            depth_m: (H, W) the depth image the cloud came from (files or a model), metres.
            label_ids: (H, W) its Cityscapes train ids, or None.
        """
        ...

    def reset(self, motion: np.ndarray | None = None) -> None:
        """Re-initialise: the next frame starts a new odometry frame (after a detected divergence).

        Args:
            motion: optional (4, 4) the vehicle's last trusted frame-to-frame motion (a frame's camera in the
                previous frame's camera, metres): the constant-velocity model's prediction of the new odometry
                frame's first step, since a vehicle's velocity does not restart with its odometry (sources that
                measure absolute poses ignore it); None: the first step is predicted at rest.
        """
        ...


MIN_SPACED_POINTS = 1000
"""The spacing filter keeps at least this many points (the best-sampled ones): a UAV whose nearest
ground is ~60 m away has only ~250 of its 7680 points under 0.6 m spacing, too few for ICP (it then
coasts and the health check ends the trajectory segment); KISS-ICP registers the 1000 best fine."""


NOISE_SPACING_SIGMAS = 3.0
"""The spacing filter's allowance for depth noise: a point's neighbours may lie this many times the depth noise
at its depth (``depth_noise_rel`` x z) farther apart than ``max_spacing_m``. Noise moves neighbouring samples
apart along their rays, so on a noisy sensor the filter otherwise drops the far points that hold the forward
motion (2 % noise, tuning world airsim-like 76, a car's KISS-ICP alone: 1.98 m ATE with the filter, 0.92 m
without it)."""


def keep_well_sampled(
    points_cam: np.ndarray, intrinsics: Intrinsics, cloud_stride: int, max_spacing_m: float,
    noise_rel: float = 0.0,
) -> np.ndarray:  # fmt: skip
    """The points of a pseudo-LiDAR cloud whose image-grid neighbours are at most ``max_spacing_m`` (plus
    ``NOISE_SPACING_SIGMAS`` x ``noise_rel`` x the point's depth) apart (``clouds.sampling_spacing_m``), or the
    ``MIN_SPACED_POINTS`` best-sampled ones when fewer.

    Args:
        points_cam: (N, 3) camera-frame points as back-projected with ``cloud_stride``, metres.
        intrinsics: intrinsics of the depth map they came from.
        noise_rel: the depth's random error relative to the depth (0: noise-free; ``scene_scale``).

    Returns:
        (M, 3) the kept points, in their order.
    """
    if len(points_cam) == 0:
        return points_cam
    spacing_m = sampling_spacing_m(points_cam, intrinsics, stride=cloud_stride)
    allowed_m = max_spacing_m
    if noise_rel > 0:  # noisy depth: neighbours also lie as far apart as the noise at their depth moves them
        allowed_m = max_spacing_m + NOISE_SPACING_SIGMAS * noise_rel * np.abs(points_cam[:, 2])
    keep = spacing_m <= allowed_m
    if keep.sum() < MIN_SPACED_POINTS:  # all far (a UAV over distant ground): the best-sampled ones
        keep = np.zeros(len(points_cam), dtype=bool)
        keep[np.argsort(spacing_m, kind="stable")[:MIN_SPACED_POINTS]] = True
    return points_cam[keep]


def image_gray(frame: Frame, depth_m: np.ndarray | None, kind: str) -> np.ndarray:
    """(H, W) uint8 grayscale of ``frame``'s RGB image for an odometry that tracks image motion.

    Raises:
        DataError: the frame has no RGB image or no depth image (``kind`` names the odometry).
    """
    if frame.image_rgb is None or depth_m is None:
        raise DataError(
            f"frame {frame.index}: {kind} odometry needs the RGB image and a depth image "
            "(a depth model or depth/ files); use odometry kind 'kiss-icp' for clouds only"
        )
    return cv2.cvtColor(np.ascontiguousarray(frame.image_rgb), cv2.COLOR_RGB2GRAY)


def yaw_disagreement_deg(T_prev: np.ndarray, T_new: np.ndarray, yaw_img_rad: float) -> float:
    """|yaw of the step T_prev -> T_new (odometry frame poses) - yaw from image motion|, degrees."""
    yaw_step = yaw_of(inverse(T_prev) @ T_new)
    return float(np.degrees(abs(np.angle(np.exp(1j * (yaw_step - yaw_img_rad))))))
