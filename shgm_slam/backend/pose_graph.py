"""Multi-robot pose graph on iSAM2: odometry chains, robust inter-robot closures, deferred anchoring.

The shared frame is the odometry frame of the first robot (index 0): its first keyframe gets a tight
prior. Every other robot starts *unanchored*: its keyframes are only recorded (no variables, no
factors) until an accepted closure connects it to an anchored robot. Then the robot's odometry frame
is placed by that closure,

    T_shared_odomB = T_shared_ai · T_ai_bj · T_odomB_bj⁻¹,

all its keyframes are inserted as ``T_shared_odomB · T_odomB_bk`` with their odometry factors, and
every accepted closure to an anchored robot is pushed (REFERENCE.md §3, deferred initialisation: no
gauge prior, so CHOLESKY never meets an indeterminate system). Closures between two unanchored robots
are kept and replayed as soon as one of them is anchored (anchoring spreads through accepted closures).

Loop closures (intra-robot: two keyframes of the same robot) go through the same path: canonical order
older keyframe first, a consistency vote of their own (the pair ``(robot, robot)``), the robust kernel.
Each is first checked against the robot's own odometry between its two keyframes (the loop it closes
with the odometry alone, ``consistent_with_odometry``), and it never anchors a robot: it enters
iSAM2 once its robot is anchored, like a closure between two anchored robots.

Closures between the same two robots are checked for pairwise consistency (``consistency.py``); only
the maximum consistent set is accepted. It is maintained incrementally per robot pair
(``PairConsistency``: O(n) per closure, a bounded search only when a larger set may have formed) over
at most ``max_closures_per_pair`` voting closures. When a later, larger consistent set outvotes earlier closures,
those are removed from iSAM2 (``removeFactorIndices``); if a removed closure was the one that anchored
a robot, the graph is rebuilt from the recorded odometry and the accepted closures, so one wrong first
match cannot leave a robot in the wrong place. Accepted closures additionally carry a robust kernel.

Attitude (``attitude``): each keyframe that measured its ground plane (``up_odom``: the plane's normal in
its odometry frame) gets a unary ``AttitudeFactorPose3`` once its robot is anchored: the normal in the
camera frame, rotated by the keyframe's estimated orientation, should point along the shared frame's up,
with a Huber kernel and the robot's own measured sigma (``attitude.normal_sigma_rad``, from its first
``attitude_warmup`` measured keyframes; none before). The shared frame's up comes from the first anchored
robot's first ``attitude_warmup`` measurements, rotated into the shared frame and weighed against the
odometry's drift since its first keyframe (``attitude.up_at_start``), and is then fixed: unary factors
keep the cost of an update flat, where a shared "gravity" variable tied to every keyframe made each
update cost O(keyframes). This stops roll and pitch from drifting with the odometry, and the height
error that pitch drift integrates; it assumes level ground (see ``attitude.py``).

Numerics: iSAM2 factorizes with QR by default. With CHOLESKY, a long straight chain with the default
sigmas raised ``IndeterminateSystem`` after ~1100 keyframes: the root clique's information couples
rotation and translation through a lever arm as long as the chain, and gtsam's partial Cholesky
declares a system indeterminate when consecutive diagonal entries of its factor differ by 2^12 or
more; QR works on the square-root information and has no such test. Should an update raise anyway,
the graph is rebuilt with QR from the recorded keyframes and accepted closures (a logged warning);
only when that fails too is ``BackendError`` raised. Relinearization checks only the part of the
Bayes tree an update touches, so adding a keyframe costs about the same at 5000 keyframes as at 1000.

``estimate()`` is cached until the next change of the graph (a version counter), so callers that
ask for poses per keyframe do not pay a full recomputation each time.

Beside this module: the plain records it answers with (``records.py``), its snapshot and the check of
one (``state.py``), each robot's recorded keyframes (``track.py``), the GTSAM noise models, poses and
iSAM2 parameters (``factors.py``), the iSAM2 instance with its pending factors, removals and recovery
(``isam.py``) and the g2o export (``g2o.py``).
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Hashable, Iterable, Mapping
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np

from shgm_slam.backend import g2o
from shgm_slam.backend.attitude import normal_sigma_rad, up_at_start
from shgm_slam.backend.consistency import (
    MAX_CLOSURES_PER_PAIR,
    ConsistencyThresholds,
    PairConsistency,
    consistent_with,
    consistent_with_odometry,
)
from shgm_slam.backend.cross_evidence import Piece, agreeing_pieces, strongest
from shgm_slam.backend.drift import closure_rate, drift_level, loop_rotation_error_rad, measured_rate
from shgm_slam.backend.factors import (
    PRIOR_SIGMA,
    RELINEARIZE_ROT_RAD,
    RELINEARIZE_TRANS_M,
    attitude_noise,
    check_pose,
    closure_noise_model,
    inverse_information,
    odometry_noise,
    pose3,
    prior_noise,
    sigmas6,
)
from shgm_slam.backend.isam import IncrementalSolver, poses_by_key
from shgm_slam.backend.keys import ROBOT_LETTERS, RobotKeys
from shgm_slam.backend.records import (
    Anchor,
    ClosureDecision,
    ClosureRecord,
    ClosureStatus,
    Factorization,
    PoseGraphStats,
)
from shgm_slam.backend.state import PoseGraphState, check_state
from shgm_slam.backend.stretches import StretchTracker, stretch_token
from shgm_slam.backend.track import RobotTrack
from shgm_slam.config import BackendConfig, RobustKernel
from shgm_slam.errors import BackendError
from shgm_slam.geometry.se3 import inverse

__all__ = [
    "PRIOR_SIGMA",
    "RELINEARIZE_ROT_RAD",
    "RELINEARIZE_TRANS_M",
    "Anchor",
    "ClosureDecision",
    "ClosureRecord",
    "ClosureStatus",
    "Factorization",
    "MultiRobotPoseGraph",
    "PoseGraphState",
    "PoseGraphStats",
    "make_pose_graph",
]  # the pose graph, and the records and constants callers use with it (re-exported: importable from here)


class MultiRobotPoseGraph:
    """iSAM2 pose graph of several robots' keyframes in one shared frame (robot 0's odometry frame).

    Args:
        robot_names: the robots, in order; the first one defines the shared frame.
        odometry_sigmas: (rotation rad, translation m) sigma of one keyframe-to-keyframe odometry step
            that did not move (the floor).
        odometry_drift: (rotation rad per metre, translation per metre) growth of those sigmas with the
            step's length: odometry drifts with distance driven, so a 2 m step is twice as uncertain as
            a 1 m one (0, 0: every step alike).
        closure_sigmas: (rotation rad, translation m) sigma of an inter-robot closure.
        robust_kernel: M-estimator on closures (string values accepted); ``kernel_width`` overrides
            its default width (Huber 1.345, Cauchy 1.0, Tukey 4.685, in sigmas).
        consistency_*: pairwise-consistency tolerances (``ConsistencyThresholds``).
        min_closures_to_anchor: a robot is anchored through a robot pair only when that pair's
            consistent set holds closures from at least this many independent sources (matches that rest
            on mutually disjoint objects, ``consistency.independent_sources``; 1 = trust a single first
            match).
        stretch_turn_deg: when set, matches on the same straight stretches of both robots count as one
            source too: each inter-robot closure with a ``support`` also rests on the pair of stretches its
            keyframes lie on (``stretches``; a stretch ends where the direction of travel turns more than
            this many degrees). None: objects alone decide.
        factorization: iSAM2 linear solver.
        relinearize_threshold: (rotation rad, translation m): iSAM2 relinearizes a keyframe whose pending
            update exceeds either in any axis (``RELINEARIZE_ROT_RAD``, ``RELINEARIZE_TRANS_M``).
        extra_updates: additional ``isam.update()`` passes after a large correction (``update``).
        attitude: attitude factors from the keyframes' ground normals (module docstring).
        attitude_warmup: measured keyframes a robot needs before its sigma is measured (and the first
            anchored one's before the shared frame's up is fixed).
        max_closures_per_pair: closures of one robot pair that vote on its consistent set; beyond
            it the oldest closure outside the set (else the oldest in it) leaves the vote and keeps
            its status (``PairConsistency``).
    """

    def __init__(
        self,
        robot_names: list[str],
        *,
        odometry_sigmas: tuple[float, float] = (0.01, 0.1),
        odometry_drift: tuple[float, float] = (0.0, 0.0),
        closure_sigmas: tuple[float, float] = (0.05, 1.0),
        robust_kernel: RobustKernel | str = RobustKernel.CAUCHY,
        kernel_width: float | None = None,
        consistency_trans_m: float = 5.0,
        consistency_rot_deg: float = 10.0,
        consistency_trans_per_m: float = 0.05,
        consistency_rot_deg_per_m: float = 0.05,
        min_closures_to_anchor: int = 1,
        stretch_turn_deg: float | None = None,
        factorization: Factorization | str = Factorization.QR,
        relinearize_threshold: tuple[float, float] = (RELINEARIZE_ROT_RAD, RELINEARIZE_TRANS_M),
        extra_updates: int = 3,
        attitude: bool = True,
        attitude_warmup: int = 20,
        max_closures_per_pair: int = MAX_CLOSURES_PER_PAIR,
    ) -> None:
        self.keys = RobotKeys(robot_names)
        try:
            self.robust_kernel = RobustKernel(robust_kernel)
            factorization = Factorization(str(getattr(factorization, "value", factorization)).upper())
        except ValueError as exc:
            raise BackendError(f"pose graph: {exc}; robust kernels: none, huber, cauchy, tukey") from None
        self._odometry_floor = sigmas6(odometry_sigmas)
        drift = np.asarray(odometry_drift, dtype=np.float64)
        if drift.shape != (2,) or not np.isfinite(drift).all() or (drift < 0).any():
            raise BackendError(f"odometry drift must be two non-negative rates, got {odometry_drift}")
        self._odometry_drift = np.r_[[drift[0]] * 3, [drift[1]] * 3]
        self._closure_sigmas = sigmas6(closure_sigmas)
        self._kernel_width = kernel_width
        self.thresholds = ConsistencyThresholds(
            consistency_trans_m, consistency_rot_deg, consistency_trans_per_m, consistency_rot_deg_per_m
        )
        if min_closures_to_anchor < 1:
            raise BackendError(f"min_closures_to_anchor must be >= 1, got {min_closures_to_anchor}")
        self.min_closures_to_anchor = min_closures_to_anchor
        if stretch_turn_deg is not None and not 0 < stretch_turn_deg <= 180:
            raise BackendError(f"stretch_turn_deg must be in (0, 180] degrees, got {stretch_turn_deg}")
        self._stretch_turn_rad = None if stretch_turn_deg is None else math.radians(stretch_turn_deg)
        if max_closures_per_pair < 1:
            raise BackendError(f"max_closures_per_pair must be >= 1, got {max_closures_per_pair}")
        self.max_closures_per_pair = max_closures_per_pair
        threshold = np.asarray(relinearize_threshold, dtype=np.float64)
        if threshold.shape != (2,) or not np.isfinite(threshold).all() or (threshold <= 0).any():
            raise BackendError(
                f"relinearize_threshold must be two positive values (rad, m), got {relinearize_threshold}"
            )
        relinearize_threshold = (float(threshold[0]), float(threshold[1]))
        if attitude_warmup < 2:
            raise BackendError(f"attitude_warmup must be >= 2 (a sigma needs pairs), got {attitude_warmup}")
        self.attitude = attitude
        self.attitude_warmup = attitude_warmup
        self._up_shared: np.ndarray | None = None  # the shared frame's up, fixed once measured
        self._attitude_factors = 0
        self._robots = {name: self._new_robot(i) for i, name in enumerate(self.keys.names)}
        self._closures: list[ClosureRecord] = []
        self._support: dict[int, frozenset] = {}  # closure id -> the objects it rests on (when given)
        self._loop_rates: dict[int, float] = {}  # loop closure id -> its drift rate (``_loop_rate``)
        self._closure_noise: list[gtsam.noiseModel.Base] = []
        self._information: list[np.ndarray] = []  # 6x6 [rot, trans] information, for g2o export
        self._pairs: dict[tuple[str, str], PairConsistency] = {}
        self._rebuilds = 0
        self._recoveries = 0
        self._anchorings: list[tuple[str, int]] = []  # (robot, closure id) each time a robot was anchored
        self._last_update_ms = 0.0
        self._version = 0  # bumped on every change of the graph; keys the estimate cache
        self._corrections = 0  # bumped when closures enter or leave iSAM2, a robot is anchored, or a rebuild
        self._large_correction = False  # pending changes need the extra relinearization passes
        self._cache_version = -1
        self._cache: dict[str, np.ndarray] = {}
        self._converged: tuple[int, gtsam.Values] | None = None  # (version, solution) of ``converge``
        self._solver = IncrementalSolver(factorization, relinearize_threshold, extra_updates)
        self._version += 1  # a fresh iSAM2 (as ``_reset_isam``)

    @property
    def factorization(self) -> Factorization:
        """iSAM2's linear solver now (QR after a recovery, module docstring)."""
        return self._solver.factorization

    @property
    def relinearize_threshold(self) -> tuple[float, float]:
        """(rotation rad, translation m) iSAM2's relinearization thresholds."""
        return self._solver.relinearize_threshold

    @property
    def extra_updates(self) -> int:
        """Additional ``isam.update()`` passes after a large correction (``update``)."""
        return self._solver.extra_updates

    # --- public API ---------------------------------------------------------------------------------

    def add_keyframe(
        self, robot: str, kf_index: int, T_odom_kf: np.ndarray, up_odom: np.ndarray | None = None
    ) -> None:
        """Add keyframe ``kf_index`` (0, 1, 2, ... per robot) with its pose in the robot's odometry frame.

        Anchored robots get the odometry factor (and robot 0's first keyframe the prior) in iSAM2
        right away; keyframes of unanchored robots are recorded until the robot is anchored.
        ``up_odom`` (3,) is the keyframe's measured ground normal (unit, pointing up) in the robot's
        odometry frame, or None; it becomes an attitude factor (module docstring).

        Raises:
            BackendError: unknown robot, a keyframe index out of order, a non-finite pose or normal.
        """
        r = self._robot(robot)
        T = check_pose(T_odom_kf, f"keyframe {kf_index} of {robot}")
        if up_odom is not None:
            up_odom = np.asarray(up_odom, dtype=np.float64)
            norm = float(np.linalg.norm(up_odom)) if up_odom.shape == (3,) else 0.0
            if not (np.isfinite(up_odom).all() and norm > 0):
                raise BackendError(f"up_odom of keyframe {kf_index} of {robot} must be a finite non-zero (3,) vector")
            up_odom = up_odom / norm
        if kf_index != len(r.T_odom_kf):
            raise BackendError(
                f"keyframe {kf_index} of {robot} is out of order: expected keyframe {len(r.T_odom_kf)} "
                "(keyframes are numbered 0, 1, 2, ... per robot)"
            )
        r.append(T, up_odom)
        self._version += 1
        if r.index == 0 and kf_index == 0:
            self._anchor_first_robot()
            self._sync()
        elif r.anchored:
            self._push_keyframe(robot, kf_index)
            self._push_attitudes()
        self._flush()

    def add_inter_robot_closure(
        self,
        robot_a: str,
        kf_a: int,
        robot_b: str,
        kf_b: int,
        T_akf_bkf: np.ndarray,
        *,
        num_inliers: int = 1,
        information: np.ndarray | None = None,
        match_id: int | None = None,
        support: Iterable[Hashable] = (),
        decisive: bool = False,
        update: bool = True,
    ) -> ClosureDecision:
        """Add a relative-pose measurement between keyframes of two robots, or two keyframes of one robot.

        With ``robot_a == robot_b`` it is a loop closure (see ``add_loop_closure``): it must also agree
        with the robot's own odometry between the two keyframes (drift-dependent tolerance), it votes
        in the robot's own consistency set and it never anchors the robot.

        Args:
            robot_a, kf_a, robot_b, kf_b: the two keyframes (already added with ``add_keyframe``).
            T_akf_bkf: (4, 4) pose of b's keyframe camera in a's keyframe camera frame.
            num_inliers: evidence behind the closure (matched objects); breaks ties between
                equally large consistent sets.
            information: optional (6, 6) information matrix in gtsam order [rot, trans]; the
                configured closure sigmas otherwise.
            match_id: the graph match the closure was cut from; closures of one match count as one
                source of evidence for ``min_closures_to_anchor`` (None: the closure is its own source).
            support: the objects the closure rests on (hashable, e.g. ``(robot, node id)``); two matches
                whose closures share one are not independent evidence (``consistency.independent_sources``).
            decisive: the closure's match alone carries as much evidence as ``min_closures_to_anchor``
                independent ones (the map server decides, ``MapServer._decisive``): once accepted, it anchors
                a robot by itself (never a loop closure); the place stays provisional until confirmed.
            update: run iSAM2 now; False leaves the factor pending until ``update`` (add the closures of
                one match, then update once: one re-elimination instead of one per closure).

        Returns:
            ``ClosureDecision``: accepted when the closure is in its robot pair's maximum consistent
            set. The reason says why, and whether the closure waits for an anchored robot.

        Raises:
            BackendError: unknown robots, a keyframe closed with itself, a keyframe not added yet, bad
                matrices.
        """
        ia, ib = self.keys.index(robot_a), self.keys.index(robot_b)
        if ia == ib and kf_a == kf_b:
            raise BackendError(f"closure between keyframe {kf_a} of {robot_a} and itself")
        T = check_pose(T_akf_bkf, f"closure {robot_a}{kf_a}-{robot_b}{kf_b}")
        for name, kf in ((robot_a, kf_a), (robot_b, kf_b)):
            if not 0 <= kf < len(self._robots[name].T_odom_kf):
                raise BackendError(
                    f"closure refers to keyframe {kf} of {name}, which has only "
                    f"{len(self._robots[name].T_odom_kf)} keyframes; add keyframes before closures"
                )
        querier = robot_b
        if ia > ib or (ia == ib and kf_a > kf_b):  # canonical order: lower robot index, older keyframe first
            robot_a, kf_a, robot_b, kf_b, T = robot_b, kf_b, robot_a, kf_a, inverse(T)
            if information is not None:
                information = inverse_information(information, T)
        noise, info = self._closure_noise_model(information)
        rec = ClosureRecord(
            len(self._closures), robot_a, kf_a, robot_b, kf_b, T, int(num_inliers), match_id=match_id, querier=querier,
            decisive=bool(decisive) and robot_a != robot_b,
        )
        self._closures.append(rec)
        if support:
            self._support[rec.closure_id] = self._with_stretches(rec, support)
        self._version += 1
        self._closure_noise.append(noise)
        self._information.append(info)
        if rec.robot_a == rec.robot_b and not self._agrees_with_odometry(rec):
            return ClosureDecision(False, rec.reason, rec.closure_id)
        self._update_pair(rec)
        if rec.robot_a == rec.robot_b and self._refresh_drift(rec.robot_a) and self._robots[rec.robot_a].anchored:
            self._rebuild()  # every odometry factor of the robot with its new sigmas (unanchored: when anchored)
        else:
            self._sync()
        if update:
            self.update()
        reason = rec.reason
        if rec.status is ClosureStatus.ACCEPTED and not rec.in_graph:
            if rec.robot_a == rec.robot_b:
                reason += f"; stored until {rec.robot_a} is anchored to {self.keys.names[0]}"
            elif self._robots[rec.robot_a].anchored or self._robots[rec.robot_b].anchored:
                reason += (
                    f"; waiting for consistent closures from {self.min_closures_to_anchor} matches between "
                    f"{rec.robot_a}-{rec.robot_b} before anchoring"
                )
            else:
                reason += f"; stored until {rec.robot_a} or {rec.robot_b} is anchored to {self.keys.names[0]}"
        return ClosureDecision(rec.status is ClosureStatus.ACCEPTED, reason, rec.closure_id)

    def update(self) -> None:
        """Run iSAM2 on the closures added with ``update=False`` (no-op when nothing is pending).

        Extra relinearization passes (``extra_updates``) follow only a large correction: a robot
        anchored, a closure removed or a rebuild, or a new closure whose translation disagrees with the
        current estimate by more than its sigma; small corrections settle in the next updates.
        """
        self._flush()

    def converge(self, max_iterations: int = 100) -> int:
        """Solve the whole graph to convergence: Levenberg-Marquardt over every factor in iSAM2 (robust
        kernels included), started from iSAM2's estimate, which relinearizes only variables that moved by
        more than ``relinearize_threshold`` and so stops short of the optimum by an amount that depends
        on the order keyframes and closures arrived in. The solution is what ``estimate`` and every pose
        query answer until the graph changes next (iSAM2 itself is left as it is). Returns the LM
        iterations run (0: nothing anchored).

        Raises:
            BackendError: the optimizer fails (an underconstrained graph).
        """
        self._flush()
        solved = self._solver.solve_batch(max_iterations)
        if solved is None:
            return 0
        result, iterations = solved
        self._version += 1
        self._converged = (self._version, result)
        return iterations

    def add_loop_closure(
        self,
        robot: str,
        kf_old: int,
        kf_new: int,
        T_old_new: np.ndarray,
        *,
        num_inliers: int = 1,
        information: np.ndarray | None = None,
        match_id: int | None = None,
        support: Iterable[Hashable] = (),
        update: bool = True,
    ) -> ClosureDecision:
        """Add an intra-robot loop closure: ``T_old_new`` (4, 4) maps points in keyframe ``kf_new``'s
        camera frame into keyframe ``kf_old``'s, both keyframes of ``robot``.

        The same as ``add_inter_robot_closure(robot, kf_old, robot, kf_new, ...)``: rejected outright when
        the loop it closes with the robot's odometry between the two keyframes exceeds the drift-dependent
        consistency tolerance, else voted on with the robot's other loop closures (pairwise consistency)
        and, when accepted, added with the robust kernel once the robot is anchored.
        """
        return self.add_inter_robot_closure(
            robot, kf_old, robot, kf_new, T_old_new,
            num_inliers=num_inliers, information=information, match_id=match_id, support=support, update=update,
        )  # fmt: skip

    def add_robot(self, robot: str) -> None:
        """Add an agent at run time (unanchored, no keyframes yet), e.g. a robot's new trajectory segment
        whose pose relative to everything else is unknown until a closure places it.

        Raises:
            BackendError: the name is taken or the 52 key letters are used up.
        """
        self._robots[robot] = self._new_robot(self.keys.add(robot))
        self._version += 1

    def _new_robot(self, index: int) -> RobotTrack:
        turn = self._stretch_turn_rad
        return RobotTrack(index, stretches=None if turn is None else StretchTracker(turn))

    @property
    def tracks_stretches(self) -> bool:
        """Whether closures also rest on the straight stretches of their keyframes (``stretch_turn_deg`` set)."""
        return self._stretch_turn_rad is not None

    def stretches(self) -> dict[int, tuple]:
        """Closure id -> the pair of straight stretches (``backend/stretches.py``) of each inter-robot closure's
        keyframes; empty when stretches are not tracked (``stretch_turn_deg`` None)."""
        if not self.tracks_stretches:
            return {}
        return {
            c.closure_id: self._stretch_token(c) for c in self._closures if c.robot_a != c.robot_b
        }

    def stretch_pair(self, closure_id: int) -> tuple[int, int] | None:
        """(the querying robot's stretch, the partner's) of an inter-robot closure (``backend/stretches.py``), or
        None (a loop closure, or stretches not tracked)."""
        rec = self._closures[closure_id]
        if not self.tracks_stretches or rec.robot_a == rec.robot_b:
            return None
        (q, kf_q), (o, kf_o) = self._querier_first(rec)
        return self._robots[q].stretches.ids[kf_q], self._robots[o].stretches.ids[kf_o]

    @staticmethod
    def _querier_first(rec: ClosureRecord) -> list[tuple[str, int]]:
        """[(the querying robot, its keyframe), (the other, its keyframe)] of an inter-robot closure."""
        ends = [(rec.robot_b, rec.kf_b), (rec.robot_a, rec.kf_a)]
        if rec.querier == rec.robot_a:
            ends.reverse()
        return ends

    def _stretch_token(self, rec: ClosureRecord) -> tuple:
        """The pair of stretches of a closure's two keyframes (``stretches.stretch_token``: either query's)."""
        robots = self._robots
        return stretch_token(rec.robot_a, robots[rec.robot_a].stretches.ids[rec.kf_a],
                             rec.robot_b, robots[rec.robot_b].stretches.ids[rec.kf_b])  # fmt: skip

    def _with_stretches(self, rec: ClosureRecord, support: Iterable[Hashable]) -> frozenset:
        """A closure's objects, plus the pair of straight stretches its keyframes lie on when stretches are
        tracked and it joins two robots (``stretches``)."""
        objects = frozenset(support)
        if not self.tracks_stretches or rec.robot_a == rec.robot_b:
            return objects
        return objects | {self._stretch_token(rec)}

    @property
    def up_shared(self) -> np.ndarray | None:
        """(3,) the shared frame's up (unit) the attitude factors hold keyframes to, once measured."""
        return None if self._up_shared is None else self._up_shared.copy()

    def is_anchored(self, robot: str) -> bool:
        """True when ``robot``'s keyframes are in the shared frame (it has variables in iSAM2)."""
        return self._robot(robot).anchored

    def estimate(self) -> dict[str, np.ndarray]:
        """Current ``T_shared_kf`` of every anchored robot: name -> (K, 4, 4), keyframe order.

        Computed once per change of the graph (``version``) and cached: the arrays are shared between
        calls and read-only (copy them to modify). A recomputation reads every pose from iSAM2 (about
        5 ms at 5000 keyframes, and it slows the next iSAM2 update), so ask when the poses are needed,
        not after every keyframe; ``T_shared_kf``/``T_shared_odom`` read a single pose without it.
        """
        if self._cache_version != self._version:
            self._cache = self._compute_estimate()
            self._cache_version = self._version
        return dict(self._cache)

    @property
    def version(self) -> int:
        """Counter bumped by every change of the graph (keyframe, closure, agent, rebuild)."""
        return self._version

    @property
    def corrections(self) -> int:
        """Counter bumped whenever closures enter or leave iSAM2, a robot is anchored or the graph is
        rebuilt: the changes that can move keyframes far from where they were (new keyframes alone do not)."""
        return self._corrections

    def T_shared_kfs(self, robot: str, kf_indices: np.ndarray) -> np.ndarray:
        """(M, 4, 4) current estimates of keyframes ``kf_indices`` of an anchored robot in the shared frame
        (from the cached estimate when it is current, else one iSAM2 query per keyframe)."""
        r = self._require_anchored(robot)
        kfs = np.asarray(kf_indices, dtype=np.int64).reshape(-1)
        if kfs.size and not (0 <= kfs.min() and kfs.max() < len(r.T_odom_kf)):
            raise BackendError(f"{robot} has keyframes 0..{len(r.T_odom_kf) - 1}, asked for {kfs.min()}..{kfs.max()}")
        if self._cache_version == self._version or (self._converged and self._converged[0] == self._version):
            return self.estimate()[robot][kfs].copy()
        out = np.zeros((kfs.size, 4, 4))
        for i, k in enumerate(kfs.tolist()):
            out[i] = self._solver.estimate_pose(self.keys.key(robot, k))
        return out

    def T_shared_kf(self, robot: str, kf_index: int) -> np.ndarray:
        """(4, 4) current estimate of one keyframe of an anchored robot in the shared frame."""
        r = self._require_anchored(robot)
        if not 0 <= kf_index < len(r.T_odom_kf):
            raise BackendError(f"{robot} has no keyframe {kf_index} ({len(r.T_odom_kf)} keyframes)")
        if self._cache_version == self._version or (self._converged and self._converged[0] == self._version):
            return self.estimate()[robot][kf_index].copy()
        return self._solver.estimate_pose(self.keys.key(robot, kf_index))

    def T_shared_odom(self, robot: str, kf_index: int | None = None) -> np.ndarray:
        """(4, 4) alignment of ``robot``'s odometry frame in the shared frame.

        Computed at one keyframe as ``T_shared_kf · T_odom_kf⁻¹``; by default the latest keyframe,
        which is the right correction for the robot's current (non-keyframe) poses and new points.
        """
        r = self._require_anchored(robot)
        k = len(r.T_odom_kf) - 1 if kf_index is None else kf_index
        return self.T_shared_kf(robot, k) @ inverse(r.T_odom_kf[k])

    def ground_normal_count(self, robot: str) -> int:
        """How many of ``robot``'s keyframes measured a ground normal (0 for an unknown robot)."""
        r = self._robots.get(robot)
        return 0 if r is None else len(r.measured)

    def measured_drift(self, robot: str) -> float | None:
        """The odometry rotation drift rate (rad per metre driven) ``robot``'s loop closures measured and its
        odometry factors now use, where more than the prior (``drift.py``); None while the prior holds."""
        return self._robot(robot).drift_rot_rad_per_m

    def anchor(self, robot: str) -> Anchor:
        """The closure that anchored ``robot`` and the alignment its keyframes were initialised with."""
        r = self._require_anchored(robot)
        return Anchor(r.anchor_closure, r.T_shared_odom_init.copy())

    def closure_keyframes(self, robot: str) -> np.ndarray:
        """Sorted (C,) int64 keyframes of ``robot`` that a factor ties to the shared frame beyond its own
        odometry: ends of its accepted closures in iSAM2 (and keyframe 0 of the shared frame's robot,
        which carries the prior). Between them the fused estimate's drift is bounded by the closures."""
        self._robot(robot)
        kfs = [c.kf_a for c in self._closures if c.in_graph and c.robot_a == robot]
        kfs += [c.kf_b for c in self._closures if c.in_graph and c.robot_b == robot]
        if robot == self.keys.names[0] and self._robots[robot].T_odom_kf:
            kfs.append(0)
        return np.unique(np.asarray(kfs, dtype=np.int64))

    def evidence_between(self, robot_a: str, robot_b: str) -> int:
        """How many independent sources of evidence (graph matches on mutually disjoint objects,
        ``PairConsistency.evidence``) the consistent set of two robots' closures (either order; a robot
        with itself: its loop closures) rests on."""
        ia, ib = self.keys.index(robot_a), self.keys.index(robot_b)
        vote = self._pairs.get((robot_a, robot_b) if ia <= ib else (robot_b, robot_a))
        return 0 if vote is None else vote.evidence()

    def anchor_closure(self, robot: str) -> int | None:
        """Id of the closure through which ``robot`` is anchored now (None: the first robot, or not anchored)."""
        r = self._robots.get(robot)
        return None if r is None else r.anchor_closure

    def anchorings(self) -> list[tuple[str, ClosureRecord]]:
        """Every (robot, closure) through which a robot entered the shared frame during this graph's life,
        in order, each pair once: a robot re-anchored after a closure was withdrawn appears again with the
        new closure, so a robot once placed through a false closure stays on record (snapshots do not keep
        this history: a restored graph starts it afresh)."""
        return [(robot, self._closures[cid]) for robot, cid in self._anchorings]

    def shared_support(self, robot_a: str, robot_b: str) -> frozenset:
        """What two or more of the graph matches behind two robots' accepted closures rest on in common (their
        objects, and the pseudo-objects of straight stretches and of marginal matches): why those matches are
        fewer independent pieces of evidence than matches. Empty when no two of them share anything."""
        by_source: dict[tuple, set] = {}
        for c in self._closures:
            if c.status is ClosureStatus.ACCEPTED and c.robot_a != c.robot_b and {c.robot_a, c.robot_b} == {
                robot_a, robot_b,
            }:  # fmt: skip
                by_source.setdefault(c.evidence, set()).update(self._support.get(c.closure_id, ()))
        seen: set = set()
        shared: set = set()
        for items in by_source.values():
            shared |= seen & items
            seen |= items
        return frozenset(shared)

    def closures(self) -> list[ClosureRecord]:
        """Every closure so far (canonical robot order) with its current status and reason."""
        return list(self._closures)

    def graph_error(self) -> float:
        """The graph's nonlinear error at the current estimate (what ``estimate`` answers): half the sum of
        every factor's squared whitened residual, robust kernels applied; 0 while nothing is anchored."""
        self._flush()
        return float(self._solver.factors().error(self._values()))

    def stats(self) -> PoseGraphStats:
        """Counters: keyframes, iSAM2 variables and factors, closures by status, rebuilds, timing."""
        accepted = sum(c.status is ClosureStatus.ACCEPTED for c in self._closures)
        return PoseGraphStats(
            num_keyframes=sum(len(r.T_odom_kf) for r in self._robots.values()),
            num_variables=self._solver.num_variables(),
            num_factors=int(self._solver.factors().nrFactors()),
            closures_total=len(self._closures),
            closures_accepted=accepted,
            closures_rejected=len(self._closures) - accepted,
            closures_in_graph=sum(c.in_graph for c in self._closures),
            anchored_robots=tuple(n for n, r in self._robots.items() if r.anchored),
            rebuilds=self._rebuilds,
            last_update_ms=self._last_update_ms,
            recoveries=self._recoveries,
            attitude_factors=self._attitude_factors,
        )

    def to_g2o(self) -> str:
        """The current graph as g2o text: VERTEX_SE3:QUAT (estimates) and EDGE_SE3:QUAT lines.

        Vertex ids are the gtsam keys (``gtsam.readG2o`` restores ``a0, b3, ...``), of the anchored agents only;
        a first comment line names each key letter's agent (``# agents (gtsam symbol letter): a=car1 b=car2
        c=car2#1``). Edges are the odometry factors and the closures in the graph, information matrices in g2o
        order [trans, rot]. Robust kernels, robot 0's prior and the attitude factors are not part of the format.
        """
        edges = []
        for name, r in self._robots.items():
            if not r.anchored:
                continue
            for k in range(1, len(r.T_odom_kf)):
                T = inverse(r.T_odom_kf[k - 1]) @ r.T_odom_kf[k]
                odo_info = np.diag(1.0 / self._odometry_sigmas(T, r) ** 2)
                edges.append((self.keys.key(name, k - 1), self.keys.key(name, k), T, odo_info))
        for c in self._closures:
            if c.in_graph:
                k_a, k_b = self.keys.key(c.robot_a, c.kf_a), self.keys.key(c.robot_b, c.kf_b)
                edges.append((k_a, k_b, c.T_a_b, self._information[c.closure_id]))
        letters = " ".join(f"{ROBOT_LETTERS[self.keys.index(n)]}={n}" for n, r in self._robots.items() if r.anchored)
        return g2o.g2o_text(self._values(), edges, [f"agents (gtsam symbol letter): {letters}"])

    def write_g2o(self, path: Path | str) -> None:
        """Write ``to_g2o()`` to ``path`` (creating the parent folder)."""
        g2o.write_g2o(path, self.to_g2o())

    # --- snapshots ---------------------------------------------------------------------------------

    def state(self) -> PoseGraphState:
        """Everything the graph decided (closures, votes, anchors) and its current estimate (copies)."""
        estimate = self.estimate()
        return PoseGraphState(
            tuple(self.keys.names),
            {n: (r.anchor_closure, r.T_shared_odom_init.copy()) for n, r in self._robots.items() if r.anchored},
            {n: T.copy() for n, T in estimate.items()},
            tuple(replace(c, T_a_b=c.T_a_b.copy()) for c in self._closures),
            np.array(self._information, dtype=np.float64).reshape(-1, 6, 6),
            {pair: v.vote() for pair, v in self._pairs.items()},
            self._rebuilds, self._recoveries, self.factorization,
            {n: np.array(r.up_odom, dtype=np.float64).reshape(-1, 3) for n, r in self._robots.items()},
        )  # fmt: skip

    def restore_state(
        self, state: PoseGraphState, T_odom_kf: dict[str, np.ndarray], support: Mapping[int, Iterable] | None = None
    ) -> None:
        """Load ``state`` into this fresh graph (made with the same settings and first robot) and build
        iSAM2 from it in one batch, starting at the stored estimate: afterwards the graph answers and
        votes as the one ``state`` came from (estimates equal to solver precision).

        Args:
            state: from ``state()``.
            T_odom_kf: robot -> (K, 4, 4) its keyframe poses in its odometry frame (every robot of ``state``).
            support: closure id -> the objects it rests on, as given to ``add_inter_robot_closure`` (none
                when None).

        Raises:
            BackendError: the graph is not fresh, or the state is inconsistent with itself or the keyframes.
        """
        if any(r.T_odom_kf for r in self._robots.values()) or self._closures:
            raise BackendError("restore_state needs a fresh pose graph (no keyframes, no closures)")
        names = list(state.robots)
        if names[: len(self.keys.names)] != self.keys.names or set(T_odom_kf) != set(names):
            raise BackendError(f"pose graph state of robots {names} does not fit robots {self.keys.names} "
                               f"with keyframes of {sorted(T_odom_kf)}")  # fmt: skip
        for name in names[len(self.keys.names):]:
            self.add_robot(name)
        misfit = []
        for name in names:
            poses = np.asarray(T_odom_kf[name], dtype=np.float64).reshape(-1, 4, 4)
            ups = np.asarray(state.up_odom.get(name, np.full((len(poses), 3), np.nan)), dtype=np.float64)
            if ups.shape != (len(poses), 3):
                misfit.append(f"{name} has {len(poses)} keyframes but normals of shape {ups.shape}")
                ups = np.full((len(poses), 3), np.nan)
            for k, (T, up) in enumerate(zip(poses, ups, strict=True)):
                measured = bool(np.isfinite(up).all())
                self._robots[name].append(check_pose(T, f"keyframe {k} of {name}"), up if measured else None)
        check_state(state, self.keys.names, {n: len(r.T_odom_kf) for n, r in self._robots.items()})
        if misfit:
            raise BackendError(f"pose graph state: {'; '.join(misfit)}")
        default_info = np.diag(1.0 / self._closure_sigmas**2)
        for c, info in zip(state.closures, state.information, strict=True):
            self._closures.append(replace(c, T_a_b=np.array(c.T_a_b, dtype=np.float64)))
            noise, info = self._closure_noise_model(None if np.array_equal(info, default_info) else info)
            self._closure_noise.append(noise)
            self._information.append(info)
        cap = self.max_closures_per_pair
        evidence = {c.closure_id: c.evidence for c in self._closures}
        self._support = {
            int(cid): self._with_stretches(self._closures[int(cid)], objects)
            for cid, objects in (support or {}).items() if objects
        }  # fmt: skip
        self._pairs = {
            pair: PairConsistency.from_vote(
                v, cap, [evidence[int(i)] for i in v.ids], [self._support.get(int(i), ()) for i in v.ids],
                [self._pieces(self._closures[int(i)]) for i in v.ids],
            )
            for pair, v in state.pairs.items()
        }
        self._rebuilds, self._recoveries = int(state.rebuilds), int(state.recoveries)
        for name in names:
            self._robots[name].drift_rot_rad_per_m = self._drift_level(name)
        self._reset_isam(Factorization(state.factorization))
        first = self.keys.names[0]
        for name, (closure_id, T_init) in state.anchors.items():
            r = self._robots[name]
            r.anchored, r.anchor_closure, r.T_shared_odom_init = True, closure_id, np.array(T_init, dtype=np.float64)
            T_shared = state.T_shared_kf[name]
            if name == first:
                self._solver.add_factor(
                    gtsam.PriorFactorPose3(self.keys.key(name, 0), pose3(r.T_odom_kf[0]), prior_noise())
                )
            for k in range(len(r.T_odom_kf)):
                key = self.keys.key(name, k)
                self._solver.add_value(key, T_shared[k])
                if k:
                    delta = inverse(r.T_odom_kf[k - 1]) @ r.T_odom_kf[k]
                    prev = self.keys.key(name, k - 1)
                    noise = odometry_noise(self._odometry_sigmas(delta, r))
                    self._solver.add_factor(gtsam.BetweenFactorPose3(prev, key, pose3(delta), noise))
        for c in self._closures:
            if c.in_graph:
                k_a, k_b = self.keys.key(c.robot_a, c.kf_a), self.keys.key(c.robot_b, c.kf_b)
                noise = self._closure_noise[c.closure_id]
                self._solver.add_factor(gtsam.BetweenFactorPose3(k_a, k_b, pose3(c.T_a_b), noise), c.closure_id)
        self._push_attitudes()
        self._flush()

    # --- consistency: which closures are accepted -------------------------------------------------

    def _agrees_with_odometry(self, rec: ClosureRecord) -> bool:
        """A loop closure must agree with its robot's own odometry between its two keyframes (the loop
        with no other closure); one that does not is rejected for good and never votes."""
        odom, path = self._robots[rec.robot_a].odometry()
        ok, trans_m, rot_deg = consistent_with_odometry(rec.T_a_b, rec.kf_a, rec.kf_b, odom, path, self.thresholds)
        if not ok:
            rec.status = ClosureStatus.REJECTED
            d = abs(path[rec.kf_b] - path[rec.kf_a])
            rec.reason = (
                f"rejected: loop closure disagrees with {rec.robot_a}'s odometry over {d:.0f} m "
                f"({trans_m:.1f} m, {rot_deg:.1f} deg off)"
            )
        return ok

    def _update_pair(self, rec: ClosureRecord) -> None:
        """Test ``rec`` against its robot pair's voting closures (O(n)) and update the pair's maximum
        consistent set incrementally (``PairConsistency``)."""
        pair = (rec.robot_a, rec.robot_b)
        voting = self._pairs.setdefault(pair, PairConsistency(self.max_closures_per_pair))
        ra, rb = self._robots[rec.robot_a], self._robots[rec.robot_b]
        others = [self._closures[i] for i in voting.ids]
        (odom_a, path_a), (odom_b, path_b) = ra.odometry(), rb.odometry()
        row = consistent_with(
            rec.T_a_b, rec.kf_a, rec.kf_b,
            np.array([c.T_a_b for c in others]).reshape(-1, 4, 4),
            np.array([c.kf_a for c in others], dtype=np.int64),
            np.array([c.kf_b for c in others], dtype=np.int64),
            odom_a, odom_b, path_a, path_b, self.thresholds,
        )  # fmt: skip
        evicted = voting.add(
            rec.closure_id, row, rec.num_inliers, rec.evidence, self._support.get(rec.closure_id, ()), self._pieces(rec)
        )
        where = f"{rec.robot_a}-{rec.robot_b}"
        if evicted is not None:
            c = self._closures[evicted[0]]
            kept = "accepted" if evicted[1] else "rejected"
            c.reason = (
                f"{kept}: left the consistency vote of {where} (at most {self.max_closures_per_pair} "
                "closures vote; the oldest outside the consistent set leave first)"
            )
        n, chosen = len(voting), voting.chosen_mask()
        size = int(chosen.sum())
        for cid, is_in in zip(voting.ids, chosen.tolist(), strict=True):
            c = self._closures[cid]
            if is_in:
                c.status = ClosureStatus.ACCEPTED
                c.reason = (
                    f"accepted: only closure between {where} so far (unconfirmed, a larger consistent set "
                    "can replace it)"
                    if n == 1
                    else f"accepted: in the maximum consistent set ({size} of {n} closures between {where})"
                )
            else:
                c.status = ClosureStatus.REJECTED
                c.reason = (
                    f"rejected: inconsistent with the maximum consistent set ({size} of {n} closures "
                    f"between {where})"
                )

    def _pieces(self, rec: ClosureRecord) -> int:
        """Pieces of evidence a closure's match gives in its pair's consistency vote: a decisive match as many as
        a robot needs to enter the shared frame (``min_closures_to_anchor``, as its anchoring rule says), any
        other one."""
        return self.min_closures_to_anchor if rec.decisive else 1

    # --- anchoring and iSAM2 bookkeeping ---------------------------------------------------------

    def _reset_isam(self, factorization: Factorization | None = None) -> None:
        """An empty iSAM2 (``factorization`` when given, else the current one): a change of the graph."""
        self._version += 1
        self._solver.reset(factorization)

    def _anchor_first_robot(self) -> None:
        name = self.keys.names[0]
        r = self._robots[name]
        r.anchored, r.T_shared_odom_init = True, np.eye(4)
        k0 = self.keys.key(name, 0)
        self._solver.add_factor(gtsam.PriorFactorPose3(k0, pose3(r.T_odom_kf[0]), prior_noise()))
        self._solver.add_value(k0, r.T_odom_kf[0])
        for k in range(1, len(r.T_odom_kf)):
            self._push_keyframe(name, k)

    def _odometry_sigmas(self, delta: np.ndarray, r: RobotTrack) -> np.ndarray:
        """(6,) [rot rad x3, trans m x3] sigmas of an odometry step ``delta`` (4, 4) of robot ``r``: the floor
        plus the drift rates times the step's length (the rotation rate the robot's loop closures measured,
        when they measured more than the prior: ``drift.py``)."""
        drift = self._odometry_drift
        if r.drift_rot_rad_per_m is not None:
            drift = np.r_[[r.drift_rot_rad_per_m] * 3, drift[3:]]
        return self._odometry_floor + drift * float(np.linalg.norm(delta[:3, 3]))

    def _drift_level(self, robot: str) -> float | None:
        """The rotation drift rate ``robot``'s accepted loop closures call for (``drift.drift_level`` of
        their median maximum-likelihood rate), None where that is the prior."""
        prior = float(self._odometry_drift[0])
        rates = [
            self._loop_rate(c) for c in self._closures
            if c.robot_a == c.robot_b == robot and c.status is ClosureStatus.ACCEPTED
        ]  # fmt: skip
        level = drift_level(measured_rate(rates), prior)
        return None if level == prior else level

    def _loop_rate(self, c: ClosureRecord) -> float:
        """Loop closure ``c``'s maximum-likelihood drift rate (``drift.closure_rate``), computed once: a
        closure and the odometry between its keyframes never change."""
        if c.closure_id not in self._loop_rates:
            odom, path = self._robots[c.robot_a].odometry()
            error = loop_rotation_error_rad(odom[c.kf_a], odom[c.kf_b], c.T_a_b)
            steps = np.diff(path[c.kf_a : c.kf_b + 1])
            self._loop_rates[c.closure_id] = closure_rate(error, steps, float(self._odometry_floor[0]))
        return self._loop_rates[c.closure_id]

    def _refresh_drift(self, robot: str) -> bool:
        """Take up the drift level ``robot``'s loop closures call for; True when it changed (the odometry
        factors in iSAM2 then need rebuilding). ``measured_drift`` tells; the caller reports it."""
        r = self._robots[robot]
        level = self._drift_level(robot)
        if level == r.drift_rot_rad_per_m:
            return False
        r.drift_rot_rad_per_m = level
        return True

    def _push_keyframe(self, robot: str, k: int) -> None:
        """Odometry factor (k-1 -> k) and initial value of keyframe k of an anchored robot."""
        r = self._robots[robot]
        k_prev, k_new = self.keys.key(robot, k - 1), self.keys.key(robot, k)
        delta = inverse(r.T_odom_kf[k - 1]) @ r.T_odom_kf[k]
        prev = self._solver.pose(k_prev)
        noise = odometry_noise(self._odometry_sigmas(delta, r))
        self._solver.add_factor(gtsam.BetweenFactorPose3(k_prev, k_new, pose3(delta), noise))
        self._solver.add_value(k_new, prev @ delta)

    def _anchor_robot(self, robot: str, closure: ClosureRecord) -> None:
        """Insert all keyframes of unanchored ``robot`` placed through ``closure`` to an anchored robot."""
        r = self._robots[robot]
        if robot == closure.robot_b:  # T_shared_odomB = T_shared_ai · T_ai_bj · T_odomB_bj⁻¹
            T_shared_kf = self._current_pose(closure.robot_a, closure.kf_a) @ closure.T_a_b
            kf = closure.kf_b
        else:  # the anchored robot is b: T_shared_odomA = T_shared_bj · T_ai_bj⁻¹ · T_odomA_ai⁻¹
            T_shared_kf = self._current_pose(closure.robot_b, closure.kf_b) @ inverse(closure.T_a_b)
            kf = closure.kf_a
        T_shared_odom = T_shared_kf @ inverse(r.T_odom_kf[kf])
        r.anchored, r.anchor_closure, r.T_shared_odom_init = True, closure.closure_id, T_shared_odom
        if (robot, closure.closure_id) not in self._anchorings:
            self._anchorings.append((robot, closure.closure_id))
        self._solver.add_value(self.keys.key(robot, 0), T_shared_odom @ r.T_odom_kf[0])
        for k in range(1, len(r.T_odom_kf)):
            self._push_keyframe(robot, k)

    def _agreeing_anchor(self, accepted: list[ClosureRecord]) -> list[ClosureRecord]:
        """The closures of the first unanchored robot (robot order) whose accepted closures with
        ``min_closures_to_anchor`` different anchored robots are independent pieces of evidence that agree on
        its place (``cross_evidence``); [] when no robot has them."""
        partners: dict[str, set[str]] = {}
        for c in accepted:
            if c.robot_a != c.robot_b and self._robots[c.robot_a].anchored != self._robots[c.robot_b].anchored:
                robot, other = (c.robot_b, c.robot_a) if self._robots[c.robot_a].anchored else (c.robot_a, c.robot_b)
                partners.setdefault(robot, set()).add(other)
        for robot in self.keys.names:
            if len(partners.get(robot, ())) >= self.min_closures_to_anchor:
                pieces = self._agreeing(robot, frozenset(partners[robot]), self.min_closures_to_anchor, accepted)
                if pieces:
                    return [self._closures[p.closure_id] for p in pieces]
        return []

    def agreeing_partners(self, robot: str, partners: Iterable[str], needed: int = 2) -> tuple[str, ...]:
        """The ``needed`` partners among anchored ``partners`` whose accepted closures with ``robot`` are
        independent pieces of evidence that agree on its place (``cross_evidence``), in piece order; () when
        there are none (``confirmation.placements`` confirms a robot through them).

        Raises:
            BackendError: ``robot`` is unknown.
        """
        self._robot(robot)
        accepted = [c for c in self._closures if c.status is ClosureStatus.ACCEPTED]
        anchored = frozenset(p for p in partners if p != robot and p in self._robots and self._robots[p].anchored)
        return tuple(p.partner for p in self._agreeing(robot, anchored, needed, accepted))

    def _agreeing(
        self, robot: str, partners: frozenset[str], needed: int, accepted: list[ClosureRecord]
    ) -> list[Piece]:
        """``cross_evidence.agreeing_pieces`` of ``robot``'s accepted closures with anchored ``partners``."""
        r = self._robots[robot]
        mine = [
            c for c in accepted
            if c.robot_a != c.robot_b and robot in (c.robot_a, c.robot_b)
            and (c.robot_b if c.robot_a == robot else c.robot_a) in partners
        ]  # fmt: skip
        others = [c.robot_b if c.robot_a == robot else c.robot_a for c in mine]
        kfs = [c.kf_b if c.robot_b == robot else c.kf_a for c in mine]
        stretches = [None if r.stretches is None else r.stretches.ids[kf] for kf in kfs]
        pieces = []
        for i in strongest(others, stretches, [c.num_inliers for c in mine], needed):
            c, other = mine[i], others[i]
            if c.robot_b == robot:  # T_shared_bj = T_shared_ai · T_ai_bj
                T = self._current_pose(other, c.kf_a) @ c.T_a_b
            else:  # T_shared_ai = T_shared_bj · T_ai_bj⁻¹
                T = self._current_pose(other, c.kf_b) @ inverse(c.T_a_b)
            objects = frozenset(
                x for x in self._support.get(c.closure_id, ()) if isinstance(x, tuple) and len(x) == 2 and x[0] == robot
            )
            pieces.append(Piece(c.closure_id, other, kfs[i], T, objects, stretches[i], c.num_inliers))
        odom, path = r.odometry()
        return agreeing_pieces(pieces, odom, path, self.thresholds, needed) if pieces else []

    def _current_pose(self, robot: str, k: int) -> np.ndarray:
        """(4, 4) ``T_shared_kf`` of keyframe ``k`` of anchored ``robot``: its initial value while pending, else
        iSAM2's estimate (``IncrementalSolver.pose``)."""
        return self._solver.pose(self.keys.key(robot, k))

    def _sync(self) -> None:
        """Bring iSAM2 in line with the accepted closures: anchor robots, add and remove closure factors."""
        accepted = [c for c in self._closures if c.status is ClosureStatus.ACCEPTED]
        broken = [
            n for n, r in self._robots.items()
            if r.anchor_closure is not None
            and self._closures[r.anchor_closure].status is not ClosureStatus.ACCEPTED
        ]  # fmt: skip
        if broken:
            self._rebuild()
            return
        pair_size = {pair: vote.evidence() for pair, vote in self._pairs.items()}
        grown = True
        while grown:  # anchoring spreads through accepted closures (replays closures of unanchored robots)
            grown = False
            candidates = [
                c for c in accepted
                if self._robots[c.robot_a].anchored != self._robots[c.robot_b].anchored
                and (pair_size[(c.robot_a, c.robot_b)] >= self.min_closures_to_anchor or c.decisive)
            ]  # fmt: skip
            if not candidates and self.min_closures_to_anchor > 1:
                candidates = self._agreeing_anchor(accepted)
            if candidates:
                c = max(candidates, key=lambda c: (c.num_inliers, -c.closure_id))
                self._anchor_robot(c.robot_b if self._robots[c.robot_a].anchored else c.robot_a, c)
                self._corrections += 1
                self._large_correction = True
                grown = True
        for c in self._closures:
            both = self._robots[c.robot_a].anchored and self._robots[c.robot_b].anchored
            if c.status is ClosureStatus.ACCEPTED and both and not c.in_graph:
                k_a, k_b = self.keys.key(c.robot_a, c.kf_a), self.keys.key(c.robot_b, c.kf_b)
                self._solver.add_factor(
                    gtsam.BetweenFactorPose3(k_a, k_b, pose3(c.T_a_b), self._closure_noise[c.closure_id]),
                    c.closure_id,
                )
                c.in_graph = True
                self._corrections += 1
                if not self._large_correction:
                    T_est = inverse(self._current_pose(c.robot_a, c.kf_a)) @ self._current_pose(c.robot_b, c.kf_b)
                    off_m = float(np.linalg.norm((inverse(c.T_a_b) @ T_est)[:3, 3]))
                    self._large_correction = off_m > self._closure_sigmas[3]
            elif c.status is ClosureStatus.REJECTED and c.in_graph:
                if self._solver.is_pending(c.closure_id):  # still pending (added with update=False): give it an index
                    self._flush()
                if not self._solver.remove(c.closure_id):  # cannot happen after a flush; be safe
                    raise BackendError(f"closure {c.closure_id} was rejected before its factor was added")
                c.in_graph = False
                self._corrections += 1
                self._large_correction = True
        self._push_attitudes()

    def _push_attitudes(self) -> None:
        """Attitude factors for the measured keyframes of anchored robots that have none yet (once the
        shared frame's up and the robot's sigma are measured)."""
        if not self.attitude:
            return
        anchored = [(name, r) for name, r in self._robots.items() if r.anchored]
        if self._up_shared is None:
            self._up_shared = self._measure_up_shared(anchored)
            if self._up_shared is None:
                return
        nav_up = gtsam.Unit3(self._up_shared)
        for name, r in anchored:
            if self._attitude_sigma(r) is None:
                continue
            if r.attitude_next == len(r.T_odom_kf):
                continue
            noise = attitude_noise(r.attitude_sigma_rad)
            start = bisect.bisect_left(r.measured, r.attitude_next)
            for k in r.measured[start:]:
                n_cam = r.T_odom_kf[k][:3, :3].T @ r.up_odom[k]
                self._solver.add_factor(
                    gtsam.AttitudeFactorPose3(self.keys.key(name, k), nav_up, noise, gtsam.Unit3(n_cam))
                )
                self._attitude_factors += 1
            r.attitude_next = len(r.T_odom_kf)

    def _measure_up_shared(self, anchored: list[tuple[str, RobotTrack]]) -> np.ndarray | None:
        """The shared frame's up, from the first anchored robot (in index order) with ``attitude_warmup``
        measured keyframes: those normals rotated by their current estimates, weighed against the odometry's
        rotation drift since its first keyframe (``attitude.up_at_start``; the drift as the odometry factors
        model it, the normals' noise as measured)."""
        for name, r in sorted(anchored, key=lambda item: item[1].index):
            ks = r.measured[: self.attitude_warmup]
            if len(ks) < self.attitude_warmup:
                continue
            ups = [
                self._current_pose(name, k)[:3, :3] @ (r.T_odom_kf[k][:3, :3].T @ r.up_odom[k]) for k in ks
            ]
            step_var = [
                self._odometry_sigmas(inverse(r.T_odom_kf[k - 1]) @ r.T_odom_kf[k], r)[0] ** 2
                for k in range(1, ks[-1] + 1)
            ]
            walk = np.concatenate([[0.0], np.cumsum(step_var)])[np.asarray(ks)]
            return up_at_start(np.stack(ups), walk, self._attitude_sigma(r))
        return None

    def _attitude_sigma(self, r: RobotTrack) -> float | None:
        """The robot's attitude sigma, measured once from its first ``attitude_warmup`` measured normals
        (``attitude.normal_sigma_rad``); None while it has fewer."""
        if r.attitude_sigma_rad is None and len(r.measured) >= self.attitude_warmup:
            first = np.stack([r.up_odom[k] for k in r.measured[: self.attitude_warmup]])
            r.attitude_sigma_rad = normal_sigma_rad(first)
        return r.attitude_sigma_rad

    def _rebuild(self) -> None:
        """Start iSAM2 afresh from the recorded odometry and the accepted closures (anchor changed)."""
        self._rebuilds += 1
        self._corrections += 1
        self._large_correction = True
        self._reset_isam()
        for r in self._robots.values():
            r.anchored, r.anchor_closure, r.T_shared_odom_init = False, None, None
            r.attitude_next = 0
        self._attitude_factors = 0
        for c in self._closures:
            c.in_graph = False
        if self._robots[self.keys.names[0]].T_odom_kf:
            self._anchor_first_robot()
            self._sync()

    def _flush(self) -> None:
        """Run iSAM2 on the pending factors/values/removals (plus extra passes after a large correction).

        An update that raises is recovered by rebuilding the graph with QR (a logged warning,
        ``IncrementalSolver.update``); ``BackendError`` when that fails too.
        """
        if not self._solver.pending:
            return
        t0 = time.perf_counter()
        self._version += 1
        closures_changed, self._large_correction = self._large_correction, False
        self._solver.update(closures_changed, self._rebuild_after_failure)
        self._last_update_ms = (time.perf_counter() - t0) * 1e3

    def _rebuild_after_failure(self) -> None:
        """The solver's recovery (``IncrementalSolver.update``, now on QR): count it and refill iSAM2 from the
        recorded keyframes and accepted closures."""
        self._recoveries += 1
        self._rebuild()

    def _values(self) -> gtsam.Values:
        """The current estimate: the converged solution while the graph has not changed since
        ``converge``, else iSAM2's."""
        if self._converged is not None and self._converged[0] == self._version:
            return self._converged[1]
        return self._solver.estimate()

    def _compute_estimate(self) -> dict[str, np.ndarray]:
        """All anchored robots' ``T_shared_kf`` from one ``calculateEstimate`` (vectorised extraction)."""
        keys, T = poses_by_key(self._values())
        letters = (keys >> np.uint64(56)).astype(np.int64)
        kf = (keys & np.uint64((1 << 56) - 1)).astype(np.int64)
        out = {}
        for name, r in self._robots.items():
            if not r.anchored:
                continue
            sel = np.flatnonzero(letters == ord(ROBOT_LETTERS[r.index]))
            poses = T[sel[np.argsort(kf[sel], kind="stable")]]
            if len(poses) != len(r.T_odom_kf):
                raise BackendError(
                    f"{name} has {len(r.T_odom_kf)} keyframes but {len(poses)} poses in iSAM2 (internal error)"
                )
            poses.flags.writeable = False
            out[name] = poses
        return out

    # --- helpers ---------------------------------------------------------------------------------

    def _robot(self, robot: str) -> RobotTrack:
        self.keys.index(robot)  # raises BackendError naming the known robots
        return self._robots[robot]

    def _require_anchored(self, robot: str) -> RobotTrack:
        r = self._robot(robot)
        if not r.anchored:
            raise BackendError(
                f"{robot} is not anchored yet: no accepted closure connects it to the shared frame"
            )
        return r

    def _closure_noise_model(self, information: np.ndarray | None) -> tuple[gtsam.noiseModel.Base, np.ndarray]:
        """A closure's noise model (with the robust kernel) and (6, 6) information (``factors.closure_noise_model``)."""
        return closure_noise_model(information, self._closure_sigmas, self.robust_kernel, self._kernel_width)


