"""Depth-assisted monocular visual odometry: KLT tracks from a reference frame, PnP on its depth.

Why not ICP for the RGB-only path: a pseudo-LiDAR cloud from a monocular depth network carries
depth errors along the viewing rays, i.e. along the direction of travel, where a street corridor
constrains ICP least; KISS-ICP on the demo model's depth follows only 30-45 % of the path. Image
features constrain the motion through their 2-D positions instead, and the network's depth only
sets the scale (through the reference frame's 3-D points), so its per-pixel errors average out.

The method (per frame):

1. KLT-track the reference frame's corners from the previous image into this one (pyramidal
   Lucas-Kanade, with a forward-backward check that drops tracks which do not return home).
2. Solve PnP (RANSAC, then Levenberg-Marquardt on the inliers) between the reference frame's 3-D
   points, back-projected from its depth, and the tracked pixels; the constant-velocity prediction
   seeds it. Tracking against a reference (not the previous frame) compounds the depth error only
   once per reference (true depth, airsim-like: ATE 4.1 -> 1.7 m for car1, 16.1 -> 6.3 m for the UAV).
   With ``planar_motion`` the turn since the previous frame comes from image motion alone: corners
   found afresh in the previous image and tracked into this one (``planar_motion.planar_turn``: a car
   turns about the vertical and drives where it points), where they agree with that model: PnP's yaw
   is replaced by it and the translation solved again with the rotation held. PnP on a network's depth
   trades turns for sideways shifts; the heading drift that compounds from it is what bent RGB-only
   trajectories away.
3. When fewer than ``min_track_fraction`` of the reference's corners survive (or fewer than
   ``min_tracks``), this frame becomes the new reference: fresh corners, 3-D from its own depth.

4. With ``road_steps`` (a car: a level road plane in view), each frame's step length and direction come
   from the road instead (``ground_speed.ground_step``): the step runs along the chord of the turn in the
   road plane, and its length is the one whose plane-induced homography moves the previous image's
   textured road onto this image best. Tracks on edges that run along the street (a bus's stripes, a
   kerb) slide along themselves under forward motion, and PnP then read steps 30-70 % short and up to
   40 deg sideways for seconds (with true depth as with a network's). The output chain composes these
   steps on the tracking chain's turns; the tracking chain itself (PnP against the reference) is kept
   as it is, so its turns still do not compound. The length is in the road plane's height: measured in
   each frame's depth, or, with ``road_height_m``, the camera's known mounting height (a network's scale
   swings from frame to frame; on real KITTI 07 the demo depth model's road lay 2-10 m below the camera).

5. With ``ground_attitude`` (a camera that sees only the ground: a UAV looking down), each new reference's
   roll and pitch are pulled towards level: the ground plane fitted to its depth and labels
   (``geometry.ground.ground_normal``) says where up is in the camera; turned into the odometry frame by
   the reference's pose it should point where the first references' did, and the pose (the tracking chain
   and the output chain alike, about the camera centre) is turned towards that by at most
   ``GROUND_ATTITUDE_STEP_DEG`` (a plane ``GROUND_ATTITUDE_MAX_TILT_DEG`` or more from the last one used is a
   bad plane, skipped).
   The tracking chain compounds its rotation error at every new reference, and a UAV's tilt, which no
   planar turn holds, drifted by 10-34 deg over 600 m (airsim-like tuning worlds, demo models), its
   steps tilted with it. Yaw is not touched: the ground does not see it.

Frames where PnP fails keep the constant-velocity prediction and are reported (``ok`` False).
Poses are ``T_odom_cam``: the camera in the odometry frame, which is the first frame's camera.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import Enum

import cv2
import numpy as np

from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.camera import backproject
from shgm_slam.geometry.ground import ground_normal
from shgm_slam.geometry.se3 import inverse, project_to_so3, so3_exp
from shgm_slam.labels import Label
from shgm_slam.odometry.ground_speed import MAX_ROAD_CONTRAST, MIN_ROAD_GRADIENT, ground_step, textured_road_pixels
from shgm_slam.odometry.image_rotation import rot_y
from shgm_slam.odometry.planar_motion import PlanarTurn, epipolar_support, planar_turn
from shgm_slam.perception.ground_scale import RoadPlane, road_plane
from shgm_slam.types import Intrinsics

MIN_PLANAR_SUPPORT = 0.8
"""A frame's planar turn replaces PnP's when at least this share of its corners agree with it (or at least as many
as agree with PnP's own motion: ``DepthVisualOdometry._planar_fits``). Rendered
cars, 320x96: median 0.96-0.99 and 1st percentile 0.66-0.85 per drive; the frames whose turn was off by
more than 0.5 deg had 0.40-0.77; a UAV (which does not move like a car) 0.2-0.33. Real KITTI 07 (160
frames, 1226x370): 154 frames at or above it, their turns 0.13 deg RMS from the ground truth."""

GROUND_ATTITUDE_STEP_DEG = 1.0
"""Most a new reference's tilt is turned towards level (``ground_attitude``, module docstring step 5). The
chain's tilt drifts by a few tenths of a degree between references; a plane fitted to a network's depth errs
by 2-3 deg (median, UAV at 44-54 m; ``geometry.ground``), so each reference moves the tilt a little and many
average its error."""

GROUND_ATTITUDE_MAX_TILT_DEG = 10.0
"""A reference whose up (in the odometry frame) lies this far or farther from the last one used is not used:
a bad plane (the 90th percentile of a UAV's plane errors on the demo models' depth is 6-10 deg, frames with
little ground in view err by 40-58 deg), while the chain turns by a fraction of a degree between references.
Measured against the last plane used, not against level: a chain that has tilted far from level (a rough
start) is brought back a step at a time."""

GROUND_ATTITUDE_FIRST = 9
"""Level is where most of the first this many references' measured up agree (the odometry frame's, before any
correction: within ``GROUND_ATTITUDE_MAX_TILT_DEG`` of each other, more than half of them); until they do, the
oldest gives way to the next. One plane's error would tilt the whole run (airsim-like tuning world 11: the
first two references' planes 32-41 deg off the rest)."""

