"""Closure cutting and the local refit (``server.closures``): solid objects seen from opposite sides."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry import se3
from shgm_slam.labels import Label
from shgm_slam.server.closures import SurfaceOffset, local_closures, refit

UP = np.array([0.0, 0.0, 1.0])


def _street(rng, n_solid: int, n_thin: int, length_m: float = 60.0):
    """Objects along both sides of a street on the x axis: (N, 3) centres and (N,) labels."""
    n = n_solid + n_thin
    x = np.sort(rng.uniform(0.0, length_m, n))
    y = rng.choice([-7.0, 7.0], n) + rng.normal(0.0, 0.5, n)
    z = rng.uniform(0.5, 3.0, n)
    labels = np.array([Label.CAR, Label.VEGETATION] * n_solid)[:n_solid].tolist() + [Label.POLE] * n_thin
    return np.column_stack([x, y, z]), np.asarray(rng.permutation(labels), dtype=np.int64)


def _seen(centres, labels, heading: float, offset_m: float):
    """What a car driving along x with ``heading`` (+1 or -1) sees: the solid objects' centroids moved
    ``offset_m`` towards the camera that first saw them (25 m before it along the street)."""
    cameras = centres.copy()
    cameras[:, 0] -= heading * 25.0
    cameras[:, 1:] = [0.0, 1.5]
    rays = centres - cameras
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    solid = np.isin(labels, [Label.CAR, Label.VEGETATION])
    return centres - offset_m * solid[:, None] * rays, rays


def _error_m(T: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    d = se3.transform_points(T, points) - se3.transform_points(T_true, points)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_opposite_views_of_solid_objects_are_refit_without_their_surface_bias(seed):
    rng = np.random.default_rng(seed)
    centres, labels = _street(rng, n_solid=14, n_thin=2)
    seen_a, rays_a = _seen(centres, labels, +1.0, 1.0)
    seen_b, rays_b = _seen(centres, labels, -1.0, 1.0)
    T_b_world = se3.make_pose(se3.rot_z(rng.uniform(-np.pi, np.pi)), rng.uniform(-50, 50, 3))
    pos_b = se3.transform_points(T_b_world, seen_b)
    rays_b = rays_b @ T_b_world[:3, :3].T
    T_true = se3.inverse(T_b_world)
    plain = refit(seen_a, pos_b, labels, UP, T_b_world[:3, :3] @ UP)
    aware = refit(seen_a, pos_b, labels, UP, T_b_world[:3, :3] @ UP, rays_a, rays_b)
    probe = se3.transform_points(T_b_world, centres)
    assert _error_m(plain, T_true, probe) > 1.0  # opposite views: ~2 x 1 m along the street
    assert _error_m(aware, T_true, probe) < 0.3  # two poles fix the translation (the prior pulls a little)


def test_the_fleet_learns_the_offset_where_thin_objects_fix_the_translation_and_uses_it_elsewhere():
    rng = np.random.default_rng(11)
    offset = SurfaceOffset()
    for solid, thin in ((12, 4), (14, 0)):  # a stretch with poles, then one with none
        centres, labels = _street(rng, n_solid=solid, n_thin=thin)
        seen_a, rays_a = _seen(centres, labels, +1.0, 1.2)
        seen_b, rays_b = _seen(centres, labels, -1.0, 1.2)
        T = refit(seen_a, seen_b, labels, UP, UP, rays_a, rays_b, offset=offset)
        assert _error_m(T, np.eye(4), centres) < 0.15
    assert offset.mean == pytest.approx(1.2, abs=0.1)
    blind = refit(seen_a, seen_b, labels, UP, UP, rays_a, rays_b)  # no poles and no fleet estimate: biased
    assert _error_m(blind, np.eye(4), centres) > 1.5


def test_same_direction_views_need_no_offset_and_stay_exact():
    rng = np.random.default_rng(5)
    centres, labels = _street(rng, n_solid=12, n_thin=0)
    seen_a, rays_a = _seen(centres, labels, +1.0, 1.0)
    T_b_world = se3.make_pose(se3.rot_z(0.7), np.array([10.0, -4.0, 0.3]))
    pos_b = se3.transform_points(T_b_world, seen_a)
    T = refit(seen_a, pos_b, labels, UP, T_b_world[:3, :3] @ UP, rays_a, rays_a @ T_b_world[:3, :3].T)
    assert _error_m(T, se3.inverse(T_b_world), pos_b) < 1e-6


def test_thin_objects_carry_the_fit_without_rays():
    rng = np.random.default_rng(7)
    centres, labels = _street(rng, n_solid=10, n_thin=5)
    seen_a, _ = _seen(centres, labels, +1.0, 1.0)
    seen_b, _ = _seen(centres, labels, -1.0, 1.0)
    T = refit(seen_a, seen_b, labels, UP, UP)
    assert _error_m(T, np.eye(4), centres) < 1e-6  # the poles alone: unbiased


def test_local_closures_cut_a_long_match_into_unbiased_stretches():
    rng = np.random.default_rng(3)
    centres, labels = _street(rng, n_solid=60, n_thin=6, length_m=200.0)
    seen_a, rays_a = _seen(centres, labels, +1.0, 1.0)
    seen_b, rays_b = _seen(centres, labels, -1.0, 1.0)
    anchors_a = np.floor(centres[:, 0] / 2.0).astype(np.int64)
    anchors_b = np.floor((200.0 - centres[:, 0]) / 2.0).astype(np.int64)
    offset = SurfaceOffset()
    for _ in range(2):  # the server sees many matches: the second pass starts from what the first measured
        out = local_closures(
            seen_a, seen_b, labels, anchors_a, anchors_b, np.eye(4), segment_m=40.0, min_inliers=4, max_rmse_m=3.0,
            up_a=UP, up_b=UP, rays_a=rays_a, rays_b=rays_b, offset=offset,
        )  # fmt: skip
    assert len(out) >= 4 and offset.mean == pytest.approx(1.0, abs=0.1)
    for _kf_a, _kf_b, T, n, rows in out:
        assert n == len(rows) >= 4
        assert _error_m(T, np.eye(4), centres[rows]) < 0.2


def test_a_uav_and_a_car_agree_on_the_height_of_flat_ground_not_on_that_of_objects():
    """A UAV sees the tops of poles and trees, a car their sides: their centroids differ in height, while
    road and sidewalk patches (flat) have the same height from anywhere but a viewpoint-dependent
    horizontal centroid. The 4-DoF refit takes its height from the flat nodes."""
    rng = np.random.default_rng(9)
    centres, labels = _street(rng, n_solid=0, n_thin=8)
    flat = np.column_stack([rng.uniform(0, 60, 6), rng.uniform(-5, 5, 6), np.zeros(6)])
    pos_a = np.r_[centres, flat]
    lift = np.array([0.0, 0.0, 1.5])
    pos_b = np.r_[centres + lift, flat + np.c_[rng.normal(0, 2.0, (6, 2)), np.zeros(6)]]
    labels = np.r_[labels, [Label.ROAD, Label.SIDEWALK] * 3]
    T_b_world = se3.make_pose(se3.rot_z(0.4), np.array([5.0, -3.0, 48.0]))
    T = refit(pos_a, se3.transform_points(T_b_world, pos_b), labels, UP, T_b_world[:3, :3] @ UP)
    assert _error_m(T, se3.inverse(T_b_world), centres) < 1e-6  # poles: yaw and horizontal; ground: height
    no_ground = refit(pos_a[:8], se3.transform_points(T_b_world, pos_b[:8]), labels[:8], UP, T_b_world[:3, :3] @ UP)
    drop = se3.transform_points(no_ground @ T_b_world, centres) - centres
    np.testing.assert_allclose(drop, np.tile([0.0, 0.0, -1.5], (8, 1)), atol=1e-6)  # the poles' tops put it 1.5 m low

