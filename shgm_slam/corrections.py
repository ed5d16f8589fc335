"""Corrections that send only what changed: what a robot holds of its fused keyframe poses, and the
delta that brings it up to date.

A robot holds a ``FusedView``: per agent, its fused keyframe poses and ``T_shared_odom``, built from the
``CorrectionMessage``s it applied. The map server keeps the same ``FusedView`` per robot (what the
robot holds if it applied everything sent, in order: Zenoh delivers one publisher's messages in order)
and sends the agents' new keyframes plus those whose fused pose moved more than a tolerance since the
robot last got them (``changes``). When a closure moved much of an agent at once, it sends the rigid
motion that explains most of it (``T_move``, applied to everything the robot holds) and only the
keyframes that motion leaves beyond the tolerance. Corrections are numbered per robot session; a robot applies a
delta only on top of the one before it, so a lost message shows as a gap and the robot asks for a
full correction (``HelloMessage.resync``), as it gets one whenever it (re)connects. The final
correction is a full one: the robot ends with exactly the server's fused poses.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry.se3 import rotation_angle
from shgm_slam.messages import AgentCorrection, CorrectionMessage


class FusedView:
    """What one robot holds of its agents' places in the shared frame (see the module docstring)."""

    def __init__(self) -> None:
        self.seq = 0  # the last correction applied (0: none)
        self.T_shared_kf: dict[str, np.ndarray] = {}  # agent -> (K, 4, 4)
        self.T_shared_odom: dict[str, np.ndarray] = {}  # agent -> (4, 4)

    def apply(self, msg: CorrectionMessage) -> bool:
        """Apply one correction. Returns False when it cannot be applied (a delta that does not follow the
        last correction applied, or one that leaves a keyframe without a pose): ask for a full one.
        An acknowledgement alone (``seq`` 0) and a repeat of an applied correction change nothing."""
        if msg.seq == 0 or (not msg.full and msg.seq <= self.seq):
            return True
        if not msg.full and msg.seq != self.seq + 1:
            return False
        poses = {} if msg.full else dict(self.T_shared_kf)
        odom = {} if msg.full else dict(self.T_shared_odom)
        for agent, c in msg.agents.items():
            if c.T_shared_odom is None:
                poses.pop(agent, None)
                odom.pop(agent, None)
                continue
            held = poses.get(agent, np.zeros((0, 4, 4)))[: c.num_keyframes]
            if c.num_keyframes > len(held) + len(c.kf_indices):  # some keyframe would be left without a pose
                return False  # (checked before allocating: a peer's count may be 2^31)
            if c.T_move is not None:
                held = c.T_move @ held
            new = np.full((c.num_keyframes, 4, 4), np.nan)
            new[: len(held)] = held
            new[c.kf_indices] = c.T_shared_kf
            if np.isnan(new).any():
                return False
            poses[agent], odom[agent] = new, np.array(c.T_shared_odom, dtype=np.float64)
        self.T_shared_kf, self.T_shared_odom, self.seq = poses, odom, msg.seq
        return True

    def changes(
        self, current: dict[str, tuple[np.ndarray, np.ndarray] | None], tol_m: float, tol_rad: float, *, full: bool
    ) -> dict[str, AgentCorrection]:
        """What to send so this view matches ``current`` to within the tolerances.

        Args:
            current: agent -> ``(T_shared_odom (4, 4), T_shared_kf (K, 4, 4))`` now, or None when not placed.
            tol_m, tol_rad: a held keyframe is sent again once its position moved more than ``tol_m``
                metres or its orientation more than ``tol_rad`` radians (both 0: any change at all).
            full: send everything (a full correction), not only what changed.
        """
        out: dict[str, AgentCorrection] = {}
        for agent, now in current.items():
            held = None if full else self.T_shared_kf.get(agent)
            if now is None:
                if agent in self.T_shared_kf and not full:
                    out[agent] = AgentCorrection(None)
                continue
            T_odom, T_kf = now
            K = len(T_kf)
            T_move = None
            if held is None:
                idx = np.arange(K)
            else:
                n = min(len(held), K)
                moved = _moved(held[:n], T_kf[:n], tol_m, tol_rad)
                if moved.sum() > 1:  # a closure moved much of it: one rigid motion and what it does not explain
                    T_move, rest = rigid_motion(held[:n], T_kf[:n], tol_m, tol_rad)
                    T_move, moved = (T_move, rest) if rest.sum() + 1 < moved.sum() else (None, moved)
                idx = np.concatenate([np.flatnonzero(moved), np.arange(n, K)])
                same_odom = not _moved(self.T_shared_odom[agent][None], T_odom[None], tol_m, tol_rad)[0]
                if not idx.size and len(held) == K and same_odom:
                    continue
            out[agent] = AgentCorrection(np.array(T_odom, dtype=np.float64), K, idx.astype(np.int64), T_kf[idx], T_move)
        return out


MOTION_HYPOTHESES = 32
"""Keyframes whose own motion is tried as the rigid motion of an agent (besides the mean of all)."""


def rigid_motion(held: np.ndarray, now: np.ndarray, tol_m: float, tol_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion of the shared frame that moves most of the poses ``held`` (N, 4, 4) to within the
    tolerances of ``now`` (N, 4, 4), and which it leaves beyond them.

    Tried: the mean motion of all poses and the motions of up to ``MOTION_HYPOTHESES`` single keyframes
    (a closure bends a trajectory, so the mean alone is off where it bent); the one that explains most
    keyframes is refined as the mean over those it explains.

    Returns:
        ``T_move`` (4, 4) with ``T_move @ held ≈ now``, and (N,) bool: still beyond the tolerances.
    """
    picks = np.unique(np.linspace(0, len(held) - 1, min(len(held), MOTION_HYPOTHESES)).round().astype(int))
    hypotheses = [_mean_motion(held, now), *(now[picks] @ np.linalg.inv(held[picks]))]
    best, left = None, None
    for T in hypotheses:
        rest = _moved(T @ held, now, tol_m, tol_rad)
        if left is None or rest.sum() < left.sum():
            best, left = T, rest
    if (~left).sum() >= 2:
        T = _mean_motion(held[~left], now[~left])
        rest = _moved(T @ held, now, tol_m, tol_rad)
        if rest.sum() <= left.sum():
            best, left = T, rest
    return best, left


def _mean_motion(held: np.ndarray, now: np.ndarray) -> np.ndarray:
    """(4, 4) mean rigid motion from ``held`` to ``now`` (N, 4, 4): the chordal mean of the rotations
    ``R_now R_heldᵀ`` (orientations fix it on straight paths too), then the mean translation left."""
    R = np.einsum("nij,nkj->ik", now[:, :3, :3], held[:, :3, :3])
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (now[:, :3, 3] - held[:, :3, 3] @ R.T).mean(axis=0)
    return T


def _moved(held: np.ndarray, now: np.ndarray, tol_m: float, tol_rad: float) -> np.ndarray:
    """(N,) True where poses ``now`` (N, 4, 4) differ from ``held`` by more than the tolerances (any
    difference at all when both are 0)."""
    if tol_m == 0 and tol_rad == 0:
        return (held != now).any(axis=(1, 2))
    trans = np.linalg.norm(now[:, :3, 3] - held[:, :3, 3], axis=1) > tol_m
    rot = rotation_angle(np.swapaxes(held[:, :3, :3], 1, 2) @ now[:, :3, :3]) > tol_rad
    return trans | rot