GROUND_ATTITUDE_EARLIEST = 3
"""Level is the mean of the earliest this many of the agreeing references' up: the chain has drifted least
there (by the ninth reference a UAV's chain had tilted by up to 7 deg: airsim-like tuning world 11)."""

GROUND_STRIDE = 2
"""Every this many pixels (both directions) back-projected for the ground plane (thousands of points at 320x96)."""


class VisualStatus(str, Enum):
    """Outcome of one frame of visual odometry."""

    OK = "ok"
    FIRST_FRAME = "first-frame"  # the odometry frame starts here
    FEW_TRACKS = "few-tracks"  # too few corners with depth survived: constant-velocity prediction
    PNP_FAILED = "pnp-failed"  # RANSAC found too few inliers or an implausible jump: prediction used


@dataclass(frozen=True)
class VisualRegistration:
    """Result of ``DepthVisualOdometry.register``.

    Attributes:
        T_odom_cam: (4, 4) camera pose in the odometry frame (a copy).
        status: what happened.
        num_tracks: reference corners tracked into this frame (before PnP).
        num_inliers: PnP inliers (0 when PnP did not run or failed).
        new_reference: whether this frame became the tracking reference.
        planar_turn: whether this frame's turn came from planar circular motion (``planar_motion``).
        road_step: whether this frame's step (length and direction) came from the road (``road_steps``).
        levelled: whether this frame became the tracking reference and its tilt was turned towards level
            (``ground_attitude``).
    """

    T_odom_cam: np.ndarray
    status: VisualStatus
    num_tracks: int
    num_inliers: int
    new_reference: bool
    planar_turn: bool = False
    road_step: bool = False
    levelled: bool = False

    @property
    def ok(self) -> bool:
        return self.status in (VisualStatus.OK, VisualStatus.FIRST_FRAME)


