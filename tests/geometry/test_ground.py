"""The ground normal against the true up: level road beside raised sidewalks, outliers, fallbacks."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry import se3
from shgm_slam.geometry.ground import MIN_GROUND_POINTS, ground_normal, rotation_to_z
from shgm_slam.labels import Label

CAMERA_HEIGHT_M = 1.65


def _street(rng: np.random.Generator, n_road: int = 4000, n_side: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Points of a street in a gravity frame (x right, y down, z forward; camera at the origin): a level road
    3.5 m left to 4 m right of the camera, a sidewalk 0.15 m higher from 4 to 7 m right, a grass strip
    0.05 m higher than that beyond it (the side a car keeps to)."""
    road = np.column_stack(
        [rng.uniform(-3.5, 4.0, n_road), np.full(n_road, CAMERA_HEIGHT_M), rng.uniform(3.0, 40.0, n_road)]
    )
    side = np.column_stack(
        [rng.uniform(4.0, 7.0, n_side), np.full(n_side, CAMERA_HEIGHT_M - 0.15), rng.uniform(3.0, 40.0, n_side)]
    )
    grass = np.column_stack(
        [rng.uniform(7.0, 9.0, n_side), np.full(n_side, CAMERA_HEIGHT_M - 0.2), rng.uniform(3.0, 40.0, n_side)]
    )
    points = np.vstack([road, side, grass])
    labels = np.concatenate(
        [np.full(n_road, Label.ROAD), np.full(n_side, Label.SIDEWALK), np.full(n_side, Label.TERRAIN)]
    ).astype(np.uint8)
    return points, labels


def _camera(points_gravity: np.ndarray, roll_deg: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The gravity-frame points seen by a camera rolled and pitched by the given angles, and the true up
    (towards the sky: -y of the gravity frame) in that camera's frame."""
    R_cam_gravity = se3.rot_x(np.radians(pitch_deg)) @ se3.so3_exp(np.array([0.0, 0.0, np.radians(roll_deg)]))
    return points_gravity @ R_cam_gravity.T, R_cam_gravity @ np.array([0.0, -1.0, 0.0])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def test_level_road_gives_the_true_up_beside_raised_sidewalks() -> None:
    rng = np.random.default_rng(0)
    points, labels = _street(rng)
    points_cam, up_true = _camera(points, roll_deg=2.0, pitch_deg=-3.0)
    normal = ground_normal(points_cam, labels)
    assert normal is not None
    assert _angle_deg(normal, up_true) < 0.01
    # the sidewalk and grass on one side tilt a plane through all ground classes: the bias the road avoids
    everything = ground_normal(points_cam, np.where(labels == Label.ROAD, Label.SIDEWALK, labels).astype(np.uint8))
    assert everything is not None and _angle_deg(everything, up_true) > 0.2


def test_mislabelled_points_are_trimmed() -> None:
    rng = np.random.default_rng(1)
    points, labels = _street(rng)
    road = np.flatnonzero(labels == Label.ROAD)
    car = rng.choice(road, size=len(road) // 10, replace=False)  # a parked car's pixels labelled road
    points[car, 1] -= rng.uniform(0.3, 1.5, size=car.size)
    points += rng.normal(0.0, 0.02, size=points.shape)
    points_cam, up_true = _camera(points, roll_deg=-1.0, pitch_deg=1.5)
    normal = ground_normal(points_cam, labels)
    assert normal is not None
    assert _angle_deg(normal, up_true) < 0.1


def test_too_little_road_falls_back_to_every_ground_class() -> None:
    rng = np.random.default_rng(2)
    points, labels = _street(rng, n_road=MIN_GROUND_POINTS - 1, n_side=1000)
    labels[labels == Label.TERRAIN] = Label.SIDEWALK
    points[:, 1] = CAMERA_HEIGHT_M  # a level square: a few road pixels, the rest paved
    points_cam, up_true = _camera(points, roll_deg=0.5, pitch_deg=0.0)
    normal = ground_normal(points_cam, labels)
    assert normal is not None
    assert _angle_deg(normal, up_true) < 0.05


def test_normal_points_towards_the_camera() -> None:
    rng = np.random.default_rng(3)
    points, labels = _street(rng)
    for roll, pitch in [(0.0, 0.0), (10.0, -20.0), (-5.0, 30.0)]:
        points_cam, up_true = _camera(points, roll, pitch)
        normal = ground_normal(points_cam, labels)
        assert normal is not None and normal @ up_true > 0.99
        assert np.isclose(np.linalg.norm(normal), 1.0)


def test_no_normal_without_a_plane() -> None:
    rng = np.random.default_rng(4)
    points, labels = _street(rng)
    assert ground_normal(points, None) is None
    few = labels.copy()
    few[MIN_GROUND_POINTS // 2 :] = Label.BUILDING
    assert ground_normal(points, few) is None
    scattered = rng.uniform(-10.0, 10.0, size=points.shape)  # no plane at all: metres of scatter
    assert ground_normal(scattered, labels) is None
    far = points * np.array([1.0, 1.0, 10.0])  # every point beyond the range cap
    assert ground_normal(far + np.array([0.0, 0.0, 200.0]), labels, max_range_m=100.0) is None


@pytest.mark.parametrize("up", [[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [0.3, -0.9, 0.1], [0.0, 0.0, -1.0]])
def test_rotation_to_z_takes_up_onto_z(up: list[float]) -> None:
    u = np.asarray(up) / np.linalg.norm(up)
    R = rotation_to_z(u)
    assert np.allclose(R @ u, [0.0, 0.0, 1.0], atol=1e-12)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_a_uav_sees_its_ground_through_range_proportional_depth_noise() -> None:
    """A UAV 45 m up sees the road 50-100 m away; a network's depth errs in proportion to range (here 2 %
    along each ray): the road is metres thick, yet its normal is right to within a few degrees. A fixed
    tolerance of a car's scale refused every such keyframe (the UAV's "up" stayed unknown)."""
    rng = np.random.default_rng(5)
    n = 4000
    road = np.column_stack([rng.uniform(-40.0, 40.0, n), np.full(n, 45.0), rng.uniform(40.0, 85.0, n)])
    labels = np.full(n, Label.ROAD, dtype=np.uint8)
    points_cam, up_true = _camera(road, roll_deg=1.0, pitch_deg=-40.0)
    noisy = points_cam * (1.0 + rng.normal(0.0, 0.02, size=(n, 1)))  # scaled along each viewing ray
    thickness_m = float(np.std((noisy - noisy.mean(axis=0)) @ up_true))
    assert thickness_m > 0.3  # beyond a car's fixed tolerance
    normal = ground_normal(noisy, labels)
    assert normal is not None
    assert _angle_deg(normal, up_true) < 3.0
    # the same scatter a few metres from the camera is no plane
    near = rng.uniform(-10.0, 10.0, size=(n, 3)) + np.array([0.0, 0.0, 12.0])
    assert ground_normal(near, labels) is None
