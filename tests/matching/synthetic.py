"""Synthetic labelled point worlds for the matching tests (small and fast, deterministic by seed)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.geometry.se3 import inverse, make_pose, rot_x, rot_y, rot_z
from shgm_slam.labels import Label
from shgm_slam.types import GraphArrays

CITY_LABELS = np.array(
    [Label.BUILDING, Label.POLE, Label.TRAFFIC_SIGN, Label.VEGETATION, Label.CAR, Label.FENCE]
)
CITY_PROBS = np.array([0.2, 0.2, 0.1, 0.2, 0.25, 0.05])


def random_pose(
    rng: np.random.Generator, gravity_aligned: bool = False, translation_m: float = 80.0
) -> np.ndarray:
    """A random rigid transform: yaw about -y (KITTI up) only, or a full 3D rotation."""
    R = rot_y(rng.uniform(-np.pi, np.pi))
    if not gravity_aligned:
        R = rot_x(rng.uniform(-np.pi, np.pi)) @ rot_z(rng.uniform(-np.pi, np.pi)) @ R
    return make_pose(R, rng.uniform(-translation_m, translation_m, 3))


def city_objects(num: int, extent_m: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``num`` labelled objects on a ground plane x-z (y = height, up = -y): positions, labels, sizes."""
    rng = np.random.default_rng(seed)
    xz = rng.uniform(0.0, extent_m, (num, 2))
    pos = np.stack([xz[:, 0], -rng.uniform(0.0, 5.0, num), xz[:, 1]], axis=1)
    return pos, rng.choice(CITY_LABELS, num, p=CITY_PROBS).astype(np.int64), rng.lognormal(7.0, 1.0, num)


def graph_of(pos: np.ndarray, labels: np.ndarray, sizes: np.ndarray, ids: np.ndarray, radius_m: float = 10.0):
    """GraphArrays with edges between nodes closer than ``radius_m``."""
    edges = cKDTree(pos).query_pairs(radius_m, output_type="ndarray").astype(np.int64).reshape(-1, 2)
    return GraphArrays(np.asarray(ids, np.int64), labels, pos, sizes, np.sort(edges, axis=1))


def city_pair(
    seed: int = 0,
    overlap: bool = True,
    num: int = 700,
    extent_m: float = 240.0,
    window_m: float = 120.0,
    noise_m: float = 0.3,
    drop: float = 0.15,
) -> tuple[GraphArrays, GraphArrays, np.ndarray]:
    """Two robots' graphs of one random city (overlapping windows) or of two different cities.

    Returns:
        (graph_a, graph_b, T_a_b) with B's positions in its own frame; ``T_a_b`` maps them into A's frame.
    """
    rng = np.random.default_rng(seed + 1000)
    pos_a, lab_a, size_a = city_objects(num, extent_m, seed)
    pos_b, lab_b, size_b = (pos_a, lab_a, size_a) if overlap else city_objects(num, extent_m, seed + 777)
    shift = np.array([0.4, 0.2]) * window_m if overlap else np.zeros(2)

    def inside(pos: np.ndarray, lo: np.ndarray) -> np.ndarray:
        xz = pos[:, [0, 2]]
        return np.all((xz >= lo) & (xz < lo + window_m), axis=1) & (rng.random(len(pos)) > drop)

    ia, ib = np.flatnonzero(inside(pos_a, np.zeros(2))), np.flatnonzero(inside(pos_b, shift))
    T_b_world = random_pose(rng, gravity_aligned=True)
    pa = pos_a[ia] + rng.normal(0.0, noise_m, (ia.size, 3))
    pb = (pos_b[ib] + rng.normal(0.0, noise_m, (ib.size, 3))) @ T_b_world[:3, :3].T + T_b_world[:3, 3]
    a = graph_of(pa, lab_a[ia], size_a[ia] * rng.uniform(0.5, 2.0, ia.size), ia)
    b = graph_of(pb, lab_b[ib], size_b[ib] * rng.uniform(0.5, 2.0, ib.size), ib + 100_000)
    return a, b, inverse(T_b_world)


def correspondence_problem(
    num_inliers: int,
    outlier_fraction: float,
    seed: int = 0,
    noise_m: float = 0.2,
    extent_m: float = 100.0,
    gravity_aligned: bool = False,
) -> dict[str, np.ndarray]:
    """Candidate correspondences with a known ``T_a_b``: inliers map exactly (plus noise), outliers not.

    Outliers pair random B points with random A points (distinct nodes), so their fraction of all
    candidates is ``outlier_fraction``.
    """
    rng = np.random.default_rng(seed)
    num_outliers = round(num_inliers * outlier_fraction / (1.0 - outlier_fraction))
    k = num_inliers + num_outliers
    T_a_b = random_pose(rng, gravity_aligned)
    points_b = rng.uniform(0.0, extent_m, (k, 3)) * [1.0, 0.1, 1.0]
    points_a = points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3] + rng.normal(0.0, noise_m, (k, 3))
    outlier = np.zeros(k, dtype=bool)
    outlier[rng.permutation(k)[:num_outliers]] = True
    points_a[outlier] = (rng.uniform(0.0, extent_m, (num_outliers, 3)) * [1.0, 0.1, 1.0]) @ T_a_b[:3, :3].T
    points_a[outlier] += T_a_b[:3, 3]
    return {
        "points_a": points_a,
        "points_b": points_b,
        "rows_a": rng.permutation(k).astype(np.int64),
        "rows_b": np.arange(k, dtype=np.int64),
        "inlier": ~outlier,
        "T_a_b": T_a_b,
    }
