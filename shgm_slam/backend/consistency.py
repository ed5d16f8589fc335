"""Pairwise consistency of inter-robot closures and their maximum consistent set (PCM-style).

Two closures between the same robots, ``T_ai_bj`` (keyframe i of robot a to keyframe j of b) and
``T_ak_bl``, are consistent when the loop they close with both robots' odometry is near identity:

    E = T_ai_bj · T_bj_bl · T_bl_ak · T_ak_ai ≈ I,   T_bj_bl, T_ak_ai from odometry, T_bl_ak = T_ak_bl⁻¹.

The tolerances grow with the odometry distance inside the loop (drift). Correct closures agree with
each other; wrong ones (perceptual aliasing) agree with nothing in particular, so the largest
mutually consistent subset (a maximum clique of the consistency graph) is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.geometry.se3 import inverse, rotation_angle

CLIQUE_BUDGET = 200_000
"""Branch-and-bound expansions before ``max_consistent_set`` returns the best set found so far."""


@dataclass(frozen=True)
class ConsistencyThresholds:
    """Loop-error tolerances: ``trans_m + trans_per_m·d`` metres, ``rot_deg + rot_deg_per_m·d`` degrees.

    ``d`` is the odometry path length inside the loop (both robots, metres).
    """

    trans_m: float = 5.0
    rot_deg: float = 10.0
    trans_per_m: float = 0.05
    rot_deg_per_m: float = 0.05


def loop_errors(
    T_ai_bj: np.ndarray,
    T_ak_bl: np.ndarray,
    T_ak_ai: np.ndarray,
    T_bj_bl: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) error of the loop closed by two closures and odometry.

    Args:
        T_ai_bj: (4, 4) first closure.
        T_ak_bl: (M, 4, 4) second closures.
        T_ak_ai: (M, 4, 4) odometry of robot a from keyframe i to k (``inv(T_odom_ak) @ T_odom_ai``).
        T_bj_bl: (M, 4, 4) odometry of robot b from keyframe j to l (``inv(T_odom_bj) @ T_odom_bl``).

    Returns:
        trans_m (M,), rot_deg (M,) of ``E = T_ai_bj · T_bj_bl · T_ak_bl⁻¹ · T_ak_ai``.
    """
    E = np.asarray(T_ai_bj, dtype=np.float64) @ T_bj_bl @ inverse(T_ak_bl) @ T_ak_ai
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angle(E))


def consistent_with(
    T_ai_bj: np.ndarray,
    kf_a: int,
    kf_b: int,
    others_T_a_b: np.ndarray,
    others_kf_a: np.ndarray,
    others_kf_b: np.ndarray,
    T_odom_a: np.ndarray,
    T_odom_b: np.ndarray,
    path_a_m: np.ndarray,
    path_b_m: np.ndarray,
    thresholds: ConsistencyThresholds,
) -> np.ndarray:
    """Which of M earlier closures between robots a and b agree with a new closure.

    Args:
        T_ai_bj: (4, 4) new closure from b's keyframe ``kf_b`` into a's keyframe ``kf_a``.
        others_T_a_b: (M, 4, 4) earlier closures ``T_ak_bl``; others_kf_a, others_kf_b: (M,) their k, l.
        T_odom_a, T_odom_b: (Ka, 4, 4), (Kb, 4, 4) keyframe poses in each robot's odometry frame.
        path_a_m, path_b_m: (Ka,), (Kb,) cumulative odometry path length at each keyframe, metres.
        thresholds: loop-error tolerances.

    Returns:
        (M,) bool, True where the loop error is within the distance-dependent tolerance.
    """
    k = np.asarray(others_kf_a, dtype=np.int64)
    l = np.asarray(others_kf_b, dtype=np.int64)
    if k.size == 0:
        return np.zeros(0, dtype=bool)
    T_ak_ai = inverse(T_odom_a[k]) @ T_odom_a[kf_a]
    T_bj_bl = inverse(T_odom_b[kf_b]) @ T_odom_b[l]
    trans_m, rot_deg = loop_errors(T_ai_bj, np.asarray(others_T_a_b, dtype=np.float64), T_ak_ai, T_bj_bl)
    d = np.abs(path_a_m[k] - path_a_m[kf_a]) + np.abs(path_b_m[l] - path_b_m[kf_b])
    return (trans_m <= thresholds.trans_m + thresholds.trans_per_m * d) & (
        rot_deg <= thresholds.rot_deg + thresholds.rot_deg_per_m * d
    )


def max_consistent_set(
    adjacency: np.ndarray, weights: np.ndarray | None = None, preferred: np.ndarray | None = None
) -> np.ndarray:
    """Maximum clique of a consistency graph, ties broken for stability and evidence.

    Among the cliques of maximum size, the one with the most ``preferred`` members wins (keeps the
    established set when new evidence is only a tie), then the largest total weight, then the one
    with the earliest members.

    Args:
        adjacency: (n, n) symmetric bool, True where two closures are consistent (diagonal ignored).
        weights: (n,) non-negative evidence per closure (e.g. inlier counts); ones when None.
        preferred: (n,) bool, the currently accepted closures; none when None.

    Returns:
        Sorted int64 indices of the chosen clique (empty only for n = 0). Exact up to
        ``CLIQUE_BUDGET`` expansions, after that the best clique found so far.
    """
    A = np.asarray(adjacency, dtype=bool)
    n = A.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    pref = np.zeros(n, dtype=bool) if preferred is None else np.asarray(preferred, dtype=bool)
    nbr = [sum(1 << int(j) for j in np.flatnonzero(A[i])) & ~(1 << i) for i in range(n)]

    def members(bits: int) -> list[int]:
        return [i for i in range(n) if bits >> i & 1]

    def score(bits: int) -> tuple:
        m = members(bits)
        return (len(m), int(pref[m].sum()), float(w[m].sum()), [-i for i in m])

    best = [0, score(0)]
    budget = [CLIQUE_BUDGET]

    def expand(R: int, P: int, X: int) -> None:
        # Bron-Kerbosch with pivoting; prune branches that cannot reach the best size
        if budget[0] <= 0 or R.bit_count() + P.bit_count() < best[1][0]:
            return
        budget[0] -= 1
        if P == 0 and X == 0:
            s = score(R)
            if s > best[1]:
                best[:] = [R, s]
            return
        pivot = max(members(P | X), key=lambda u: (P & nbr[u]).bit_count())
        for v in members(P & ~nbr[pivot]):
            expand(R | 1 << v, P & nbr[v], X & nbr[v])
            P &= ~(1 << v)
            X |= 1 << v

    expand(0, (1 << n) - 1, 0)
    return np.array(members(best[0]), dtype=np.int64)