def backproject_pixels(pixels_uv: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """3-D points of sub-pixel positions, depth read at the nearest pixel.

    Args:
        pixels_uv: (N, 2) pixel coordinates (u right, v down) inside the image.
        depth_m: (H, W) metric depth along the optical axis (z), metres.
        intrinsics: pinhole intrinsics of the image.

    Returns:
        (N, 3) float64 points in the camera frame (x right, y down, z forward), metres.
    """
    h, w = depth_m.shape
    u = np.clip(np.rint(pixels_uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(pixels_uv[:, 1]).astype(np.int64), 0, h - 1)
    z = depth_m[v, u].astype(np.float64)
    x = (pixels_uv[:, 0] - intrinsics.cx) / intrinsics.fx * z
    y = (pixels_uv[:, 1] - intrinsics.cy) / intrinsics.fy * z
    return np.stack([x, y, z], axis=1)


def triangulated_scale(
    T_cam_ref: np.ndarray,
    uv_ref: np.ndarray,
    uv_cam: np.ndarray,
    z_ref_m: np.ndarray,
    K: np.ndarray,
    *,
    min_parallax_deg: float = 1.0,
    min_points: int = 20,
) -> float | None:
    """Length of the translation of ``T_cam_ref`` that makes triangulated depths match ``z_ref_m``.

    The tracks are triangulated with the rotation of ``T_cam_ref`` and a unit baseline along its
    translation; the scale is the median ratio of the given (network) depths to the triangulated
    ones over tracks with at least ``min_parallax_deg`` of parallax. A median of ratios is not
    shrunk by depth noise, unlike the least-squares PnP translation, whose lever arms are the noisy
    depths themselves (errors in variables: noisier depth, shorter path).

    Args:
        T_cam_ref: (4, 4) pose of the reference camera in the current camera's frame.
        uv_ref, uv_cam: (N, 2) pixels of the same tracks in the reference and current image.
        z_ref_m: (N,) their depths in the reference frame, metres.
        K: (3, 3) camera matrix.

    Returns:
        The translation length in metres, or None with too few well-triangulated tracks.
    """
    t = T_cam_ref[:3, 3]
    norm = float(np.linalg.norm(t))
    if norm < 1e-9 or len(uv_ref) < min_points:
        return None
    R, t_unit = T_cam_ref[:3, :3], t / norm
    P_ref = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_cam = K @ np.hstack([R, t_unit[:, None]])
    X_h = cv2.triangulatePoints(P_ref, P_cam, uv_ref.T.astype(np.float64), uv_cam.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X_h[:3] / X_h[3]).T  # (N, 3) reference frame, unit-baseline units
        centre_cam = -R.T @ t_unit  # current camera centre in the reference frame
        ray_ref = X / np.linalg.norm(X, axis=1, keepdims=True)
        ray_cam = (X - centre_cam) / np.linalg.norm(X - centre_cam, axis=1, keepdims=True)
        parallax_deg = np.degrees(np.arccos(np.clip(np.sum(ray_ref * ray_cam, axis=1), -1.0, 1.0)))
        z_cam = X @ R[2] + t_unit[2]
        good = (X[:, 2] > 0) & (z_cam > 0) & (parallax_deg >= min_parallax_deg) & (z_ref_m > 0)
        good &= np.isfinite(X).all(axis=1)
    if np.count_nonzero(good) < min_points:
        return None
    return float(np.median(z_ref_m[good] / X[good, 2]))


def depth_window_on_image(window_model_px: int, image_width: int, model_width: int) -> int:
    """The corner-depth window on the image for a window given in the depth model's input pixels.

    A network blurs depth edges over a few of *its* pixels; when it runs on a smaller input than the image,
    the adapter upsamples that blur with its output, so the window grows by ``image_width / model_width``
    (rounded to an odd size; never below the given window). Demo models (320 wide) at 640x192: 5 -> 9 px;
    rendered car drives of the demo world, ground-scaled depth: path length 0.967-0.969 -> 0.993-1.001
    of the truth, SE(3)-aligned ATE 3.0-3.4 -> 1.1-1.4 m.

    Args:
        window_model_px: window in model-input pixels (``odometry.visual_depth_window_px``).
        image_width: width of the images the odometry tracks, pixels.
        model_width: width of the depth model's input for those images, pixels.
    """
    if model_width <= 0 or image_width <= model_width or window_model_px <= 1:
        return int(window_model_px)
    scaled = window_model_px * image_width / model_width
    return max(int(window_model_px), 2 * round((scaled - 1) / 2) + 1)


def half_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation about the same axis as (3, 3) ``R`` by half its angle."""
    rvec = cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0]
    return cv2.Rodrigues(0.5 * rvec)[0]


def _pose_from_rt(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.ravel(tvec)
    return T


class DepthVisualOdometry:
    """Frame-to-reference PnP visual odometry on a monocular image and its (predicted) metric depth.

    Args:
        max_features: corners detected per reference frame (Shi-Tomasi).
        min_feature_distance_px: minimum distance between corners, pixels.
        min_depth_m, max_depth_m: corners are taken only where the depth is inside this range;
            far depth from a monocular network is the least accurate.
        min_track_fraction: a new reference is taken when fewer than this fraction of the
            reference's corners are still tracked ...
        min_tracks: ... or fewer than this many. Low on purpose (about twice ``min_inliers``): at
            320x96 a reference holds 150-300 corners, and a floor of 100 renewed it on 83-99 % of the
            frames, so each frame's scale came from one frame of baseline and one frame's depth (25:
            18-57 %; odometry ATE lower on 13 of 13 rendered tuning drives together with the ground scale).
        reprojection_px: RANSAC inlier threshold, pixels.
        forward_backward_px: tracks that do not return within this distance are dropped, pixels.
        min_inliers: fewer PnP inliers count as a failure.
        max_step_m: a frame-to-frame translation change beyond this (vs constant velocity) is
            rejected as implausible, metres.
        exclude_labels: Cityscapes train ids whose pixels never give corners (sky, people).
        triangulated_scale: take the translation length from ``triangulated_scale`` (median depth
            ratio) instead of PnP's least squares, which network depth noise shrinks.
        depth_window_px: a corner's depth is the largest in this window (1: its own pixel). Depth
            networks blur depth edges toward the foreground and corners sit on edges; without the
            window the demo model's path comes out 5-7 % short (3: 2-5 %, 5: 1-3 %; with true
            depth 5 overshoots by 2 %, so sensor depth wants 1).
        planar_motion: take each frame's turn from corners tracked since the previous image under planar
            circular motion (a ground vehicle), where at least ``MIN_PLANAR_SUPPORT`` of them agree with it or
            at least as many as agree with PnP's motion (``_planar_fits``; module docstring).
        road_steps: take each frame's step from the road where a level road plane is in view and the road's
            image motion gives a distinct answer (module docstring, step 4; needs ``label_ids``).
        road_height_m: the camera's height above the road, metres, that road steps take their length in;
            None: the road plane's height measured in each frame's depth.
        ground_attitude: hold each new reference's roll and pitch to the ground plane in view (module
            docstring, step 5; needs ``label_ids``; assumes level ground).
    """

    def __init__(
        self,
        *,
        max_features: int = 1000,
        min_feature_distance_px: float = 7.0,
        min_depth_m: float = 0.5,
        max_depth_m: float = 40.0,
        min_track_fraction: float = 0.5,
        min_tracks: int = 25,
        reprojection_px: float = 2.0,
        forward_backward_px: float = 1.0,
        min_inliers: int = 12,
        max_step_m: float = 5.0,
        exclude_labels: tuple[int, ...] = (10, 11, 12),
        lk_window_px: int = 21,
        lk_levels: int = 3,
        triangulated_scale: bool = True,
        depth_window_px: int = 5,
        planar_motion: bool = False,
        road_steps: bool = False,
        road_height_m: float | None = None,
        ground_attitude: bool = False,
    ) -> None:
        if not 0.0 <= min_depth_m < max_depth_m:
            raise ConfigError(f"visual odometry needs 0 <= min_depth_m < max_depth_m, got {min_depth_m}, {max_depth_m}")
        if depth_window_px < 1:
            raise ConfigError(f"visual odometry needs depth_window_px >= 1, got {depth_window_px}")
        if max_features < 8 or not 0.0 < min_track_fraction <= 1.0 or min_inliers < 6:
            raise ConfigError(
                "visual odometry needs max_features >= 8, 0 < min_track_fraction <= 1 and min_inliers >= 6"
            )
        if reprojection_px <= 0 or forward_backward_px <= 0 or max_step_m <= 0:
            raise ConfigError("visual odometry thresholds (reprojection, forward-backward, max step) must be > 0")
        self.max_features = max_features
        self.min_feature_distance_px = min_feature_distance_px
        self.min_depth_m, self.max_depth_m = min_depth_m, max_depth_m
        self.min_track_fraction = min_track_fraction
        self.min_tracks = min_tracks
        self.reprojection_px = reprojection_px
        self.forward_backward_px = forward_backward_px
        self.min_inliers = min_inliers
        self.max_step_m = max_step_m
        self.exclude_labels = tuple(exclude_labels)
        self.triangulated_scale = triangulated_scale
        self.depth_window_px = depth_window_px
        self.planar_motion = planar_motion
        self.road_steps = road_steps
        self.road_height_m = road_height_m
        self.ground_attitude = ground_attitude
        self._ups: list[np.ndarray] = []  # the first references' measured up, odometry frame (ground_attitude)
        self._level_up: np.ndarray | None = None  # level: where up points in the odometry frame
        self._last_up: np.ndarray | None = None  # the last plane used: its up, odometry frame, as corrected
        self.num_levelled = 0  # references turned towards level
        self._road: tuple[np.ndarray, np.ndarray, RoadPlane] | None = None  # previous image, its road pixels, plane
        self._road_sign: float | None = None  # the last road step's sign along the chord (backward camera: -1)
        self.num_road_steps = 0
        self._turn: PlanarTurn | None = None  # this frame's planar turn (``_track``; used where ``_planar_fits``)
        self._turn_tracks = (np.zeros((0, 2)), np.zeros((0, 2)))  # the corners it came from: previous, this image
        self._turn_used = False  # this frame's pose took it
        self._lk = {
            "winSize": (lk_window_px, lk_window_px),
            "maxLevel": lk_levels,
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        }
        self.T_odom_cam = np.eye(4)  # the output chain (road steps composed on the tracking chain's turns)
        self._track_T = np.eye(4)  # the tracking chain: PnP against the reference
        self._T_prev_cam = np.eye(4)  # last frame-to-frame motion of the tracking chain (constant velocity)
        self._prev_gray: np.ndarray | None = None
        self._prev_labels: np.ndarray | None = None  # (H, W) the previous image's labels (its fresh corners' mask)
        self._ref_T_odom_cam = np.eye(4)
        self._ref_points = np.zeros((0, 3))  # (M, 3) reference corners in the reference camera frame
        self._tracks_uv = np.zeros((0, 1, 2), np.float32)  # (M, 1, 2) their pixels in the previous image
        self._ref_uv = np.zeros((0, 2))  # (M, 2) their pixels in the reference image
        self._ref_count = 0
        self.num_frames = 0
        self.num_references = 0

    @property
    def predicted_delta(self) -> np.ndarray:
        """(4, 4) the constant-velocity model's next frame-to-frame motion (the last measured step), a copy."""
        return self._T_prev_cam.copy()

    def seed_motion(self, motion: np.ndarray) -> None:
        """Predict the next step with ``motion`` instead of at rest (before the second frame: a re-initialised
        odometry continues the vehicle's last trusted velocity; PnP's initial guess, and the step kept where PnP
        fails, as with any constant-velocity prediction).

        Args:
            motion: (4, 4) frame-to-frame motion, a frame's camera in the previous frame's camera, metres.
        """
        self._T_prev_cam = np.asarray(motion, dtype=np.float64).copy()

    def register(
        self,
        image_gray: np.ndarray,
        depth_m: np.ndarray,
        intrinsics: Intrinsics,
        label_ids: np.ndarray | None = None,
        motion_prior: np.ndarray | None = None,
    ) -> VisualRegistration:
        """Estimate the pose of the next frame.

        Args:
            image_gray: (H, W) uint8 grayscale image.
            depth_m: (H, W) metric depth of the same frame, metres; 0 or non-finite = unknown.
            intrinsics: pinhole intrinsics of the image.
            label_ids: optional (H, W) Cityscapes train ids; ``exclude_labels`` pixels give no corners.
            motion_prior: optional (4, 4) frame-to-frame motion (this camera in the previous one) to predict
                with instead of the constant-velocity model's: PnP's initial guess, and the pose kept when PnP
                fails (e.g. the step with its yaw measured from image motion, which a sharp turn needs).

        Returns:
            ``VisualRegistration`` with the new ``T_odom_cam`` (4, 4).

        Raises:
            DataError: image, depth or labels have the wrong shape or type, or the image size changed.
        """
        gray, depth = self._check_inputs(image_gray, depth_m, label_ids)
        self.num_frames += 1
        levelled_before = self.num_levelled
        if self._prev_gray is None:
            self._new_reference(gray, depth, intrinsics, label_ids)
            self._prev_gray, self._prev_labels = gray, label_ids
            if self.road_steps:
                self._road = self._road_view(gray, depth, intrinsics, label_ids)
            return VisualRegistration(self.T_odom_cam.copy(), VisualStatus.FIRST_FRAME, 0, 0, True)
        if gray.shape != self._prev_gray.shape:
            raise DataError(
                f"image size changed from {self._prev_gray.shape[::-1]} to {gray.shape[::-1]} inside one sequence"
            )

        motion = self._T_prev_cam if motion_prior is None else motion_prior
        T_pred = self._track_T @ motion
        self._turn_used = False
        num_tracks = self._track(gray, intrinsics)
        status, num_inliers, T_new = VisualStatus.FEW_TRACKS, 0, T_pred
        if num_tracks >= self.min_inliers:
            T_new, num_inliers = self._solve_pnp(T_pred, intrinsics)
            status = VisualStatus.OK if T_new is not None else VisualStatus.PNP_FAILED
            if T_new is None:
                T_new = T_pred
        if status is VisualStatus.OK:  # coasting keeps the last motion as it is
            self._T_prev_cam = inverse(self._track_T) @ T_new
        T_new[:3, :3] = project_to_so3(T_new[:3, :3])  # products of many poses drift off SO(3)
        step = inverse(T_new) @ self._track_T  # X_cur = step X_prev
        self._track_T = T_new
        road = None
        if self.road_steps:
            road = self._road_step(step, gray, intrinsics, float(np.linalg.norm(motion[:3, 3])) + self.max_step_m)
            self.T_odom_cam = self.T_odom_cam @ inverse(step if road is None else road)
            self.T_odom_cam[:3, :3] = project_to_so3(self.T_odom_cam[:3, :3])
            self._road = self._road_view(gray, depth, intrinsics, label_ids)
        else:
            self.T_odom_cam = T_new.copy()
        self._prev_gray, self._prev_labels = gray, label_ids
        renew = len(self._ref_points) < max(self.min_tracks, self.min_track_fraction * self._ref_count)
        if renew:
            self._new_reference(gray, depth, intrinsics, label_ids)
        planar = self._turn_used and status is VisualStatus.OK
        return VisualRegistration(
            self.T_odom_cam.copy(), status, num_tracks, num_inliers, renew, planar, road is not None,
            self.num_levelled > levelled_before,
        )

    # ----------------------------------------------------------------------------------------------

    def _road_view(
        self, gray: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, label_ids: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, RoadPlane] | None:
        """This frame's image, textured road pixels and level road plane (at ``road_height_m`` where set), for
        the next frame's road step (None without labels or a level road plane: a UAV's oblique view, a road out
        of sight)."""
        if label_ids is None:
            return None
        plane = road_plane(depth, label_ids, intrinsics)
        if plane is None:
            return None
        if self.road_height_m is not None:  # the road's direction from the depth, its distance known
            plane = replace(plane, height=self.road_height_m)
        pixels = textured_road_pixels(gray, depth, np.asarray(label_ids) == Label.ROAD, MIN_ROAD_GRADIENT)
        return gray, pixels, plane

    def _road_step(
        self, step: np.ndarray, gray: np.ndarray, intrinsics: Intrinsics, max_length_m: float
    ) -> np.ndarray | None:
        """(4, 4) this frame's step (``X_cur = step X_prev``) with the tracking chain's turn and the road's
        translation, or None where the road gives no distinct answer.

        The car moves along the chord of its turn in the road plane: the previous camera's forward axis laid
        into the plane and turned by half the step's rotation (planar circular motion, with the camera's own
        pitch and roll to the road taken out); forward or backward as the tracking chain's step says (a camera
        looking backwards). Where the chain's step points against the last road step's, the road is searched
        both ways and the way whose best length moves the road better (lower photometric cost: the same pixels
        of the same images) is taken. A car does not reverse from one frame to the next, while a chain whose
        tracks slide along the street reads a step of a few centimetres, either way, where the car drove a metre
        (synthia-like, 10 m/s), and PnP on a dozen inliers can read a whole step backwards (synthia-like 584:
        1 m back and 0.8 m sideways at 10 m/s). Searched one way only, stripes across the road (a zebra
        crossing, lane dashes) line up again a stripe period the wrong way: a distinct best length too (584:
        0.54 m back, contrast 0.61, where the car drove 1.07 m on; the true way 0.39)."""
        if self._road is None:
            return None
        prev_gray, pixels, plane = self._road
        R_cam_prev = step[:3, :3]
        n = plane.normal_cam
        forward = np.array([0.0, 0.0, 1.0]) - n[2] * n
        forward /= np.linalg.norm(forward)
        chord_prev = half_rotation(R_cam_prev.T) @ forward  # the step's direction in the previous frame
        along = float(-(R_cam_prev.T @ step[:3, 3]) @ chord_prev)  # the tracking chain's step along it
        chain_sign = (1.0 if along > 0 else -1.0) if abs(along) > 1e-6 else (self._road_sign or 1.0)
        signs = [chain_sign] if self._road_sign in (None, chain_sign) else [chain_sign, self._road_sign]
        best = None
        for sign in signs:
            direction_cam = -R_cam_prev @ (sign * chord_prev)
            found = ground_step(prev_gray, gray, pixels, intrinsics.K, R_cam_prev, direction_cam, plane, max_length_m)
            distinct = found is not None and found.contrast <= MAX_ROAD_CONTRAST
            if distinct and (best is None or found.cost < best[1].cost):
                best = (sign, found, direction_cam)
        if best is None:
            return None
        sign, found, direction_cam = best
        self._road_sign = sign
        out = np.eye(4)
        out[:3, :3] = R_cam_prev
        out[:3, 3] = found.length_m * direction_cam
        self.num_road_steps += 1
        return out

    def _check_inputs(
        self, image_gray: np.ndarray, depth_m: np.ndarray, label_ids: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        gray = np.asarray(image_gray)
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise DataError(f"visual odometry needs an (H, W) uint8 grayscale image, got {gray.dtype} {gray.shape}")
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != gray.shape:
            raise DataError(f"depth {depth.shape} and image {gray.shape} differ in size")
        if label_ids is not None and np.shape(label_ids) != gray.shape:
            raise DataError(f"labels {np.shape(label_ids)} and image {gray.shape} differ in size")
        return gray, np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)

    def _corner_mask(self, label_ids: np.ndarray | None) -> np.ndarray | None:
        """(H, W) uint8 mask (255: may give corners) of the pixels not labelled ``exclude_labels``; None without
        labels or exclusions (every pixel may)."""
        if label_ids is None or not self.exclude_labels:
            return None
        return (~np.isin(label_ids, self.exclude_labels)).astype(np.uint8) * 255

    def _new_reference(
        self, gray: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, label_ids: np.ndarray | None
    ) -> None:
        if self.ground_attitude and label_ids is not None:
            self._level(depth, intrinsics, label_ids)
        usable = (depth > self.min_depth_m) & (depth < self.max_depth_m)
        mask = self._corner_mask(label_ids)
        if mask is not None:
            usable &= mask > 0
        corners = None
        if usable.any():
            corners = cv2.goodFeaturesToTrack(
                gray, self.max_features, 0.01, self.min_feature_distance_px, mask=usable.astype(np.uint8) * 255,
                blockSize=5,
            )  # fmt: skip
        if corners is None:
            corners = np.zeros((0, 1, 2), np.float32)
        self._tracks_uv = corners.astype(np.float32)
        self._ref_uv = corners.reshape(-1, 2).astype(np.float64)
        if self.depth_window_px > 1:
            # the farthest depth around a corner: networks blur depth edges toward the foreground, and
            # corners sit on edges; a background corner given foreground depth shortens the motion
            depth = cv2.dilate(depth, np.ones((self.depth_window_px, self.depth_window_px), np.uint8))
        self._ref_points = backproject_pixels(self._ref_uv, depth, intrinsics)
        self._ref_T_odom_cam = self._track_T.copy()
        self._ref_count = len(corners)
        self.num_references += 1

    def _level(self, depth: np.ndarray, intrinsics: Intrinsics, label_ids: np.ndarray) -> None:
        """Turn this frame's pose (tracking and output chain, about the camera centre) towards level by at most
        ``GROUND_ATTITUDE_STEP_DEG`` (module docstring, step 5); nothing without a ground plane in view."""
        points_cam, index = backproject(depth, intrinsics, stride=GROUND_STRIDE, min_depth_m=self.min_depth_m)
        normal = ground_normal(points_cam, np.asarray(label_ids).reshape(-1)[index])
        if normal is None:
            return
        up = self._track_T[:3, :3] @ normal  # where this frame says up is, in the odometry frame
        level = self._level_up
        if level is None:
            self._level_up = self._agreed_level(up)
            self._last_up = up if self._level_up is not None else None
            return
        if self._last_up is not None and up @ self._last_up < np.cos(np.radians(GROUND_ATTITUDE_MAX_TILT_DEG)):
            return  # a bad plane
        axis = np.cross(up, level)
        tilt = float(np.arctan2(np.linalg.norm(axis), up @ level))
        turn = so3_exp(axis / max(np.linalg.norm(axis), 1e-12) * min(tilt, np.radians(GROUND_ATTITUDE_STEP_DEG)))
        self._last_up = turn @ up
        self._track_T[:3, :3] = turn @ self._track_T[:3, :3]
        self.T_odom_cam[:3, :3] = turn @ self.T_odom_cam[:3, :3]
        self.num_levelled += 1

    def _agreed_level(self, up: np.ndarray) -> np.ndarray | None:
        """Level from the first references' measured up (``GROUND_ATTITUDE_FIRST``), or None while too few
        agree; ``up`` is the newest, (3,) unit, odometry frame."""
        self._ups.append(up)
        if len(self._ups) < GROUND_ATTITUDE_FIRST:
            return None
        ups = np.array(self._ups)
        agree = ups @ ups.T >= np.cos(np.radians(GROUND_ATTITUDE_MAX_TILT_DEG))
        best = int(np.argmax(agree.sum(axis=1)))
        if 2 * int(agree[best].sum()) <= len(ups):
            self._ups.pop(0)
            return None
        mean = ups[np.flatnonzero(agree[best])[:GROUND_ATTITUDE_EARLIEST]].mean(axis=0)
        return mean / np.linalg.norm(mean)

    def _track(self, gray: np.ndarray, intrinsics: Intrinsics) -> int:
        """KLT-track the reference corners from the previous image into ``gray``; drop lost tracks; with
        ``planar_motion`` measure the turn since the previous image (``self._turn``; ``_planar_fits`` decides
        whether it is used) from corners found afresh there (``_fresh_corners``), tracked in the same calls."""
        fresh = self._fresh_corners() if self.planar_motion else np.zeros((0, 1, 2), np.float32)
        n = len(self._tracks_uv)
        if n + len(fresh) == 0:
            self._turn = None
            return 0
        fwd, keep = self._lk_track(np.concatenate([self._tracks_uv, fresh]), gray)
        self._turn_tracks = (fresh[keep[n:], 0].astype(np.float64), fwd[n:][keep[n:], 0].astype(np.float64))
        self._turn = planar_turn(*self._turn_tracks, intrinsics) if len(fresh) else None
        self._keep_tracks(keep[:n], fwd[:n])
        return int(keep[:n].sum())

    def _lk_track(self, uv_prev: np.ndarray, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M, 1, 2) float32 pixels ``uv_prev`` of the previous image tracked into ``gray``: their (M, 1, 2)
        positions there and an (M,) mask of the tracks that return home (forward-backward check) and stay in
        the image."""
        fwd, st_f, _ = cv2.calcOpticalFlowPyrLK(self._prev_gray, gray, uv_prev, None, **self._lk)
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray, self._prev_gray, fwd, None, **self._lk)
        h, w = gray.shape
        keep = (st_f[:, 0] == 1) & (st_b[:, 0] == 1)
        keep &= np.linalg.norm((back - uv_prev)[:, 0], axis=1) < self.forward_backward_px
        uv = fwd[:, 0]
        keep &= (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        return fwd, keep

    def _fresh_corners(self) -> np.ndarray:
        """(F, 1, 2) float32 corners found afresh in the previous image (``_corner_mask``), for the turn."""
        corners = cv2.goodFeaturesToTrack(
            self._prev_gray, self.max_features, 0.01, self.min_feature_distance_px,
            mask=self._corner_mask(self._prev_labels), blockSize=5,
        )  # fmt: skip
        return np.zeros((0, 1, 2), np.float32) if corners is None else corners.astype(np.float32)

    def _planar_fits(self, T_cam_ref: np.ndarray, intrinsics: Intrinsics) -> bool:
        """Whether this frame's planar turn replaces PnP's (``T_cam_ref``, this camera in the reference's): where at
        least ``MIN_PLANAR_SUPPORT`` of its corners agree with it, or at least as many as agree with PnP's own motion
        since the previous image (``planar_motion.epipolar_support``, the same corners and truncation).

        The turn comes from corners found afresh in the previous image (``_fresh_corners``), not from the
        reference's tracks: those, carried from image to image, slide off the corners they started on and thin
        out (PnP drops its outliers for good), and their frame-to-frame motion is the noisier for it. On the 16
        tuning drives of the RGB benchmark (airsim-like and synthia-like cars, demo models' images, 320x96) the
        fresh corners' turn erred 0.032-0.047 deg RMS per frame against 0.052-0.095 deg from the tracks (worst
        frame 0.10-0.30 deg against 0.19-0.86), on 125 corners per frame against 72 (medians). In a sharp turn
        (9 deg per frame) fewer corners agree with any motion: the planar turn was right within 0.14 deg on 59-82 %
        of them while PnP's turn, 2.5-3.1 deg off, was taken; compared with what PnP's motion explains, it is not.
        """
        turn = self._turn
        if turn is None:
            return False
        if turn.support >= MIN_PLANAR_SUPPORT:
            return True
        T_prev_cur = inverse(self._track_T) @ self._ref_T_odom_cam @ inverse(T_cam_ref)
        pnp = epipolar_support(T_prev_cur, *self._turn_tracks, intrinsics)
        return pnp is not None and turn.support >= pnp

    def _keep_tracks(self, keep: np.ndarray, tracks_uv: np.ndarray | None = None) -> None:
        tracks_uv = self._tracks_uv if tracks_uv is None else tracks_uv
        self._tracks_uv, self._ref_points = tracks_uv[keep], self._ref_points[keep]
        self._ref_uv = self._ref_uv[keep]

    def _solve_pnp(self, T_pred: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray | None, int]:
        """Pose of the current frame from reference 3-D points and tracked pixels, or (None, inliers)."""
        K = intrinsics.K
        uv = self._tracks_uv[:, 0].astype(np.float64)
        T_cam_ref = inverse(T_pred) @ self._ref_T_odom_cam
        rvec = cv2.Rodrigues(T_cam_ref[:3, :3])[0]
        tvec = T_cam_ref[:3, 3].reshape(3, 1).copy()
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            self._ref_points, uv, K, None, rvec=rvec, tvec=tvec, useExtrinsicGuess=True, iterationsCount=200,
            reprojectionError=self.reprojection_px, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE,
        )  # fmt: skip
        if not ok or inliers is None or len(inliers) < self.min_inliers:
            return None, 0 if inliers is None else len(inliers)
        idx = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(self._ref_points[idx], uv[idx], K, None, rvec, tvec)
        if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
            return None, len(idx)
        T_cam_ref = _pose_from_rt(rvec, tvec)
        if self._planar_fits(T_cam_ref, intrinsics):
            T_cam_ref = self._with_planar_turn(T_cam_ref, self._turn, idx, intrinsics)
        if self.triangulated_scale:
            scale = triangulated_scale(T_cam_ref, self._ref_uv[idx], uv[idx], self._ref_points[idx, 2], K)
            t_norm = np.linalg.norm(T_cam_ref[:3, 3])
            if scale is not None and 0.5 * t_norm < scale < 2.0 * t_norm:
                T_cam_ref[:3, 3] *= scale / t_norm
        T_new = self._ref_T_odom_cam @ inverse(T_cam_ref)
        if np.linalg.norm(T_new[:3, 3] - T_pred[:3, 3]) > self.max_step_m:
            return None, len(idx)
        # outliers are dropped for good: they are on moving objects or carry bad depth
        self._keep_tracks(idx)
        return T_new, len(idx)

    def _with_planar_turn(
        self, T_cam_ref: np.ndarray, turn: PlanarTurn, inliers: np.ndarray, intrinsics: Intrinsics
    ) -> np.ndarray:
        """``T_cam_ref`` with its rotation set to the previous frame's turned by the planar ``turn`` (no pitch
        or roll of its own: planar motion) and its translation solved again on the PnP ``inliers`` with that
        rotation held."""
        R_ref_prev = (inverse(self._ref_T_odom_cam) @ self._track_T)[:3, :3]
        R_ref_cam = R_ref_prev @ rot_y(turn.yaw_rad)
        out = np.eye(4)
        out[:3, :3] = R_ref_cam.T
        t = translation_given_rotation(
            out[:3, :3], self._ref_points[inliers], self._tracks_uv[inliers, 0].astype(np.float64), intrinsics
        )
        out[:3, 3] = T_cam_ref[:3, 3] if t is None else t
        self._turn_used = True
        return out


def translation_given_rotation(
    R_cam_ref: np.ndarray, points_ref: np.ndarray, pixels_uv: np.ndarray, intrinsics: Intrinsics
) -> np.ndarray | None:
    """(3,) translation ``t`` of ``T_cam_ref`` that best reprojects reference points with the rotation held.

    Each point gives two linear equations ``m x (R X + t) = 0`` (``m`` its pixel's normalized ray), each
    divided by the point's depth so that the residual is close to the image-plane error.

    Args:
        R_cam_ref: (3, 3) rotation of the reference frame in the current camera frame.
        points_ref: (N, 3) points in the reference camera frame, metres.
        pixels_uv: (N, 2) their pixels in the current image.
        intrinsics: pinhole intrinsics of the current image.

    Returns:
        (3,) metres, or None with fewer than 3 points in front of the camera.
    """
    rotated = points_ref @ R_cam_ref.T  # (N, 3) R X
    front = rotated[:, 2] > 1e-6
    if np.count_nonzero(front) < 3:
        return None
    rotated, uv = rotated[front], pixels_uv[front]
    mx = (uv[:, 0] - intrinsics.cx) / intrinsics.fx
    my = (uv[:, 1] - intrinsics.cy) / intrinsics.fy
    w = 1.0 / rotated[:, 2]
    # x - mx z = 0 and y - my z = 0 for the point R X + t
    one, zero = np.ones_like(mx), np.zeros_like(mx)
    w2 = np.tile(w, 2)
    A = np.concatenate([np.stack([one, zero, -mx], axis=1), np.stack([zero, one, -my], axis=1)]) * w2[:, None]
    b = -np.concatenate([rotated[:, 0] - mx * rotated[:, 2], rotated[:, 1] - my * rotated[:, 2]]) * w2
    t, *_ = np.linalg.lstsq(A, b, rcond=None)
    return t if np.all(np.isfinite(t)) else None
