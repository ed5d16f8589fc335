"""A camera that sees only the ground holds its roll and pitch to it (``DepthVisualOdometry(ground_attitude=True)``),
on the exactly rendered corridor seen from a camera pitched down (a UAV's view, scaled to the corridor)."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import inverse, rot_x
from shgm_slam.labels import Label
from shgm_slam.odometry.visual import GROUND_ATTITUDE_FIRST, DepthVisualOdometry
from tests.odometry.corridor import INTRINSICS, render

FLOOR_Y_M = 1.6  # the corridor's floor (world y down)
PITCH_RAD = np.radians(-35.0)  # the camera looks 35 deg down
DRIFT_DEG = 0.5  # injected tilt error per new reference (half the most a reference is turned back)


def path(num_frames: int, step_m: float = 0.4) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam``: straight down the corridor, level, the camera pitched down."""
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    poses[:, :3, :3] = rot_x(PITCH_RAD)
    poses[:, 2, 3] = step_m * np.arange(num_frames)
    return poses


def floor_labels(T_world_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W) train ids: road where the pixel's point lies on the floor, building elsewhere."""
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]].astype(np.float64)
    rays = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx, (v - INTRINSICS.cy) / INTRINSICS.fy, np.ones_like(u)], -1)
    y_world = (rays * depth[..., None]) @ T_world_cam[1, :3] + T_world_cam[1, 3]
    return np.where((depth > 0) & (np.abs(y_world - FLOOR_Y_M) < 0.05), Label.ROAD, Label.BUILDING).astype(np.uint8)


def tilt_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle between the world's down axis as seen by two camera poses (their tilt difference), degrees."""
    down_a, down_b = T_a[:3, :3].T @ [0.0, 1.0, 0.0], T_b[:3, :3].T @ [0.0, 1.0, 0.0]
    return float(np.degrees(np.arccos(np.clip(down_a @ down_b, -1.0, 1.0))))


def drive(ground_attitude: bool, poses: np.ndarray) -> tuple[np.ndarray, DepthVisualOdometry, list]:
    """The odometry's poses (first frame = identity) with the chain tilted by ``DRIFT_DEG`` at every new reference
    (how PnP's rotation error compounds), the odometry, and its registrations."""
    vo = DepthVisualOdometry(depth_window_px=1, ground_attitude=ground_attitude)
    new_reference = vo._new_reference

    def drifting(gray, depth, intrinsics, label_ids):
        if vo.num_frames > 1:
            tilt = rot_x(np.radians(DRIFT_DEG))
            vo._track_T[:3, :3] = vo._track_T[:3, :3] @ tilt
            vo.T_odom_cam[:3, :3] = vo.T_odom_cam[:3, :3] @ tilt
        new_reference(gray, depth, intrinsics, label_ids)

    vo._new_reference = drifting
    regs = []
    for T in poses:
        gray, depth = render(T)
        regs.append(vo.register(gray, depth, INTRINSICS, floor_labels(T, depth)))
    return np.stack([r.T_odom_cam for r in regs]), vo, regs


@pytest.fixture(scope="module")
def poses() -> np.ndarray:
    return path(60)


def test_the_tilt_drifts_without_the_ground(poses):
    est, vo, regs = drive(False, poses)
    gt = inverse(poses[0]) @ poses
    assert vo.num_references > GROUND_ATTITUDE_FIRST + 5 and not any(r.levelled for r in regs)
    assert tilt_deg(est[-1], gt[-1]) > 0.8 * DRIFT_DEG * (vo.num_references - 1)


def test_the_ground_holds_the_tilt(poses):
    est, vo, regs = drive(True, poses)
    gt = inverse(poses[0]) @ poses
    assert vo.num_levelled >= vo.num_references - GROUND_ATTITUDE_FIRST - 2
    # each registration says whether it was a reference turned towards level (what the run's summary counts)
    assert sum(r.levelled for r in regs) == vo.num_levelled and all(r.new_reference for r in regs if r.levelled)
    # level is agreed on over the first references, whose drift (0 to FIRST - 1 steps) it averages; from then on
    # each reference is turned back by its drift and more, so the chain settles at level: about half the first
    # references' drift off the truth (without the ground: 23 deg by the end)
    bias = DRIFT_DEG * (GROUND_ATTITUDE_FIRST - 1) / 2
    assert tilt_deg(est[-1], gt[-1]) < bias + DRIFT_DEG
    worst_late = max(tilt_deg(e, g) for e, g in zip(est[len(est) // 2 :], gt[len(gt) // 2 :], strict=True))
    assert worst_late < bias + DRIFT_DEG


def test_a_car_camera_is_not_levelled_by_default():
    assert not DepthVisualOdometry().ground_attitude
