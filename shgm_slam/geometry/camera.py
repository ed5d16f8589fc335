"""Pinhole camera geometry: back-projection of depth maps and projection of points.

Camera frame is KITTI's RDF: x right, y down, z forward; pixel (u, v) = (column, row), pixel centres
at integer coordinates.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.types import Intrinsics


def backproject(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    stride: int = 1,
    min_depth_m: float = 0.0,
    max_depth_m: float = np.inf,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth map to camera-frame points.

    Args:
        depth_m: (H, W) metric z-depth; 0 or non-finite is invalid.
        intrinsics: pinhole intrinsics of the depth map.
        stride: keep every ``stride``-th pixel in both directions.
        min_depth_m, max_depth_m: keep depths in (min, max].

    Returns:
        points_cam: (M, 3) float64 points in the camera frame (metres);
        pixel_index: (M,) int64 flat indices ``v * W + u`` of the kept pixels into the full image.
    """
    depth = np.asarray(depth_m)
    W = depth.shape[1]
    z = depth[::stride, ::stride]
    ok = np.isfinite(z) & (z > max(min_depth_m, 0.0)) & (z <= max_depth_m)
    v, u = np.nonzero(ok)
    v = v * stride
    u = u * stride
    zz = z[ok].astype(np.float64)
    x = (u - intrinsics.cx) * zz / intrinsics.fx
    y = (v - intrinsics.cy) * zz / intrinsics.fy
    return np.stack([x, y, zz], axis=1), (v.astype(np.int64) * W + u)


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) float64 ray directions with z = 1 for every pixel (camera frame)."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width].astype(np.float64)
    return np.stack(
        [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], axis=-1
    )


def project(points_cam: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera-frame points to pixels.

    Returns:
        uv: (N, 2) float64 pixel coordinates (u = column, v = row);
        in_front: (N,) bool, True where z > 0 (uv of other points is meaningless).
    """
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    in_front = z > 1e-9
    zs = np.where(in_front, z, 1.0)
    uv = np.stack([intrinsics.fx * p[:, 0] / zs + intrinsics.cx, intrinsics.fy * p[:, 1] / zs + intrinsics.cy], 1)
    return uv, in_front
