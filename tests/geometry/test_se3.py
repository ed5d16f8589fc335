"""SE(3) helpers and the rigid fits (the paper's Eq. 2) against transforms they must recover exactly."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.geometry.se3 import (
    inverse,
    kabsch,
    kabsch_yaw,
    make_pose,
    pose_error,
    project_to_so3,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    so3_exp,
    transform_points,
    yaw_basis,
)


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """(N, 4, 4) rigid transforms: random rotations (any angle up to pi) and translations up to 1 km."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return make_pose(so3_exp(axes * rng.uniform(0, np.pi, (n, 1))), rng.uniform(-1000, 1000, (n, 3)))


def test_inverse_composes_to_identity_and_maps_points_back() -> None:
    rng = np.random.default_rng(0)
    T = _random_poses(rng, 50)
    np.testing.assert_allclose(inverse(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-9)
    p = rng.uniform(-50, 50, (20, 3))
    np.testing.assert_allclose(transform_points(inverse(T[0]), transform_points(T[0], p)), p, atol=1e-9)


def test_rodrigues_agrees_with_the_axis_rotations_and_their_angle() -> None:
    for a in (1e-12, 0.3, 2.0, np.pi - 1e-6):
        np.testing.assert_allclose(so3_exp([a, 0, 0]), rot_x(a), atol=1e-12)
        np.testing.assert_allclose(so3_exp([0, a, 0]), rot_y(a), atol=1e-12)
        np.testing.assert_allclose(so3_exp([0, 0, a]), rot_z(a), atol=1e-12)
        assert rotation_angle(so3_exp([a / 3**0.5] * 3)) == pytest.approx(a, abs=1e-6)
    R = so3_exp(np.random.default_rng(1).normal(size=(100, 3)))
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_pose_error_reads_a_known_offset() -> None:
    T = _random_poses(np.random.default_rng(2), 1)[0]
    off = make_pose(rot_z(np.radians(7.0)), [3.0, 4.0, 0.0])
    trans_m, rot_deg = pose_error(T @ off, T)
    assert trans_m == pytest.approx(5.0) and rot_deg == pytest.approx(7.0)


def test_projection_gives_the_nearest_proper_rotation() -> None:
    rng = np.random.default_rng(3)
    R = so3_exp(rng.normal(size=(30, 3)))
    np.testing.assert_allclose(project_to_so3(R + rng.normal(0, 1e-3, R.shape)), R, atol=5e-3)
    reflected = R @ np.diag([1.0, 1.0, -1.0])  # det -1: the nearest rotation, not the reflection
    assert np.allclose(np.linalg.det(project_to_so3(reflected)), 1.0)


def test_kabsch_recovers_a_rigid_transform_batched_and_weighted() -> None:
    rng = np.random.default_rng(4)
    T = _random_poses(rng, 8)
    P = rng.uniform(-30, 30, (8, 12, 3))
    Q = np.einsum("bij,bkj->bki", T[:, :3, :3], P) + T[:, None, :3, 3]
    np.testing.assert_allclose(kabsch(P, Q), T, atol=1e-8)
    np.testing.assert_allclose(kabsch(P[0], Q[0]), T[0], atol=1e-8)
    # an outlier with zero weight changes nothing; the others' weights do not matter when they agree exactly
    Q_bad = Q[0].copy()
    Q_bad[0] += 100.0
    w = rng.uniform(0.5, 2.0, 12)
    w[0] = 0.0
    np.testing.assert_allclose(kabsch(P[0], Q_bad, w), T[0], atol=1e-8)
    # collinear points: still a proper rotation, never NaN
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    R = kabsch(line, line + 1.0)[:3, :3]
    assert np.all(np.isfinite(R)) and np.allclose(np.linalg.det(R), 1.0)


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, -1.0, 0.0), (0.3, -0.9, 0.2)], ids=["z-up", "kitti", "tilted"])
def test_kabsch_yaw_recovers_a_turn_about_up_and_only_turns_about_it(up: tuple[float, float, float]) -> None:
    rng = np.random.default_rng(5)
    u = np.asarray(up) / np.linalg.norm(up)
    B = yaw_basis(u)
    np.testing.assert_allclose(B @ B.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(B[2], u)
    yaw = 2.5
    R = so3_exp(u * yaw)
    t = rng.uniform(-200, 200, 3)
    P = rng.uniform(-40, 40, (15, 3))
    T = kabsch_yaw(P, P @ R.T + t, up=u)
    np.testing.assert_allclose(T, make_pose(R, t), atol=1e-8)
    # noisy points: the fit still turns about up only (up is a fixed axis of its rotation)
    T_noisy = kabsch_yaw(P, P @ R.T + t + rng.normal(0, 0.5, P.shape), up=u)
    np.testing.assert_allclose(T_noisy[:3, :3] @ u, u, atol=1e-12)
    assert rotation_angle(T_noisy[:3, :3] @ R.T) < np.radians(3.0)
