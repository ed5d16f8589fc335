"""Pairwise closure consistency and the maximum consistent set."""

from __future__ import annotations

import numpy as np

from shgm_slam.backend.consistency import ConsistencyThresholds, consistent_with, max_consistent_set
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y


def _chain(n: int, step: float, yaw: float, start: np.ndarray) -> np.ndarray:
    poses = [start]
    for _ in range(n - 1):
        poses.append(poses[-1] @ make_pose(rot_y(yaw), [0.0, 0.0, step]))
    return np.stack(poses)


def test_true_closures_agree_and_a_wrong_one_does_not():
    gt_a = _chain(20, 2.0, 0.05, np.eye(4))
    gt_b = _chain(20, 2.0, -0.03, make_pose(rot_y(1.0), [20.0, 0.0, 5.0]))
    odom_a, odom_b = inverse(gt_a[0]) @ gt_a, inverse(gt_b[0]) @ gt_b  # exact odometry
    path = np.arange(20) * 2.0
    pairs = [(2, 5), (8, 3), (15, 17), (19, 0)]
    T = np.stack([inverse(gt_a[i]) @ gt_b[j] for i, j in pairs])
    thr = ConsistencyThresholds()
    ok = consistent_with(T[0], 2, 5, T[1:], [8, 15, 19], [3, 17, 0], odom_a, odom_b, path, path, thr)
    assert ok.all()
    wrong = T[0] @ make_pose(rot_y(0.6), [8.0, 0.0, -3.0])
    bad = consistent_with(wrong, 2, 5, T[1:], [8, 15, 19], [3, 17, 0], odom_a, odom_b, path, path, thr)
    assert not bad.any()
    none = consistent_with(T[0], 2, 5, np.zeros((0, 4, 4)), [], [], odom_a, odom_b, path, path, thr)
    assert none.shape == (0,)


def test_tolerance_grows_with_odometry_distance():
    gt = _chain(60, 2.0, 0.0, np.eye(4))
    odom = inverse(gt[0]) @ gt
    path = np.arange(60) * 2.0
    T_near = np.eye(4)
    off = make_pose(np.eye(3), [6.0, 0.0, 0.0])  # 6 m loop error: above the 5 m base tolerance
    strict = ConsistencyThresholds(5.0, 10.0, 0.0, 0.0)
    loose = ConsistencyThresholds(5.0, 10.0, 0.05, 0.05)
    args_near = (T_near, 0, 0, off[None], [2], [2], odom, odom, path, path)
    args_far = (T_near, 0, 0, off[None], [50], [50], odom, odom, path, path)
    assert not consistent_with(*args_near, strict)[0] and not consistent_with(*args_near, loose)[0]
    assert not consistent_with(*args_far, strict)[0] and consistent_with(*args_far, loose)[0]


def test_max_consistent_set_finds_the_largest_clique_and_breaks_ties():
    n = 9
    A = np.zeros((n, n), dtype=bool)
    inliers = [1, 3, 4, 6, 8]
    A[np.ix_(inliers, inliers)] = True
    A[0, 2] = A[2, 0] = A[5, 7] = A[7, 5] = True  # small wrong cliques
    np.testing.assert_array_equal(max_consistent_set(A), inliers)
    # ties of size 2: the preferred (already accepted) set wins, then the heavier one
    B = np.zeros((4, 4), dtype=bool)
    B[0, 1] = B[1, 0] = B[2, 3] = B[3, 2] = True
    np.testing.assert_array_equal(max_consistent_set(B), [0, 1])
    np.testing.assert_array_equal(max_consistent_set(B, weights=[1, 1, 5, 1]), [2, 3])
    np.testing.assert_array_equal(
        max_consistent_set(B, weights=[1, 1, 5, 1], preferred=[True, True, False, False]), [0, 1]
    )
    assert max_consistent_set(np.zeros((0, 0), dtype=bool)).size == 0
    np.testing.assert_array_equal(max_consistent_set(np.zeros((3, 3), dtype=bool)), [0])


def test_max_consistent_set_on_a_random_graph_is_a_clique_of_planted_size():
    rng = np.random.default_rng(0)
    n = 60
    A = rng.random((n, n)) < 0.15
    A = A | A.T
    planted = rng.choice(n, 12, replace=False)
    A[np.ix_(planted, planted)] = True
    chosen = max_consistent_set(A)
    sub = A[np.ix_(chosen, chosen)] | np.eye(len(chosen), dtype=bool)
    assert sub.all() and len(chosen) >= 12
