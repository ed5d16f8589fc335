"""A procedurally textured corridor rendered exactly (ray-plane intersection): images with true depth.

World frame = camera convention of the first frame: x right, y down, z forward (metres). Walls at
x = +-6 m, floor at y = +1.6 m, ceiling at y = -8 m; every surface carries a random block texture
(0.4 m blocks, like windows and paving), which gives trackable corners.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.types import Intrinsics

INTRINSICS = Intrinsics(fx=300.0, fy=300.0, cx=319.5, cy=95.5, width=640, height=192)
PLANES = ((np.array([1.0, 0, 0]), 6.0), (np.array([1.0, 0, 0]), -6.0), (np.array([0, 1.0, 0]), 1.6),
          (np.array([0, 1.0, 0]), -8.0))  # (normal, offset): points with normal . p = offset  # fmt: skip
_TEXTURE = np.random.default_rng(7).integers(20, 236, size=(512, 512)).astype(np.uint8)
BLOCK_M = 0.4


def render(T_world_cam: np.ndarray, intrinsics: Intrinsics = INTRINSICS) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) uint8 image and (H, W) float32 depth (z, metres; 0 = nothing hit) seen from ``T_world_cam``."""
    w, h = intrinsics.width, intrinsics.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays_cam = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], -1)
    rays = rays_cam @ T_world_cam[:3, :3].T
    origin = T_world_cam[:3, 3]
    depth = np.full((h, w), np.inf)
    tex = np.zeros((h, w), np.uint8)
    for k, (n, c) in enumerate(PLANES):
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - origin @ n) / denom
        hit = (t > 0.1) & (t < depth) & (t < 150.0)
        p = origin + rays[hit] * t[hit, None]
        a, b = (p[:, 1], p[:, 2]) if n[0] else (p[:, 0], p[:, 2])
        ia = np.floor(a / BLOCK_M).astype(np.int64) + 97 * k
        ib = np.floor(b / BLOCK_M).astype(np.int64)
        tex[hit] = _TEXTURE[ia % 512, ib % 512]
        depth[hit] = t[hit]
    depth[~np.isfinite(depth)] = 0.0
    return tex, depth.astype(np.float32)


def path(num_frames: int, step_m: float = 1.0, yaw_amplitude_rad: float = 0.15) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam`` driving down the corridor, weaving gently (yaw and sideways)."""
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(num_frames):
        s = i / max(num_frames - 1, 1)
        yaw = yaw_amplitude_rad * np.sin(2 * np.pi * s)
        c, si = np.cos(yaw), np.sin(yaw)
        poses[i, :3, :3] = [[c, 0, si], [0, 1, 0], [-si, 0, c]]
        poses[i, :3, 3] = [1.5 * np.sin(2 * np.pi * s), 0.0, i * step_m]
    return poses
