"""The pose-graph estimate is cached per graph version and stays correct after every change."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y
from tests.backend.test_pose_graph import N, noisy_odometry, route, run, true_closures


@pytest.fixture(scope="module")
def scene():
    """Robot a drives a curve, robot b drives it back in the other lane (as in test_pose_graph)."""
    rng = np.random.default_rng(3)
    gt_a = route(N, np.eye(4))
    gt_b = gt_a[::-1] @ make_pose(rot_y(np.pi), [3.0, 0.0, 0.0])
    odo_a, odo_b = noisy_odometry(gt_a, rng), noisy_odometry(gt_b, rng)
    return {"odo_a": odo_a, "odo_b": odo_b, "closures": true_closures(gt_a, gt_b, rng)}


def fresh(pg: MultiRobotPoseGraph) -> dict[str, np.ndarray]:
    """The estimate read key by key from iSAM2 (the uncached reference)."""
    values = pg._solver.estimate()
    return {
        name: np.stack([values.atPose3(pg.keys.key(name, k)).matrix() for k in range(len(est))])
        for name, est in pg.estimate().items()
    }


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_allclose(a[name], b[name], atol=1e-9)


def test_estimate_is_cached_until_the_graph_changes(scene):
    pg, _ = run(scene, scene["closures"])
    first, second = pg.estimate(), pg.estimate()
    assert first["a"] is second["a"] and first["b"] is second["b"]  # no recomputation
    assert not first["a"].flags.writeable
    with pytest.raises(ValueError):
        first["a"][0, 0, 0] = 1.0
    assert_same(first, fresh(pg))
    for k in (0, N // 2, N - 1):
        np.testing.assert_allclose(pg.T_shared_kf("b", k), first["b"][k], atol=1e-12)
    np.testing.assert_allclose(pg.T_shared_odom("b"), first["b"][-1] @ inverse(scene["odo_b"][-1]), atol=1e-9)
    version = pg.version

    # a new keyframe invalidates the cache: the new keyframe appears, the others stay right
    pg.add_keyframe("a", N, scene["odo_a"][-1] @ make_pose(rot_y(0.03), [0.0, 0.0, 2.0]))
    assert pg.version > version
    after = pg.estimate()
    assert after["a"].shape == (N + 1, 4, 4) and after["a"] is not first["a"]
    assert_same(after, fresh(pg))

    # so does a closure
    i, j, T = scene["closures"][0]
    pg.add_inter_robot_closure("a", i, "b", j, T, num_inliers=8)
    assert_same(pg.estimate(), fresh(pg))


def test_uncached_single_pose_matches_the_estimate(scene):
    pg, _ = run(scene, scene["closures"][:5])
    pg.add_keyframe("a", N, scene["odo_a"][-1])  # the cache is stale now
    T = pg.T_shared_kf("a", N // 3)  # read from iSAM2 directly, without a full recomputation
    np.testing.assert_allclose(T, pg.estimate()["a"][N // 3], atol=1e-12)


def test_unanchored_robot_keyframes_do_not_change_the_estimate():
    pg = MultiRobotPoseGraph(["a", "b"])
    pg.add_keyframe("a", 0, np.eye(4))
    before = pg.estimate()
    pg.add_keyframe("b", 0, np.eye(4))
    assert pg.estimate().keys() == {"a"}
    np.testing.assert_allclose(pg.estimate()["a"], before["a"])
