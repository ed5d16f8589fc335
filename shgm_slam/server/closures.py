"""Closure cutting: one graph match becomes several keyframe-to-keyframe closures, each refitted locally.

A whole-graph transform averages over both robots' drift and is exact only near its inliers, so the
inliers are cut into stretches along robot a's graph and each stretch gets its own Eq. 2 refit.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry import se3
from shgm_slam.geometry.ground import rotation_to_z
from shgm_slam.labels import Label
from shgm_slam.matching.pose import spread_m

COMPACT_LABELS = (
    Label.POLE,
    Label.TRAFFIC_LIGHT,
    Label.TRAFFIC_SIGN,
    Label.VEGETATION,
    Label.CAR,
    Label.TRUCK,
    Label.BUS,
)
"""Classes whose object centroid does not depend on the viewpoint (unlike buildings or road patches)."""


def local_closures(
    pos_a: np.ndarray,
    pos_b: np.ndarray,
    labels: np.ndarray,
    anchors_a: np.ndarray,
    anchors_b: np.ndarray,
    T_a_b: np.ndarray,
    *,
    segment_m: float,
    min_inliers: int,
    max_rmse_m: float,
    up_a: np.ndarray | None,
    up_b: np.ndarray | None,
) -> list[tuple[int, int, np.ndarray, int, np.ndarray]]:
    """Cut one graph match into local closures ``(kf_a, kf_b, T_a_b_local, inliers, rows)``.

    Args:
        pos_a, pos_b: (M, 3) inlier node positions in robot a's / robot b's graph frame (metres).
        labels: (M,) inlier label ids.
        anchors_a, anchors_b: (M,) keyframe each inlier node is anchored to, in a's / b's graph.
        T_a_b: (4, 4) the whole match's transform (b's graph frame -> a's graph frame).
        segment_m: stretch length along a's graph (``backend.local_closure_m``).
        min_inliers: fewest inliers in a stretch that gives its own closure.
        max_rmse_m: a stretch whose refit leaves a larger RMS residual gives none.
        up_a, up_b: (3,) "up" in a's / b's graph frame when known (then refits are 4-DoF).

    Returns:
        Closures between the keyframes anchoring each stretch's central inlier, ``T_a_b_local`` in the
        graph frames (b -> a), with the (n,) indices into the M inliers that support it; without any
        good stretch, one closure at the centre with ``T_a_b``, supported by all inliers.
    """
    order = np.argsort(anchors_a, kind="stable")
    groups: list[np.ndarray] = []
    start = 0
    for i in range(1, len(order) + 1):
        if i == len(order) or np.linalg.norm(pos_a[order[i]] - pos_a[order[start]]) > segment_m:
            groups.append(order[start:i])
            start = i
    out = []
    for g in groups:
        if len(g) < min_inliers or spread_m(pos_a[g]) < 0.25 * segment_m:
            continue
        T_local = refit(pos_a[g], pos_b[g], labels[g], up_a, up_b)
        resid = np.linalg.norm(se3.transform_points(T_local, pos_b[g]) - pos_a[g], axis=1)
        if np.sqrt(np.mean(resid**2)) > max_rmse_m:
            continue
        c = g[int(np.argmin(np.linalg.norm(pos_a[g] - pos_a[g].mean(axis=0), axis=1)))]
        out.append((int(anchors_a[c]), int(anchors_b[c]), T_local, len(g), np.sort(g)))
    if not out:
        c = int(np.argmin(np.linalg.norm(pos_a - pos_a.mean(axis=0), axis=1)))
        out.append((int(anchors_a[c]), int(anchors_b[c]), T_a_b, len(pos_a), np.arange(len(pos_a))))
    return out


def refit(
    pos_a: np.ndarray, pos_b: np.ndarray, labels: np.ndarray, up_a: np.ndarray | None, up_b: np.ndarray | None
) -> np.ndarray:
    """Eq. 2 refit of ``T_a_b`` (4, 4; b's graph frame -> a's) to matched positions (M, 3) each.

    Compact objects (poles, lights, signs, trees, vehicles) have centroids that do not depend on the
    viewpoint, unlike buildings or road patches seen from different sides, so they alone are used
    when there are at least 4. With both robots' "up" known the fit is 4-DoF (yaw + translation).
    """
    compact = np.isin(labels, COMPACT_LABELS)
    if compact.sum() >= 4:
        pos_a, pos_b = pos_a[compact], pos_b[compact]
    if up_a is None or up_b is None:
        return se3.kabsch(pos_b, pos_a)
    R_a, R_b = rotation_to_z(up_a), rotation_to_z(up_b)
    T_g = se3.kabsch_yaw(pos_b @ R_b.T, pos_a @ R_a.T)
    return se3.make_pose(R_a.T, np.zeros(3)) @ T_g @ se3.make_pose(R_b, np.zeros(3))
