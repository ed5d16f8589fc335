"""Depth map -> pseudo-LiDAR point cloud in the camera frame (the input of KISS-ICP).

Ranges are Euclidean distances from the camera centre, the same measure KISS-ICP's own range filter
uses, so the odometry sees exactly the points this module keeps.
"""

from __future__ import annotations

import cv2
import numpy as np

from shgm_slam.errors import DataError
from shgm_slam.geometry.camera import backproject
from shgm_slam.labels import Label
from shgm_slam.types import Intrinsics

UNTRUSTED_LABELS: tuple[int, ...] = (
    Label.SKY, Label.PERSON, Label.RIDER, Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN,
)  # fmt: skip
"""Classes whose predicted depth ICP should not see: sky (no surface), people (moving) and thin
structures (a network smears their few pixels into the background)."""


def depth_to_cloud(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    stride: int,
    min_range_m: float,
    max_range_m: float,
    label_ids: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Back-project every ``stride``-th pixel of a depth map into camera-frame points.

    Args:
        depth_m: (H, W) z-depth in metres; 0, negative, NaN and inf pixels are invalid and skipped.
        intrinsics: pinhole intrinsics of this (H, W) depth map.
        stride: keep every ``stride``-th pixel in both directions (>= 1).
        min_range_m, max_range_m: keep points whose Euclidean range |p| is in [min, max], metres.
        label_ids: optional (H, W) uint8 Cityscapes train ids aligned with ``depth_m``.

    Returns:
        points_cam: (N, 3) float64 points in the camera frame (x right, y down, z forward), metres;
        label_ids: (N,) uint8 label of each point, or None when no labels were given.
        N may be 0 (an all-invalid depth map); the caller decides what an empty cloud means.

    Raises:
        DataError: the depth map is not 2-D, its size disagrees with the intrinsics or the labels, or
            the stride/ranges are invalid.
    """
    depth = np.asarray(depth_m)
    if depth.ndim != 2:
        raise DataError(f"depth map must be (H, W), got shape {depth.shape}")
    H, W = depth.shape
    if (W, H) != intrinsics.size_wh:
        raise DataError(
            f"depth map is {W}x{H} but the intrinsics describe {intrinsics.width}x{intrinsics.height} "
            "images; rescale them with Intrinsics.scaled(width, height)"
        )
    if label_ids is not None and np.shape(label_ids) != depth.shape:
        raise DataError(f"label image {np.shape(label_ids)} and depth map {depth.shape} differ in size")
    if stride < 1:
        raise DataError(f"cloud stride must be >= 1, got {stride}")
    if not 0.0 <= min_range_m < max_range_m:
        raise DataError(f"need 0 <= min_range_m < max_range_m, got {min_range_m} and {max_range_m}")

    # |p| >= z, so z <= max_range is necessary; the exact Euclidean cut follows.
    points_cam, pixel_index = backproject(depth, intrinsics, stride=stride, max_depth_m=max_range_m)
    range_m = np.linalg.norm(points_cam, axis=1)
    keep = (range_m >= min_range_m) & (range_m <= max_range_m)
    points_cam = points_cam[keep]
    if label_ids is None:
        return points_cam, None
    labels = np.asarray(label_ids).reshape(-1)[pixel_index[keep]].astype(np.uint8, copy=False)
    return points_cam, labels


def sampling_spacing_m(points_cam: np.ndarray, intrinsics: Intrinsics, *, stride: int) -> np.ndarray:
    """Distance from each pseudo-LiDAR point to its neighbours on the image sampling grid.

    A depth image samples far and grazing surfaces (the road ahead, facades along the street) sparsely,
    and the sample pattern moves with the camera: two frames of such a surface match best at zero
    motion, which stalls point-to-point ICP. This spacing tells dense samples (safe for ICP) from sparse
    ones. Points are put back on the ``stride`` pixel grid they were back-projected from (as made by
    ``depth_to_cloud``); per point the spacing is max(horizontal, vertical), each the nearer of the two
    neighbours along that image axis, so a point on an occlusion edge takes the spacing of its surface.

    Args:
        points_cam: (N, 3) camera-frame points (x right, y down, z forward), metres, z > 0.
        intrinsics: the intrinsics of the depth map the points came from.
        stride: the pixel stride used by ``depth_to_cloud`` (>= 1).

    Returns:
        (N,) float64 spacing in metres; inf for points with no neighbour along an image axis (isolated
        samples) and for points with z <= 0 or outside the image.

    Raises:
        DataError: points are not (N, 3) or the stride is invalid.
    """
    pts = np.asarray(points_cam, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DataError(f"points must be (N, 3), got shape {pts.shape}")
    if stride < 1:
        raise DataError(f"cloud stride must be >= 1, got {stride}")
    spacing = np.full(pts.shape[0], np.inf)
    h, w = -(-intrinsics.height // stride), -(-intrinsics.width // stride)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint((intrinsics.fx * pts[:, 0] / pts[:, 2] + intrinsics.cx) / stride)
        v = np.rint((intrinsics.fy * pts[:, 1] / pts[:, 2] + intrinsics.cy) / stride)
    on_grid = (pts[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = u[on_grid].astype(np.intp), v[on_grid].astype(np.intp)
    grid = np.full((h + 2, w + 2, 3), np.nan)  # one NaN cell of padding on every side
    grid[v + 1, u + 1] = pts[on_grid]
    centre = grid[1:-1, 1:-1]

    def dist2(dv: int, du: int) -> np.ndarray:  # (h, w) squared distance to the neighbour (dv, du)
        diff = grid[1 + dv : h + 1 + dv, 1 + du : w + 1 + du] - centre
        return np.einsum("ijk,ijk->ij", diff, diff)

    horizontal = np.fmin(dist2(0, -1), dist2(0, 1))  # fmin: a NaN (missing) neighbour is ignored
    vertical = np.fmin(dist2(-1, 0), dist2(1, 0))
    spacing2 = np.fmax(horizontal, vertical)
    spacing2 = np.where(np.isnan(horizontal) | np.isnan(vertical), np.inf, spacing2)
    spacing[on_grid] = np.sqrt(spacing2[v, u])
    return spacing


def depth_edges(depth_m: np.ndarray, rel_jump: float) -> np.ndarray:
    """Pixels at depth discontinuities: where inverse depth bends by more than ``rel_jump`` of itself.

    Inverse depth is linear in the pixel coordinates across any plane (road, facade, even at grazing
    angles), so its second difference along u or v vanishes on surfaces and is large only where one
    surface occludes another. A pixel next to an invalid one (sky, no return) is an edge too.

    Args:
        depth_m: (H, W) z-depth, metres; 0 or non-finite = invalid.
        rel_jump: threshold on ``|second difference of 1/d| * d`` (0.1: a 10 % jump).

    Returns:
        (H, W) bool, True on edges (invalid pixels are False).
    """
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    inv = np.where(valid, 1.0 / np.where(valid, d, 1.0), np.nan).astype(np.float32)
    pad = np.pad(inv, 1, mode="reflect", reflect_type="odd")  # linear extrapolation: planes stay planar
    centre = pad[1:-1, 1:-1]
    bend_u = np.abs(pad[1:-1, :-2] - 2.0 * centre + pad[1:-1, 2:])
    bend_v = np.abs(pad[:-2, 1:-1] - 2.0 * centre + pad[2:, 1:-1])
    with np.errstate(invalid="ignore"):
        bend = np.maximum(bend_u, bend_v) * np.where(valid, d, np.nan)  # NaN where a neighbour is missing
    edge = ~(bend <= rel_jump)  # NaN (a missing neighbour) counts as an edge
    return edge & valid


def trusted_depth(
    depth_m: np.ndarray,
    label_ids: np.ndarray | None,
    *,
    max_depth_m: float,
    edge_rel_jump: float,
    edge_margin_px: int,
    untrusted_labels: tuple[int, ...] = UNTRUSTED_LABELS,
) -> np.ndarray:
    """Predicted depth with the pixels a monocular network gets worst set invalid (0), for ICP.

    Args:
        depth_m: (H, W) z-depth, metres; 0 or non-finite = invalid.
        label_ids: (H, W) Cityscapes train ids, or None.
        max_depth_m: farther depth is dropped (a network's error grows with range), metres.
        edge_rel_jump: ``depth_edges`` threshold.
        edge_margin_px: pixels within this many of an edge are dropped too (networks blur edges).
        untrusted_labels: train ids whose pixels are dropped (default ``UNTRUSTED_LABELS``).

    Returns:
        (H, W) float32 depth, 0 where untrusted or invalid.
    """
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0).astype(np.float32)
    drop = depth_edges(d, edge_rel_jump)
    if edge_margin_px > 0:
        k = 2 * edge_margin_px + 1
        drop = cv2.dilate(drop.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    drop |= d > max_depth_m
    if label_ids is not None and untrusted_labels:
        if np.shape(label_ids) != d.shape:
            raise DataError(f"label image {np.shape(label_ids)} and depth map {d.shape} differ in size")
        drop |= np.isin(label_ids, untrusted_labels)
    return np.where(drop, 0.0, d).astype(np.float32)
