"""The pose graph's snapshot (``PoseGraphState``: what it decided, without its keyframes) and the check that
a snapshot fits itself and the keyframes it is restored with (``check_state``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.backend.consistency import PairVote
from shgm_slam.backend.records import ClosureRecord, ClosureStatus, Factorization
from shgm_slam.errors import BackendError


@dataclass(frozen=True, eq=False)
class PoseGraphState:
    """What a pose graph decided, without its keyframes (``MultiRobotPoseGraph.state``; a map server's
    snapshot): ``restore_state`` rebuilds iSAM2 from it and the keyframe poses in one batch.

    Attributes:
        robots: every robot in key order (the first defines the shared frame).
        anchors: anchored robot -> (closure id that anchored it or None for the first robot,
            ``T_shared_odom`` (4, 4) its keyframes were initialised with).
        T_shared_kf: anchored robot -> (K, 4, 4) current estimate (the restored graph starts there).
        closures: every closure with its status, reason and whether its factor is in iSAM2.
        information: (C, 6, 6) each closure's information matrix (gtsam order [rot, trans]).
        pairs: robot pair -> its consistency vote.
        rebuilds, recoveries: counters; factorization: the solver in use (QR after a recovery).
        up_odom: robot -> (K, 3) each keyframe's ground normal in its odometry frame (NaN rows: none
            measured); the attitude factors are rebuilt from them.
    """

    robots: tuple[str, ...]
    anchors: dict[str, tuple[int | None, np.ndarray]]
    T_shared_kf: dict[str, np.ndarray]
    closures: tuple[ClosureRecord, ...]
    information: np.ndarray
    pairs: dict[tuple[str, str], PairVote]
    rebuilds: int
    recoveries: int
    factorization: Factorization
    up_odom: dict[str, np.ndarray] = field(default_factory=dict)


def check_state(state: PoseGraphState, names: Sequence[str], counts: Mapping[str, int]) -> None:
    """``BackendError`` naming the first thing in ``state`` that does not fit itself or the keyframes.

    Args:
        state: the snapshot to restore.
        names: the graph's robots in key order (the first defines the shared frame).
        counts: robot -> how many keyframes it has been given.
    """
    count = dict(counts)
    index = {n: i for i, n in enumerate(names)}
    first = names[0]

    def fail(what: str) -> None:
        raise BackendError(f"pose graph state is inconsistent: {what}")

    if np.shape(state.information) != (len(state.closures), 6, 6):
        fail(f"{np.shape(state.information)} information matrices for {len(state.closures)} closures")
    for i, c in enumerate(state.closures):
        if c.closure_id != i or c.robot_a not in index or c.robot_b not in index:
            fail(f"closure {i} has id {c.closure_id} or unknown robots {c.robot_a}, {c.robot_b}")
        if not (0 <= c.kf_a < count[c.robot_a] and 0 <= c.kf_b < count[c.robot_b]):
            fail(f"closure {i} joins keyframes that do not exist")
        if (index[c.robot_a], c.kf_a) >= (index[c.robot_b], c.kf_b):
            fail(f"closure {i} is not in canonical order")
        if np.shape(c.T_a_b) != (4, 4) or not np.isfinite(c.T_a_b).all():
            fail(f"closure {i} has no finite (4, 4) pose")
        if c.in_graph and not (c.status is ClosureStatus.ACCEPTED and {c.robot_a, c.robot_b} <= set(state.anchors)):
            fail(f"closure {i} is in the graph but not accepted between anchored robots")
    if (first in state.anchors) != (count[first] > 0):
        fail(f"{first} (the shared frame) must be anchored exactly when it has keyframes")
    for name, (closure_id, T_init) in state.anchors.items():
        T = np.asarray(state.T_shared_kf.get(name, np.zeros(0)))
        if name not in count or T.shape != (count[name], 4, 4) or not np.isfinite(T).all():
            fail(f"anchored robot {name} has no finite estimate for each of its keyframes")
        if np.shape(T_init) != (4, 4) or (closure_id is None) != (name == first):
            fail(f"anchor of {name} is malformed")
        if closure_id is not None and not 0 <= closure_id < len(state.closures):
            fail(f"{name} is anchored by closure {closure_id}, which does not exist")
    for (a, b), v in state.pairs.items():
        ids = np.asarray(v.ids, dtype=np.int64)
        if a not in index or b not in index or ((ids < 0) | (ids >= len(state.closures))).any():
            fail(f"the vote of {a}-{b} names unknown robots or closures")
