"""Batched SE(3) helpers and (weighted) rigid alignment.

Every function accepts a single (4, 4) pose or an (N, 4, 4) stack where it says so; poses are
``T_to_from`` float64. Rotations are (…, 3, 3).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble (…, 4, 4) poses from (…, 3, 3) rotations and (…, 3) translations."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of (…, 4, 4) rigid transforms (uses R^T, no general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return make_pose(Rt, t)


def transform_points(T_to_from: np.ndarray, points_from: np.ndarray) -> np.ndarray:
    """Map (N, 3) points by one (4, 4) transform: returns (N, 3) float64 in the ``to`` frame."""
    T = np.asarray(T_to_from, dtype=np.float64)
    p = np.asarray(points_from, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def rot_x(a: float) -> np.ndarray:
    """(3, 3) rotation about x by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """(3, 3) rotation about y by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """(3, 3) rotation about z by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: (…, 3) rotation vectors (radians) to (…, 3, 3) rotation matrices."""
    w = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    small = theta < 1e-9
    safe = np.where(small, 1.0, theta)
    A = np.where(small, 1.0, np.sin(safe) / safe)
    B = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + A * K + B * (K @ K)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of (…, 3, 3) rotations (or of the rotation part of (…, 4, 4) poses)."""
    R = np.asarray(R, dtype=np.float64)[..., :3, :3]
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation error (m) and rotation error (deg) between (…, 4, 4) poses."""
    d = inverse(T_true) @ np.asarray(T_est, dtype=np.float64)
    return np.linalg.norm(d[..., :3, 3], axis=-1), np.degrees(rotation_angle(d))


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to each (…, 3, 3) matrix."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.ones(U.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def kabsch(
    points_src: np.ndarray, points_dst: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Weighted least-squares rigid transform(s) ``T_dst_src`` minimizing sum w_k |q_k - R p_k - t|^2.

    This is the closed form of the paper's Eq. 2 (Umeyama without scale).

    Args:
        points_src: (K, 3) or batched (B, K, 3) points p_k.
        points_dst: same shape, corresponding points q_k.
        weights: (K,) or (B, K) non-negative weights W_k; uniform when None.

    Returns:
        (4, 4) or (B, 4, 4) float64 transform mapping src points onto dst points. Degenerate inputs
        (fewer than 3 non-collinear weighted points) still return a proper rotation, not NaN.
    """
    P = np.asarray(points_src, dtype=np.float64)
    Q = np.asarray(points_dst, dtype=np.float64)
    single = P.ndim == 2
    if single:
        P, Q = P[None], Q[None]
        weights = None if weights is None else np.asarray(weights, dtype=np.float64)[None]
    w = np.ones(P.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    wsum = np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    wn = w / wsum
    mp = np.einsum("bk,bki->bi", wn, P)
    mq = np.einsum("bk,bki->bi", wn, Q)
    H = np.einsum("bk,bki,bkj->bij", wn, P - mp[:, None], Q - mq[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.ones((P.shape[0], 3))
    D[:, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ (D[:, :, None] * np.swapaxes(U, -1, -2))
    t = mq - np.einsum("bij,bj->bi", R, mp)
    T = make_pose(R, t)
    return T[0] if single else T


def yaw_basis(up: np.ndarray) -> np.ndarray:
    """(3, 3) read-only rows (e1, e2, up) of an orthonormal frame whose third axis is ``up`` (3,), any length
    > 0: the horizontal plane is e1-e2 (cached per axis)."""
    u = np.asarray(up, dtype=np.float64)
    return _yaw_basis(tuple((u / np.linalg.norm(u)).tolist()))


@lru_cache(maxsize=16)
def _yaw_basis(up: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) read-only rows (e1, e2, up) for a unit ``up``: yaw is a rotation in the e1-e2 plane (cached:
    every gravity-aligned fit of a run uses the same axis)."""
    u = np.asarray(up)
    e1 = np.cross(u, [1.0, 0, 0]) if abs(u[0]) < 0.9 else np.cross(u, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    B = np.stack([e1, e2, u])
    B.flags.writeable = False
    return B


def kabsch_yaw(
    points_src: np.ndarray, points_dst: np.ndarray, weights: np.ndarray | None = None, up: np.ndarray | None = None
) -> np.ndarray:
    """Gravity-aligned 4-DoF (yaw about ``up`` + translation) weighted fit ``T_dst_src``.

    Args:
        points_src, points_dst: (K, 3) or (B, K, 3) corresponding points.
        weights: (K,) or (B, K) weights, uniform when None.
        up: (3,) unit vector of the shared vertical axis (default +z).

    Returns:
        (4, 4) or (B, 4, 4) transforms whose rotation is about ``up`` only.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    P = np.asarray(points_src, dtype=np.float64)
    Q = np.asarray(points_dst, dtype=np.float64)
    single = P.ndim == 2
    if single:
        P, Q = P[None], Q[None]
        weights = None if weights is None else np.asarray(weights, dtype=np.float64)[None]
    w = np.ones(P.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    wn = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    mp = np.einsum("bk,bki->bi", wn, P)
    mq = np.einsum("bk,bki->bi", wn, Q)
    B = _yaw_basis(tuple(up.tolist()))
    p = np.einsum("ij,bkj->bki", B, P - mp[:, None])
    q = np.einsum("ij,bkj->bki", B, Q - mq[:, None])
    s = np.einsum("bk,bk->b", wn, p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0])
    c = np.einsum("bk,bk->b", wn, p[..., 0] * q[..., 0] + p[..., 1] * q[..., 1])
    yaw = np.arctan2(s, c)
    Rl = np.zeros((P.shape[0], 3, 3))
    Rl[:, 0, 0], Rl[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    Rl[:, 1, 0], Rl[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    Rl[:, 2, 2] = 1.0
    R = B.T @ Rl @ B
    t = mq - np.einsum("bij,bj->bi", R, mp)
    T = make_pose(R, t)
    return T[0] if single else T
