"""Where each robot looks from, and what that does to the evidence between two of them.

A car's camera is 1.5-2 m above the street, a UAV's 30-60 m: the same objects look different from the two.
Flat ground (road, sidewalk, lawn) and buildings have a horizontal centroid that depends on the part seen
(a car sees the strip beside it or a facade, a UAV the whole block or a roof), and poles, traffic lights and
signs are a few pixels from above, so between robots whose cameras look from very different heights they give
no evidence in the match verification (``MatchingConfig.viewpoint_dependent_labels``,
``labels.VIEWPOINT_DEPENDENT_LABELS``);
and the visible part of a solid object moves with the viewpoint, so a closure's translation is less
precise the more the two robots' elevation angles onto its objects differ (``closure_information``).

Each robot's camera height is measured from its own graph: how far above its flat-ground nodes the
keyframes that first saw them were (``camera_height_m``). No configuration says which robot flies.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.labels import FLAT_GROUND_LABELS


def camera_height_m(
    cameras_xyz: np.ndarray, nodes_xyz: np.ndarray, label_ids: np.ndarray, up: np.ndarray | None
) -> float | None:
    """A robot's camera height above the ground it mapped: the median, over its flat-ground nodes
    (``FLAT_GROUND_LABELS``), of how far above the node the camera that first saw it was (metres).

    Args:
        cameras_xyz: (N, 3) position of the keyframe camera anchoring each node, odometry frame, metres.
        nodes_xyz: (N, 3) the nodes' positions in the same frame.
        label_ids: (N,) the nodes' train ids.
        up: (3,) the robot's "up" in that frame (its ground normal), or None.

    Returns:
        Metres, or None without "up" or without flat-ground nodes.
    """
    flat = np.isin(label_ids, FLAT_GROUND_LABELS)
    if up is None or not flat.any():
        return None
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return float(np.median((cameras_xyz[flat] - nodes_xyz[flat]) @ up))


def up_spread_rad(normals_sum: np.ndarray, count: int) -> float | None:
    """Angular spread (radians) of a robot's unit ground normals, all in its odometry frame, from their sum:
    ``sqrt(-2 ln R)`` with ``R`` the length of their mean (the circular standard deviation; 0 when all
    agree). It holds the plane fits' own noise and the odometry's tilt drift between the keyframes: a car's
    normals agree to 0.5-0.7 degrees over a drive, a UAV's from a network's depth scatter by 10-21 degrees
    (the airsim-like tuning worlds 10 and 13, whose UAV odometry's orientation drifted 11 and 46 degrees).

    Args:
        normals_sum: (3,) the sum of the unit normals.
        count: how many were summed.

    Returns:
        Radians, or None without normals.
    """
    if count <= 0:
        return None
    length = float(np.linalg.norm(normals_sum)) / count
    return float(np.sqrt(max(0.0, -2.0 * np.log(max(length, 1e-12)))))


def up_is_level(spread_rad: float | None, object_range_m: float | None, radius_m: float) -> bool:
    """Whether a robot's mean "up" may stand for all of its graph in a gravity-aligned (4-DoF) match: the
    tilt its normals spread by moves its objects, at their distance from the camera, by no more than the
    verification radius (``spread_rad * object_range_m <= radius_m``). A robot whose up is that uncertain
    is matched in 6-DoF, which absorbs a submap's own tilt; a 4-DoF match under a tilted up cannot. False
    while either value is unknown."""
    if spread_rad is None or object_range_m is None:
        return False
    return spread_rad * object_range_m <= radius_m


def views_differ(height_a_m: float | None, height_b_m: float | None, ratio: float) -> bool:
    """Whether two robots look from very different heights: the higher camera more than ``ratio`` times
    as high as the lower one (a floor of 0.1 m keeps a camera at ground level finite). False while either
    height is unknown: viewpoint-dependent labels then count, as between two cars."""
    if height_a_m is None or height_b_m is None:
        return False
    low, high = sorted((height_a_m, height_b_m))
    return high > ratio * max(low, 0.1)


def elevation_gap_rad(
    rays_a: np.ndarray, rays_b: np.ndarray, up_a: np.ndarray | None, up_b: np.ndarray | None
) -> float:
    """Median angle in radians between the elevations at which two robots saw the same objects: 0 for two
    cars, ~0.7 for a car and a UAV 50 m up.

    Args:
        rays_a, rays_b: (M, 3) unit viewing rays onto the M matched objects, each in its robot's graph frame.
        up_a, up_b: (3,) "up" in those frames; 0 when either is unknown or there are no rays.
    """
    if up_a is None or up_b is None or len(rays_a) == 0:
        return 0.0
    elev_a = np.arcsin(np.clip(rays_a @ (up_a / np.linalg.norm(up_a)), -1.0, 1.0))
    elev_b = np.arcsin(np.clip(rays_b @ (up_b / np.linalg.norm(up_b)), -1.0, 1.0))
    return float(np.median(np.abs(elev_a - elev_b)))


def viewing_rays(cameras_xyz: np.ndarray, positions_xyz: np.ndarray) -> np.ndarray:
    """(M, 3) unit rays from each camera towards its node.

    Args:
        cameras_xyz: (M, 3) position of the camera that first saw each node (its anchor keyframe), metres.
        positions_xyz: (M, 3) the nodes' positions in the same frame, metres.
    """
    rays = positions_xyz - cameras_xyz
    return rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)


def closure_information(
    sigma_rot_rad: float, sigma_trans_m: float, elevation_gap: float, per_elevation: float
) -> np.ndarray:
    """(6, 6) information of a closure in gtsam order [rot, trans]: the configured sigmas, translation
    grown by ``1 + per_elevation * elevation_gap`` (``elevation_gap_rad``). What a camera sees of an object
    depends on where it looks from: a car sees a tree's side and a bus's flank, a UAV their tops, so a
    car-UAV closure is less precise than one between two cars (airsim-like tuning worlds: 1.12 against
    0.40 m median error) while its rotation is not (0.8 against 1.1 degrees). Weighted alike, the closures
    of a UAV that joined pulled the cars already placed by up to a metre."""
    trans = sigma_trans_m * (1.0 + per_elevation * elevation_gap)
    return np.diag([sigma_rot_rad**-2] * 3 + [trans**-2] * 3)
