"""A car's step from the road's image motion, on the exactly rendered corridor (its floor is the road)."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import inverse
from shgm_slam.labels import Label
from shgm_slam.metrics import ate, trajectory_length
from shgm_slam.odometry.ground_speed import MIN_ROAD_GRADIENT, ground_step, textured_road_pixels
from shgm_slam.odometry.image_rotation import rot_y
from shgm_slam.odometry.visual import DepthVisualOdometry, half_rotation
from shgm_slam.perception.ground_scale import road_plane
from tests.odometry.corridor import INTRINSICS, render

FLOOR_Y_M = 1.6  # the corridor's floor, below the camera (y down)


def road_labels(depth: np.ndarray) -> np.ndarray:
    """(H, W) train ids: road where the pixel's point lies on the floor (a level camera), building elsewhere."""
    v = np.arange(depth.shape[0], dtype=np.float64)[:, None]
    y = (v - INTRINSICS.cy) / INTRINSICS.fy * depth
    return np.where((depth > 0) & (np.abs(y - FLOOR_Y_M) < 0.05), Label.ROAD, Label.BUILDING).astype(np.uint8)


def car_path(num_frames: int, step_m: float = 1.0, turn_rad: float = 0.01) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam`` of a car on the corridor floor: a gentle arc, driving where it points."""
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(1, num_frames):
        R_prev = poses[i - 1, :3, :3]
        chord = R_prev @ rot_y(turn_rad / 2) @ np.array([0.0, 0.0, 1.0])
        poses[i, :3, :3] = R_prev @ rot_y(turn_rad)
        poses[i, :3, 3] = poses[i - 1, :3, 3] + step_m * chord
    return poses


def test_half_rotation_composes_to_the_rotation():
    R = rot_y(0.3) @ np.array([[1.0, 0, 0], [0, np.cos(0.1), -np.sin(0.1)], [0, np.sin(0.1), np.cos(0.1)]])
    H = half_rotation(R)
    assert np.allclose(H @ H, R, atol=1e-9)


@pytest.mark.parametrize("length_m", [0.0, 0.4, 0.93, 2.5])
def test_the_road_gives_the_step_length(length_m):
    poses = car_path(2, step_m=length_m, turn_rad=0.02)
    prev, cur = render(poses[0]), render(poses[1])
    step = inverse(poses[1]) @ poses[0]  # X_cur = step X_prev
    plane = road_plane(prev[1], road_labels(prev[1]), INTRINSICS)
    assert plane is not None and plane.height == pytest.approx(FLOOR_Y_M, rel=0.01)
    pixels = textured_road_pixels(prev[0], prev[1], road_labels(prev[1]) == Label.ROAD, MIN_ROAD_GRADIENT)
    t = step[:3, 3]
    direction = t / np.linalg.norm(t) if length_m > 0 else np.array([0.0, 0.0, -1.0])
    found = ground_step(prev[0], cur[0], pixels, INTRINSICS.K, step[:3, :3], direction, plane, 5.0)
    assert found is not None
    assert found.length_m == pytest.approx(length_m, abs=0.03 + 0.02 * length_m)
    assert found.contrast < 0.7 or length_m == 0.0


def test_no_texture_or_no_room_gives_no_length():
    prev = render(np.eye(4))
    plane = road_plane(prev[1], road_labels(prev[1]), INTRINSICS)
    assert ground_step(prev[0], prev[0], np.zeros((0, 2)), INTRINSICS.K, np.eye(3), np.array([0, 0, -1.0]), plane,
                       5.0) is None  # fmt: skip
    flat = np.full_like(prev[0], 128)
    assert len(textured_road_pixels(flat, prev[1], road_labels(prev[1]) == Label.ROAD, MIN_ROAD_GRADIENT)) == 0


def run(poses, road_steps, depth_fn=lambda d, labels: d, labels=True, road_height_m=None):
    vo = DepthVisualOdometry(depth_window_px=1, planar_motion=True, road_steps=road_steps, road_height_m=road_height_m)
    est, regs = [], []
    for T in poses:
        gray, depth = render(T)
        lab = road_labels(depth)
        reg = vo.register(gray, depth_fn(depth, lab), INTRINSICS, lab if labels else None)
        est.append(reg.T_odom_cam)
        regs.append(reg)
    return np.stack(est), regs, vo


@pytest.fixture(scope="module")
def drive() -> np.ndarray:
    return car_path(25, step_m=0.9, turn_rad=0.015)


def test_road_steps_follow_a_car_on_true_depth(drive):
    gt = inverse(drive[0]) @ drive
    est, regs, vo = run(drive, True)
    assert vo.num_road_steps >= 20 and sum(r.road_step for r in regs) == vo.num_road_steps
    assert trajectory_length(est) == pytest.approx(trajectory_length(gt), rel=0.02)
    assert ate(gt, est, align="none").rmse < 0.2


def test_road_steps_hold_where_the_tracks_mislead(drive):
    """Everything but the floor 2.5x too far (a network that misjudges the walls): PnP's steps are off by
    far, the road's steps (the floor's own plane) are not."""
    def walls_far(depth, labels):
        return np.where(labels == Label.ROAD, depth, depth * np.float32(2.5)).astype(np.float32)

    gt = inverse(drive[0]) @ drive
    tracks, _, _ = run(drive, False, walls_far)
    road, _, _ = run(drive, True, walls_far)
    true_len = trajectory_length(gt)
    assert abs(trajectory_length(tracks) / true_len - 1.0) > 0.15
    assert trajectory_length(road) == pytest.approx(true_len, rel=0.03)
    assert ate(gt, road, align="none").rmse < 0.5 * ate(gt, tracks, align="none").rmse


def test_road_steps_at_the_known_camera_height_hold_where_the_depth_scale_swings(drive):
    """Each frame's whole depth off by its own factor (0.6-1.6: a network on images unlike its training set):
    measured in that depth, the road's height and with it each road step swing too; at the camera's known
    height (``road_height_m``) the steps keep their length."""
    rng = np.random.default_rng(7)
    factors = rng.uniform(0.6, 1.6, size=len(drive))
    calls = iter(range(len(drive)))

    def swinging(depth, labels):
        return (depth * np.float32(factors[next(calls)])).astype(np.float32)

    gt = inverse(drive[0]) @ drive
    measured, _, _ = run(drive, True, swinging)
    calls = iter(range(len(drive)))
    known, _, vo = run(drive, True, swinging, road_height_m=FLOOR_Y_M)
    assert vo.num_road_steps >= 20
    true_len = trajectory_length(gt)
    assert trajectory_length(known) == pytest.approx(true_len, rel=0.03)
    assert ate(gt, known, align="none").rmse < 0.2
    assert ate(gt, known, align="none").rmse < 0.5 * ate(gt, measured, align="none").rmse


def test_without_labels_or_road_the_steps_are_the_tracks(drive):
    """No labels (or a UAV's view without a level road): the output is the tracking chain's."""
    off, _, _ = run(drive, False)
    unlabelled, regs, vo = run(drive, True, labels=False)
    assert vo.num_road_steps == 0 and not any(r.road_step for r in regs)
    assert np.allclose(off, unlabelled, atol=1e-6)


def misread_drive(drive: np.ndarray, frames: range, misread) -> np.ndarray:
    """(N, 4, 4) odometry poses along ``drive`` (planar turns and road steps on) where PnP's step in ``frames``
    (frame counts) is misread: its translation (this camera in the previous one) replaced by ``misread(t)``."""
    vo = DepthVisualOdometry(depth_window_px=1, planar_motion=True, road_steps=True)
    solve = vo._solve_pnp

    def misreading(T_pred, intrinsics):
        T, inliers = solve(T_pred, intrinsics)
        if vo.num_frames in frames and T is not None:
            motion = inverse(vo._track_T) @ T  # PnP's turn is kept
            motion[:3, 3] = misread(motion[:3, 3])
            return vo._track_T @ motion, inliers
        return T, inliers

    vo._solve_pnp = misreading
    est = []
    for T in drive:
        gray, depth = render(T)
        est.append(vo.register(gray, depth, INTRINSICS, road_labels(depth)).T_odom_cam)
    assert vo.num_road_steps >= len(drive) - 5
    return np.stack(est)


def test_a_chain_that_reads_the_step_backwards_does_not_turn_the_road_around(drive):
    """Tracks that slide along the street read a few centimetres, either way, where the car drove a metre
    (synthia-like at 10 m/s): five frames whose tracking chain steps 5 cm backwards. A car does not reverse
    from one frame to the next: the road is searched the way it was going too, and finds the true steps."""
    gt = inverse(drive[0]) @ drive
    est = misread_drive(drive, range(8, 13), lambda t: -0.05 * t / np.linalg.norm(t))  # 5 cm back, not 0.9 m on
    assert trajectory_length(est) == pytest.approx(trajectory_length(gt), rel=0.02)
    assert ate(gt, est, align="none").rmse < 0.3


def test_a_chain_that_reads_a_whole_step_backwards_does_not_turn_the_road_around(monkeypatch):
    """PnP on a dozen inliers can read a step backwards at full length (synthia-like report world 584, RGB only:
    1 m back and 0.8 m sideways where the car drove 1.07 m on, then kept by the constant-velocity model while
    PnP failed; a zebra crossing in view). Stripes every 1.6 m across the road give the road a best length that
    way too: 0.7 m back lines them up again where the car drove 0.9 m on, distinct against the lengths around
    it. Searched both ways, the way the car went moves the road better (a one-way search followed the chain)."""
    import tests.odometry.corridor as corridor

    stripes = (np.arange(512) % 4 == 0)[None, :] * 150.0  # a stripe every 4 blocks of 0.4 m along the drive
    monkeypatch.setattr(corridor, "_TEXTURE", (corridor._TEXTURE * 0.3 + stripes).clip(0, 255).astype(np.uint8))
    drive = car_path(20, step_m=0.9, turn_rad=0.015)
    gt = inverse(drive[0]) @ drive
    est = misread_drive(drive, range(8, 11), lambda t: -t)
    along = np.einsum("ni,ni->n", np.diff(est[:, :3, 3], axis=0), est[:-1, :3, 2])  # each step along the camera's axis
    assert (along > 0.8).all(), f"steps along the car's heading: {np.round(along, 2)}"
    assert ate(gt, est, align="none").rmse < 0.3
