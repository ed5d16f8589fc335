"""Candidate places: the part of an agent's graph a query can overlap, so matching cost stays flat.

A query (a robot's submap: its recent keyframes and their nodes) is matched against the nodes of another
graph anchored to keyframes that could see the same objects. Two keyframes see a common object only if
they are within ``reach`` of each other (each object lies within its robot's object range of the keyframe
that anchors it). Where the two keyframes *are* is known up to the drift between them: the tolerance of
the pose graph's own consistency checks (``ConsistencyThresholds``: ``trans_m + trans_per_m · d``, with
``d`` the metres of odometry the error can have accumulated over). A keyframe farther from every query
keyframe than ``reach + tolerance`` cannot give a closure the pose graph would accept, so its nodes are
left out of the match. How ``d`` is counted (``free_path_m``): along one robot's own odometry, the path
between the two keyframes (the loop-closure test); in the fused estimate, the path from each keyframe to
the nearest keyframe a closure ties to the shared frame (between such keyframes the closures bound the
drift).
"""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.consistency import ConsistencyThresholds


def free_path_m(path_m: np.ndarray, constrained: np.ndarray) -> np.ndarray:
    """(K,) metres of path from each keyframe to the nearest ``constrained`` keyframe (inf: none).

    Args:
        path_m: (K,) cumulative odometry path length at each keyframe, metres (non-decreasing).
        constrained: (C,) indices of the keyframes a closure (or the prior) ties to the shared frame.
    """
    path_m = np.asarray(path_m, dtype=np.float64)
    c = np.unique(np.asarray(constrained, dtype=np.int64))
    c = c[(c >= 0) & (c < path_m.size)]
    if c.size == 0:
        return np.full(path_m.size, np.inf)
    at = path_m[c]
    right = np.searchsorted(at, path_m).clip(0, at.size - 1)
    left = (right - 1).clip(0)
    return np.minimum(np.abs(path_m - at[left]), np.abs(path_m - at[right]))


def tolerance_m(drift_path_m: np.ndarray, thresholds: ConsistencyThresholds) -> np.ndarray:
    """Position tolerance (m) after ``drift_path_m`` metres of drift (any shape): the pose graph's own."""
    return thresholds.trans_m + thresholds.trans_per_m * np.asarray(drift_path_m, dtype=np.float64)


def near_keyframes(
    query_xyz: np.ndarray, cand_xyz: np.ndarray, tol_m: np.ndarray, reach_m: float
) -> np.ndarray:
    """(K,) bool: candidate keyframes within ``reach_m + tol_m`` of at least one query keyframe.

    Args:
        query_xyz: (Q, 3) query keyframe positions; cand_xyz: (K, 3) candidate keyframe positions (one frame).
        tol_m: (Q, K) (or broadcastable) position tolerance of each pair, metres (inf: always near).
        reach_m: how far apart two keyframes can be and still see one object, metres.
    """
    q = np.asarray(query_xyz, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(cand_xyz, dtype=np.float64).reshape(-1, 3)
    if q.shape[0] == 0 or c.shape[0] == 0:
        return np.zeros(c.shape[0], dtype=bool)
    d = np.linalg.norm(q[:, None, :] - c[None, :, :], axis=2)
    return (d <= reach_m + np.broadcast_to(tol_m, d.shape)).any(axis=0)


def rows_near(
    anchors_a: np.ndarray, xyz_a: np.ndarray, free_a: np.ndarray, xyz_b: np.ndarray, free_b: np.ndarray,
    reach_m: float, thresholds: ConsistencyThresholds,
) -> np.ndarray:  # fmt: skip
    """Rows of placed robot a's graph anchored near placed robot b's query keyframes in the fused estimate:
    within both object ranges (``reach_m``) plus the drift tolerance (``free_path_m`` of both sides).

    Args:
        anchors_a: (N,) keyframe each node of a's graph is anchored to (row order of the graph).
        xyz_a: (K_a, 3) a's keyframe positions in the shared frame (fused estimate), metres.
        free_a: (K_a,) ``free_path_m`` of a's keyframes, metres.
        xyz_b: (Q, 3) b's query keyframe positions in the shared frame, metres.
        free_b: (Q,) ``free_path_m`` of those keyframes, metres.
        reach_m: the sum of the two robots' object ranges, metres.
        thresholds: the pose graph's consistency thresholds.

    Returns:
        (M,) int row indices of a's graph, ascending.
    """
    tol = tolerance_m(free_b[:, None] + free_a[None, :], thresholds)
    near = near_keyframes(xyz_b, xyz_a, tol, reach_m)
    return np.flatnonzero(near[anchors_a])


def loop_near(
    xyz: np.ndarray, path_m: np.ndarray, free_m: np.ndarray | None, kfs: np.ndarray, cutoff: int, reach_m: float,
    thresholds: ConsistencyThresholds,
) -> np.ndarray:  # fmt: skip
    """(K,) bool: a robot's keyframes before ``cutoff`` near its query keyframes ``kfs`` (a loop closure's
    candidates): within ``reach_m`` plus the drift tolerance, counted along the robot's odometry between the
    two keyframes (exactly what the pose graph's odometry check of a loop closure allows) or, once the robot
    is placed (``free_m``), from each to its nearest keyframe tied by a closure, whichever is shorter.

    Args:
        xyz: (K, 3) keyframe positions: the fused estimate once placed, else the odometry frame, metres.
        path_m: (K,) cumulative odometry path length at each keyframe, metres.
        free_m: (K,) ``free_path_m`` of each keyframe once the robot is placed, else None.
        kfs: (Q,) the query keyframes; cutoff: keyframes from here on are never candidates.
        reach_m: how far apart two keyframes can be and still see one object, metres.
        thresholds: the pose graph's consistency thresholds.
    """
    d_path = np.abs(path_m[kfs][:, None] - path_m[None, :cutoff])
    if free_m is not None:
        d_path = np.minimum(d_path, free_m[kfs][:, None] + free_m[None, :cutoff])
    near = np.zeros(len(path_m), dtype=bool)
    near[:cutoff] = near_keyframes(xyz[kfs], xyz[:cutoff], tolerance_m(d_path, thresholds), reach_m)
    return near
