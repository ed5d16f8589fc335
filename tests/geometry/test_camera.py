"""Pinhole back-projection and projection: each undoes the other, pixel for pixel."""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry.camera import backproject, pixel_rays, project
from shgm_slam.types import Intrinsics

K = Intrinsics(fx=180.0, fy=175.0, cx=159.5, cy=47.2, width=320, height=96)


def test_a_back_projected_depth_map_projects_onto_its_own_pixels() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(2.0, 80.0, (K.height, K.width))
    points, index = backproject(depth, K)
    assert points.shape == (K.height * K.width, 3) and np.array_equal(index, np.arange(K.height * K.width))
    uv, in_front = project(points, K)
    v, u = np.divmod(index, K.width)
    assert in_front.all()
    np.testing.assert_allclose(uv, np.stack([u, v], axis=1), atol=1e-9)
    np.testing.assert_allclose(points[:, 2], depth.reshape(-1))  # z-depth, not range
    rays = pixel_rays(K).reshape(-1, 3)
    np.testing.assert_allclose(points, rays * depth.reshape(-1, 1), atol=1e-9)


def test_invalid_depth_and_the_range_are_left_out_and_indices_point_into_the_full_image() -> None:
    depth = np.full((K.height, K.width), 10.0)
    depth[0, 0], depth[0, 2], depth[2, 2], depth[4, 4] = np.nan, 0.0, 500.0, 1.0
    points, index = backproject(depth, K, stride=2, min_depth_m=1.5, max_depth_m=100.0)
    assert points.shape[0] == (K.height // 2) * (K.width // 2) - 4  # NaN, zero, too far, too near
    assert np.all(index % K.width % 2 == 0) and np.all(index // K.width % 2 == 0)
    assert not {0, 2, 2 * K.width + 2, 4 * K.width + 4} & set(index.tolist())
    assert np.allclose(points[:, 2], 10.0)


def test_points_behind_the_camera_are_flagged() -> None:
    _, in_front = project(np.array([[0.0, 0.0, 5.0], [1.0, 1.0, -5.0], [0.0, 0.0, 0.0]]), K)
    assert in_front.tolist() == [True, False, False]