def make_pose_graph(robot_names: list[str], cfg: BackendConfig) -> MultiRobotPoseGraph:
    """Build the pose graph from the back-end configuration (drift rates still None: depth from files,
    ``BackendConfig.for_depth``)."""
    cfg = cfg.for_depth(predicted_depth=False)
    return MultiRobotPoseGraph(
        robot_names,
        odometry_sigmas=(cfg.odometry_sigma_rot_rad, cfg.odometry_sigma_trans_m),
        odometry_drift=(cfg.odometry_drift_rot_rad_per_m, cfg.odometry_drift_trans_per_m),
        closure_sigmas=(cfg.closure_sigma_rot_rad, cfg.closure_sigma_trans_m),
        robust_kernel=cfg.robust_kernel,
        consistency_trans_m=cfg.consistency_trans_m,
        consistency_rot_deg=cfg.consistency_rot_deg,
        consistency_trans_per_m=cfg.consistency_trans_per_m,
        consistency_rot_deg_per_m=cfg.consistency_rot_deg_per_m,
        min_closures_to_anchor=cfg.min_closures_to_anchor,
        stretch_turn_deg=cfg.stretch_turn_deg,
        attitude=cfg.attitude_factors,
        attitude_warmup=cfg.attitude_warmup_keyframes,
    )
