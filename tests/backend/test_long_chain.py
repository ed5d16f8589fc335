"""Long keyframe chains (issue 11): iSAM2 never raises and recovers when forced to (its cost with distance is
measured by `shgm-slam bench scale`, not here)."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from shgm_slam.backend.pose_graph import Factorization, MultiRobotPoseGraph, make_pose_graph
from shgm_slam.config import BackendConfig
from shgm_slam.errors import BackendError
from shgm_slam.geometry.se3 import make_pose, rot_y

N_LONG = 5000


def chain(n: int, yaw_rad: float, step_m: float = 2.0) -> np.ndarray:
    """(n, 4, 4) exact odometry of a robot driving ``step_m`` per keyframe while turning ``yaw_rad``."""
    D = make_pose(rot_y(yaw_rad), [0.0, 0.0, step_m])
    out = np.empty((n, 4, 4))
    out[0] = np.eye(4)
    for k in range(1, n):
        out[k] = out[k - 1] @ D
    return out


def add_chain(pg: MultiRobotPoseGraph, odo: np.ndarray, robot: str = "a") -> list[float]:
    """Add every keyframe; returns the seconds each ``add_keyframe`` took."""
    times = []
    for k, T in enumerate(odo):
        t0 = time.perf_counter()
        pg.add_keyframe(robot, k, T)
        times.append(time.perf_counter() - t0)
    return times


@pytest.mark.parametrize("shape, yaw_rad", [("straight", 0.0), ("curved", 0.01)])
def test_5000_keyframe_chain_with_default_sigmas_does_not_raise(shape, yaw_rad):
    # CHOLESKY raised IndeterminateSystem after ~1100 keyframes of this straight chain (2 m steps)
    odo = chain(N_LONG, yaw_rad)
    pg = make_pose_graph(["a"], BackendConfig())
    times = add_chain(pg, odo)
    est = pg.estimate()["a"]
    assert est.shape == (N_LONG, 4, 4)
    np.testing.assert_allclose(est[:, :3, 3], odo[:, :3, 3], atol=1e-3)
    np.testing.assert_allclose(pg.T_shared_kf("a", N_LONG - 1), odo[-1], atol=1e-3)
    assert pg.stats().recoveries == 0
    first, last = np.median(times[500:1000]) * 1e3, np.median(times[-500:]) * 1e3
    # printed, not asserted: timings belong to `bench scale` (a loaded CI machine starved this test's last
    # 500 keyframes to 2.1 ms against 0.14 ms at 1k, where it measures 0.5 against 0.16 alone)
    print(f"{shape}: add_keyframe median {first:.3f} ms at 1k keyframes, {last:.3f} ms at 5k")


def test_cholesky_failure_is_recovered_by_rebuilding_with_qr(caplog):
    odo = chain(1500, 0.0)
    pg = MultiRobotPoseGraph(["a", "b"], odometry_sigmas=(0.01, 0.1), factorization="cholesky")
    with caplog.at_level(logging.WARNING, logger="shgm_slam.backend.pose_graph"):
        add_chain(pg, odo)
    assert pg.stats().recoveries == 1 and pg.factorization is Factorization.QR
    assert any("rebuilding the pose graph with QR" in r.getMessage() for r in caplog.records)
    np.testing.assert_allclose(pg.estimate()["a"][:, :3, 3], odo[:, :3, 3], atol=1e-3)
    # the recovered graph keeps working: robot b is placed by a closure
    pg.add_keyframe("b", 0, np.eye(4))
    pg.add_inter_robot_closure("a", 1400, "b", 0, np.eye(4))
    np.testing.assert_allclose(pg.T_shared_kf("b", 0), odo[1400], atol=1e-3)


def test_backend_error_only_when_recovery_fails_too(monkeypatch):
    pg = MultiRobotPoseGraph(["a"])
    pg.add_keyframe("a", 0, np.eye(4))

    def broken(*args, **kwargs):
        raise RuntimeError("Indeterminate linear system detected while working near variable a1")

    monkeypatch.setattr(pg._solver, "_update", broken)
    with pytest.raises(BackendError, match="rebuilding the graph with QR failed too"):
        pg.add_keyframe("a", 1, make_pose(np.eye(3), [0.0, 0.0, 1.0]))
