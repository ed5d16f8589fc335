"""The ground plane and "up": where gravity points, from the road under a camera."""

from __future__ import annotations

import logging

import numpy as np

from shgm_slam.geometry import se3
from shgm_slam.labels import Label

log = logging.getLogger(__name__)


GROUND_LABELS = (Label.ROAD, Label.SIDEWALK, Label.TERRAIN)


def ground_normal(
    points_cam: np.ndarray, label_ids: np.ndarray | None, *, max_range_m: float = 100.0
) -> np.ndarray | None:
    """Unit normal of the ground plane, pointing up (towards the camera), in the camera frame.

    Fitted to the road, sidewalk and terrain points of one pseudo-LiDAR cloud (least squares plane);
    None when there are too few ground points or they are not planar (RMS distance > 0.3 m).
    """
    if label_ids is None:
        return None
    ground = np.isin(label_ids, GROUND_LABELS) & (np.linalg.norm(points_cam, axis=1) < max_range_m)
    pts = points_cam[ground]
    if len(pts) < 200:
        return None
    centre = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts[:: max(1, len(pts) // 5000)] - centre, full_matrices=False)
    normal = vt[2]
    if sv[2] / np.sqrt(len(pts[:: max(1, len(pts) // 5000)])) > 0.3 or sv[1] < 1e-6:
        return None
    return normal if normal @ (-centre) > 0 else -normal


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking the unit vector ``up`` onto +z (the gravity-aligned frame's vertical)."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = np.linalg.norm(axis), float(up @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else se3.rot_x(np.pi)
    return se3.so3_exp(axis / s * np.arctan2(s, c))
