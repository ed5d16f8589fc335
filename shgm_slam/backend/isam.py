"""iSAM2 plumbing of the pose graph: one ``gtsam.ISAM2``, the factors and initial values waiting for its
next update, the iSAM2 indices of closure factors (to remove them), the update calls, and the recovery
when an update raises.

``IncrementalSolver`` knows keys, factors and poses, not robots or closures: factors may carry a tag (a
closure id) so that they can be removed later by that tag. Every pose it takes or answers is a (4, 4)
``T_shared_kf``: a keyframe camera's pose in the shared frame, translation in metres. The order of
``add_factor`` calls is the order the factors reach iSAM2, which changes its results: callers keep it.

Recovery: when an update raises (``RuntimeError``, e.g. gtsam's ``IndeterminateSystem`` under CHOLESKY),
the solver switches to QR, asks its owner to refill it from scratch (the ``rebuild`` callback of
``update``: ``reset`` and every factor and value again) and runs the update once more; ``BackendError``
when that fails too. The warning goes to the pose graph's logger (``shgm_slam.backend.pose_graph``): it
is the pose graph's warning, and tests and users filter on that name.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import gtsam
import numpy as np

from shgm_slam.backend.factors import isam2_params, pose3
from shgm_slam.backend.records import Factorization
from shgm_slam.errors import BackendError

__all__ = ["IncrementalSolver", "poses_by_key"]

_log = logging.getLogger("shgm_slam.backend.pose_graph")


class IncrementalSolver:
    """One iSAM2 instance with its pending factors, initial values and removals.

    Args:
        factorization: iSAM2's linear solver (QR or CHOLESKY); switched to QR by a recovery.
        relinearize_threshold: (rotation rad, translation m) relinearization thresholds
            (``factors.isam2_params``).
        extra_updates: additional ``isam.update()`` passes after a large correction (``update``).
    """

    def __init__(
        self, factorization: Factorization, relinearize_threshold: tuple[float, float], extra_updates: int
    ) -> None:
        self.relinearize_threshold = relinearize_threshold
        self.extra_updates = extra_updates
        self._factorization = factorization
        self.reset()

    @property
    def factorization(self) -> Factorization:
        """iSAM2's linear solver now (QR after a recovery)."""
        return self._factorization

    def reset(self, factorization: Factorization | None = None) -> None:
        """Start afresh: an empty iSAM2 (with ``factorization`` when given, else the current one), nothing
        pending, no tagged factors."""
        if factorization is not None:
            self._factorization = factorization
        self._isam = gtsam.ISAM2(isam2_params(self._factorization, self.relinearize_threshold))
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_tags: list[int | None] = []  # closure id of each pending factor (None: odometry/prior/attitude)
        self._factor_index: dict[int, int] = {}  # closure id -> iSAM2 factor index
        self._to_remove: list[int] = []

    # --- what goes in ----------------------------------------------------------------------------

    def add_factor(self, factor: gtsam.NonlinearFactor, closure_id: int | None = None) -> None:
        """Queue ``factor`` for the next update, tagged with ``closure_id`` when it may be removed later
        (``remove``); factors reach iSAM2 in the order they were added."""
        self._new_factors.add(factor)
        self._new_tags.append(closure_id)

    def add_value(self, key: int, T_shared_kf: np.ndarray) -> None:
        """Queue the initial value of a new variable: gtsam ``key`` at (4, 4) ``T_shared_kf`` (shared frame,
        metres; the rotation projected onto SO(3), ``factors.pose3``)."""
        self._new_values.insert(key, pose3(T_shared_kf))

    def is_pending(self, closure_id: int) -> bool:
        """True while the factor tagged ``closure_id`` waits for the next update (it has no index yet)."""
        return closure_id in self._new_tags

    def remove(self, closure_id: int) -> bool:
        """Queue the removal of the factor tagged ``closure_id`` from iSAM2 at the next update. False when
        iSAM2 holds no factor with that tag (never added, still pending, or removed already)."""
        idx = self._factor_index.pop(closure_id, None)
        if idx is None:
            return False
        self._to_remove.append(idx)
        return True

    @property
    def pending(self) -> bool:
        """True when factors or removals wait for the next update (values alone do not make one)."""
        return self._new_factors.size() != 0 or bool(self._to_remove)

    # --- updates and recovery --------------------------------------------------------------------

    def update(self, large_correction: bool, rebuild: Callable[[], None]) -> None:
        """Run iSAM2 on the pending factors, values and removals; ``extra_updates`` more passes after a
        ``large_correction``. Nothing is pending afterwards, whatever happens.

        When the update raises, the solver is recovered: a warning, the factorization switched to QR, then
        ``rebuild()``, which must ``reset`` the solver and add every factor and value again, and one more
        update with the extra passes.

        Raises:
            BackendError: the update after the rebuild raised too.
        """
        try:
            self._update(large_correction)
        except RuntimeError as exc:
            self._recover(exc, rebuild)

    def _update(self, large_correction: bool) -> None:
        try:
            result = self._isam.update(self._new_factors, self._new_values, self._to_remove)
            for idx, tag in zip(result.getNewFactorsIndices(), self._new_tags, strict=True):
                if tag is not None:
                    self._factor_index[tag] = int(idx)
            if large_correction:
                for _ in range(self.extra_updates):
                    self._isam.update()
        finally:
            self._new_factors = gtsam.NonlinearFactorGraph()
            self._new_values = gtsam.Values()
            self._new_tags = []
            self._to_remove = []

    def _recover(self, exc: RuntimeError, rebuild: Callable[[], None]) -> None:
        """Switch to QR, refill through ``rebuild`` and update once more after ``exc``."""
        first = _first_line(exc)
        _log.warning(
            "iSAM2 update with %s factorization failed (%s); rebuilding the pose graph with QR",
            self._factorization.value, first,
        )  # fmt: skip
        self._factorization = Factorization.QR
        rebuild()
        try:
            self._update(large_correction=True)
        except RuntimeError as again:
            raise BackendError(
                f"iSAM2 update failed ({first}) and rebuilding the graph with QR failed too "
                f"({_first_line(again)}); the graph is underconstrained or a pose is invalid"
            ) from None

    # --- what comes out --------------------------------------------------------------------------

    def pose(self, key: int) -> np.ndarray:
        """(4, 4) ``T_shared_kf`` of ``key``: its pending initial value while it waits for the next update,
        else iSAM2's current estimate."""
        if self._new_values.exists(key):
            return self._new_values.atPose3(key).matrix()
        return self._isam.calculateEstimatePose3(key).matrix()

    def estimate_pose(self, key: int) -> np.ndarray:
        """(4, 4) ``T_shared_kf`` of ``key`` from iSAM2's current estimate alone (gtsam raises for a key
        iSAM2 does not hold yet)."""
        return self._isam.calculateEstimatePose3(key).matrix()

    def estimate(self) -> gtsam.Values:
        """iSAM2's current estimate of every variable (``calculateEstimate``)."""
        return self._isam.calculateEstimate()

    def factors(self) -> gtsam.NonlinearFactorGraph:
        """The factors in iSAM2 (gtsam's own graph, not a copy: removed factors leave empty slots)."""
        return self._isam.getFactorsUnsafe()

    def num_variables(self) -> int:
        """Variables in iSAM2 (its linearization point's size)."""
        return int(self._isam.getLinearizationPoint().size())

    def solve_batch(self, max_iterations: int) -> tuple[gtsam.Values, int] | None:
        """Levenberg-Marquardt over every factor in iSAM2 (robust kernels included), started from iSAM2's
        estimate: (the solution, iterations run), or None when iSAM2 holds no variable. Pending factors
        are not included (update first); iSAM2 itself is left as it is.

        Raises:
            BackendError: the optimizer fails (an underconstrained graph).
        """
        factors = self._isam.getFactorsUnsafe()
        graph = gtsam.NonlinearFactorGraph()
        for i in range(factors.size()):
            if factors.exists(i):
                graph.add(factors.at(i))
        initial = self._isam.calculateEstimate()
        if initial.size() == 0:
            return None
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(1e-9)
        params.setAbsoluteErrorTol(1e-12)
        try:
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
            result = optimizer.optimize()
        except RuntimeError as exc:
            raise BackendError(f"converging the pose graph failed: {_first_line(exc)}") from None
        return result, int(optimizer.iterations())


def poses_by_key(values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
    """Every pose in ``values`` at once: ((N,) uint64 keys in key order, (N, 4, 4) poses), vectorised
    (``gtsam.utilities.extractPose3``)."""
    keys = np.fromiter(values.keys(), dtype=np.uint64, count=values.size())
    rows = gtsam.utilities.extractPose3(values)  # (N, 12): R row-major, t; in key order
    T = np.zeros((len(keys), 4, 4))
    T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = rows[:, 9:12]
    T[:, 3, 3] = 1.0
    return keys, T


def _first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception message (gtsam's run over many lines)."""
    return next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
