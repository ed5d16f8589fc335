"""Evidence from different partners: a robot placed by independent matches with two placed robots.

A robot enters the shared frame once two independent pieces of evidence agree on its place
(``confirmation.py``). Within one robot pair that means two graph matches on disjoint objects and other
straight stretches. A robot whose overlap with each placed robot is short gets one piece from each and
never two from one: kitti00b cut from KITTI 00 (frames 3300-3800) shares 54 m of one straight street with
kitti00a and crosses kitti00c's track, so eight accepted matches with kitti00a were one piece, three with
kitti00c another, and it stayed unplaced although both agreed.

A *piece* is one accepted closure between the robot R and a placed partner P: where it puts R's keyframe k
in the shared frame, ``T_shared_Rk = T_shared_Pl · T_Pl_Rk`` (P's current fused pose). Pieces with
different partners are evidence that checks itself when they are

- **independent**: they rest on disjoint objects of R and on different straight stretches of R's
  trajectory (``backend/stretches.py``). An aliased street keeps aliasing along its length, and two
  partners that both mapped the street R's alias lands on would place R alike: only evidence from another
  part of R's own drive can contradict an alias;
- **in agreement**: the two poses of R's keyframes they imply differ by no more than R's odometry between
  those keyframes may have drifted (the loop-closure tolerance, ``consistency.consistent_with_odometry``,
  vectorised here).

Nothing here is tuned: the count is the anchoring threshold's ("two"), the tolerances are the consistency
thresholds of every other closure check.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from shgm_slam.backend.consistency import ConsistencyThresholds
from shgm_slam.geometry.se3 import inverse, rotation_angle

PIECES_PER_STRETCH = 4
"""Pieces kept per (partner, straight stretch of the robot), most inliers first (``strongest``): more pieces
from one partner on one stretch are not more independent evidence (the pair's own rule counts them once),
and the search is quadratic in the pieces (a robot that never joins can hold hundreds of closures)."""


def strongest(
    partners: Sequence[str], stretches: Sequence[int | None], inliers: Sequence[int], needed: int
) -> list[int]:
    """Indices of the pieces worth searching, given each one's partner, stretch of the robot (None: not
    tracked) and inliers: at most ``PIECES_PER_STRETCH`` per (partner, stretch), most inliers first (ties: the
    earlier index); [] when they cannot make ``needed`` independent pieces (fewer partners, or fewer stretches
    where stretches are tracked). Decided before any pose is read."""
    if len(set(partners)) < needed:
        return []
    tracked = [s for s in stretches if s is not None]
    if len(tracked) == len(stretches) and len(set(tracked)) < needed:
        return []
    kept: dict[tuple[str, int | None], int] = {}
    out = []
    for i in sorted(range(len(partners)), key=lambda i: (-inliers[i], i)):
        key = (partners[i], stretches[i])
        if kept.get(key, 0) < PIECES_PER_STRETCH:
            kept[key] = kept.get(key, 0) + 1
            out.append(i)
    return sorted(out)


@dataclass(frozen=True)
class Piece:
    """One accepted closure between a robot and a placed partner, seen from the robot.

    Attributes:
        closure_id: the closure.
        partner: the placed robot at its other end.
        kf: the robot's keyframe in it.
        T_shared_kf: (4, 4) the pose of that keyframe in the shared frame the closure implies.
        objects: the robot's own objects the closure rests on (empty: unknown, never shared).
        stretch: the straight stretch of the robot's trajectory the keyframe lies on (None: not tracked).
        inliers: matched objects behind it (ranks the pieces: the best-supported first).
    """

    closure_id: int
    partner: str
    kf: int
    T_shared_kf: np.ndarray
    objects: frozenset[Hashable]
    stretch: int | None
    inliers: int


def agreeing_pieces(
    pieces: Sequence[Piece],
    T_odom_kf: np.ndarray,
    path_m: np.ndarray,
    thresholds: ConsistencyThresholds,
    needed: int,
) -> list[Piece]:
    """``needed`` pieces with as many different partners, pairwise independent and in agreement (module
    docstring), or [] when there are none.

    Greedy from each piece in turn, best-supported first (most inliers, then the oldest closure): a seed
    collects the best piece of every other partner that is independent of and agrees with all collected so
    far. Deterministic for a given list.

    Args:
        pieces: the robot's pieces (any order).
        T_odom_kf: (K, 4, 4) the robot's keyframe poses in its odometry frame.
        path_m: (K,) its odometry path length at each keyframe, metres.
        thresholds: loop-error tolerances (``ConsistencyThresholds``).
        needed: pieces required (>= 2).
    """
    if needed < 2:
        raise ValueError(f"agreeing pieces need at least 2, got {needed}")
    order = sorted(pieces, key=lambda p: (-p.inliers, p.closure_id))
    if len({p.partner for p in order}) < needed:
        return []
    kfs = np.array([p.kf for p in order], dtype=np.int64)
    T_shared = np.stack([p.T_shared_kf for p in order])
    stretches = [p.stretch for p in order]
    for s in range(len(order)):
        agree = _agree_with(s, kfs, T_shared, T_odom_kf, path_m, thresholds)
        chosen = [s]
        for i in np.flatnonzero(agree).tolist():
            if all(_independent(order[i], order[j], stretches[i], stretches[j]) for j in chosen) and all(
                _agree_with(j, kfs, T_shared, T_odom_kf, path_m, thresholds)[i] for j in chosen[1:]
            ):
                chosen.append(i)
                if len(chosen) == needed:
                    return [order[j] for j in chosen]
    return []


def _independent(p: Piece, q: Piece, stretch_p: int | None, stretch_q: int | None) -> bool:
    """Different partners, disjoint objects of the robot, different stretches of its trajectory (when known)."""
    if p.partner == q.partner or p.objects & q.objects:
        return False
    return stretch_p is None or stretch_q is None or stretch_p != stretch_q


def _agree_with(
    s: int, kfs: np.ndarray, T_shared: np.ndarray, T_odom_kf: np.ndarray, path_m: np.ndarray,
    thresholds: ConsistencyThresholds,
) -> np.ndarray:  # fmt: skip
    """(P,) bool: piece i puts the robot where piece s does, up to the odometry drift between their keyframes.

    The loop ``E = (T_shared_s⁻¹ · T_shared_i) · (T_odom_i⁻¹ · T_odom_s)``: the relative pose of the two
    keyframes the pieces imply, against the robot's own odometry between them; its translation and rotation
    within ``trans_m + trans_per_m d`` and ``rot_deg + rot_deg_per_m d`` for ``d`` metres driven between them.
    """
    implied = inverse(T_shared[s]) @ T_shared  # (P, 4, 4) keyframe i in keyframe s's frame
    odometry = inverse(T_odom_kf[kfs]) @ T_odom_kf[kfs[s]]  # (P, 4, 4) keyframe s in keyframe i's frame
    E = implied @ odometry
    trans_m = np.linalg.norm(E[:, :3, 3], axis=1)
    rot_deg = np.degrees(rotation_angle(E))
    d = np.abs(path_m[kfs] - path_m[kfs[s]])
    return (trans_m <= thresholds.trans_m + thresholds.trans_per_m * d) & (
        rot_deg <= thresholds.rot_deg + thresholds.rot_deg_per_m * d
    )
