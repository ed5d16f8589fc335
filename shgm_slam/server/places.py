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
