"""KISS-ICP at the core of the monocular path: registration against its local map, on the part of a
predicted depth image that is trustworthy, seeded by the visual odometry and fused with it step by step.

Why: a monocular network's depth error lies along the viewing rays and changes from frame to frame,
so ICP on its pseudo-LiDAR slides along a street corridor, the one direction a corridor does not
constrain (plain KISS-ICP on the demo model's depth follows 30-45 % of the path), and a depth error
that differs between the left and the right of the image turns the registered cloud. Image motion
measures both without depth: the visual odometry's turn comes from the tracks' bearings and its length
from many triangulated tracks. Per frame:

1. the visual odometry (``visual.DepthVisualOdometry``) measures this frame's step;
2. the cloud is built from trusted depth (``clouds.trusted_depth``: no occlusion edges or their
   blurred neighbourhood, no sky, people or thin structures) and filtered for sampling density like
   ``KissIcpSource`` does;
3. KISS-ICP registers it against its local map starting from the visual step;
4. the kept step (``step_fusion.fuse_steps``) blends ICP's and the visual odometry's by how noisy
   each one's turns have recently been (``YawNoiseTracker``: three-cornered hat with the image's own
   yaw). Good depth leaves ICP's frame-to-map registration in charge; flickering depth hands the step
   to the visual odometry. The local map is updated with the kept pose.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shgm_slam.errors import ConfigError
from shgm_slam.geometry.se3 import inverse
from shgm_slam.odometry.clouds import depth_to_cloud, trusted_depth
from shgm_slam.odometry.estimate import OdometryEstimate, image_gray, keep_well_sampled, yaw_disagreement_deg
from shgm_slam.odometry.image_rotation import ImageYawEstimator
from shgm_slam.odometry.kiss import KissOdometry
from shgm_slam.odometry.step_fusion import MIN_WEIGHT_SAMPLES, YawNoiseTracker, fuse_steps, step_yaw
from shgm_slam.odometry.visual import DepthVisualOdometry, VisualStatus
from shgm_slam.types import Frame

EDGE_MARGIN_PER_PX = 1.0 / 320.0
"""Pixels dropped around a depth edge per pixel of image width (1 at 320 px, the demo models' size)."""


class HybridOdometrySource:
    """KISS-ICP on trusted pseudo-LiDAR, seeded by the visual odometry and fused with it step by step.

    Args:
        kiss: the KISS-ICP odometry (its range limits apply to the trusted cloud).
        visual_factory: builds a fresh ``DepthVisualOdometry`` (now and on ``reset``).
        cloud_stride: back-projection stride of the trusted cloud.
        max_depth_m: trusted depth range, metres (inf: KISS-ICP's own range only).
        edge_rel_jump: ``clouds.depth_edges`` threshold.
        max_spacing_m: sampling-density filter as in ``KissIcpSource`` (None: off).
        depth_noise_rel: the depth's relative noise, the filter's allowance as in ``KissIcpSource``.
        image_yaw: turn from image motion (the third yaw of the weights, and the health check's).
        noise_window: frames of memory of the yaw noise estimates.
    """

    def __init__(
        self,
        kiss: KissOdometry,
        visual_factory: Callable[[], DepthVisualOdometry],
        *,
        cloud_stride: int,
        max_depth_m: float,
        edge_rel_jump: float,
        max_spacing_m: float | None = None,
        depth_noise_rel: float = 0.0,
        image_yaw: ImageYawEstimator | None = None,
        noise_window: int = 30,
    ) -> None:
        if cloud_stride < 1 or max_depth_m <= 0 or edge_rel_jump <= 0:
            raise ConfigError("hybrid odometry needs cloud_stride >= 1, max_depth_m > 0 and edge_rel_jump > 0")
        self.kiss = kiss
        self._visual_factory = visual_factory
        self.visual = visual_factory()
        self.cloud_stride = cloud_stride
        self.max_depth_m = max_depth_m
        self.edge_rel_jump = edge_rel_jump
        self.max_spacing_m = max_spacing_m
        self.depth_noise_rel = depth_noise_rel
        self.image_yaw = image_yaw
        self.noise = YawNoiseTracker(noise_window)
        self.icp_weight = 0.0  # ICP's weight in the last fused step (diagnostics)

    def reset(self, motion: np.ndarray | None = None) -> None:
        self.kiss.reset(motion)
        self.visual = self._visual_factory()
        if motion is not None:
            self.visual.seed_motion(motion)
        self.noise.reset()
        if self.image_yaw is not None:
            self.image_yaw.reset()

    def _cloud(self, frame: Frame, depth_m: np.ndarray, label_ids: np.ndarray | None) -> np.ndarray:
        margin = max(1, round(EDGE_MARGIN_PER_PX * frame.intrinsics.width))
        depth = trusted_depth(depth_m, label_ids, max_depth_m=self.max_depth_m, edge_rel_jump=self.edge_rel_jump,
                              edge_margin_px=margin)  # fmt: skip
        points, _ = depth_to_cloud(depth, frame.intrinsics, stride=self.cloud_stride,
                                   min_range_m=self.kiss.min_range_m, max_range_m=self.kiss.max_range_m)  # fmt: skip
        if self.max_spacing_m is not None:
            points = keep_well_sampled(points, frame.intrinsics, self.cloud_stride, self.max_spacing_m,
                                       self.depth_noise_rel)  # fmt: skip
        return points

    def update(
        self, frame: Frame, points_cam: np.ndarray, depth_m: np.ndarray | None = None,
        label_ids: np.ndarray | None = None,
    ) -> OdometryEstimate:
        """Pose of ``frame``; ``points_cam`` is not used (the cloud is rebuilt from trusted depth)."""
        gray = image_gray(frame, depth_m, "hybrid")
        T_visual_prev = self.visual.T_odom_cam.copy()
        reg_v = self.visual.register(gray, depth_m, frame.intrinsics, label_ids)
        step_v = inverse(T_visual_prev) @ reg_v.T_odom_cam
        yaw_img = None if self.image_yaw is None else self.image_yaw.update(frame.image_rgb, frame.intrinsics.fx)
        points = self._cloud(frame, depth_m, label_ids)
        T_prev = self.kiss.T_odom_cam
        first = reg_v.status is VisualStatus.FIRST_FRAME or self.kiss.num_frames == 0

        def fuse(step_icp: np.ndarray) -> np.ndarray:
            if reg_v.ok:  # a coasting visual odometry says nothing about this step's turn
                self.noise.update(step_yaw(step_icp), step_yaw(step_v), yaw_img)
            self.icp_weight = self.noise.weight_a(MIN_WEIGHT_SAMPLES) if reg_v.ok else 1.0
            return fuse_steps(step_icp, step_v, self.icp_weight)

        reg = self.kiss.register(points) if first else self.kiss.register(points, step_v, fuse)
        disagreement = None if yaw_img is None or first else yaw_disagreement_deg(T_prev, reg.T_odom_cam, yaw_img)
        ok = reg.ok or reg_v.ok
        note = "" if ok else (
            f"frame {frame.index}: ICP {reg.status.value} ({reg.num_points} trusted points), visual "
            f"{reg_v.status.value} ({reg_v.num_tracks} tracks)"
        )
        return OdometryEstimate(reg.T_odom_cam, ok, note, self.kiss.threshold_m, disagreement)
