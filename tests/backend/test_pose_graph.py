"""Multi-robot pose graph: fusion beats odometry, wrong closures are rejected, deferred anchoring, g2o."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from shgm_slam.backend.pose_graph import (
    ClosureStatus,
    Factorization,
    MultiRobotPoseGraph,
    make_pose_graph,
)
from shgm_slam.config import BackendConfig
from shgm_slam.errors import BackendError
from shgm_slam.geometry.se3 import inverse, make_pose, pose_error, rot_y, so3_exp
from shgm_slam.metrics import ate

N = 60  # keyframes per robot


def route(n: int, start: np.ndarray, step_m: float = 2.0, yaw_rad: float = 0.03) -> np.ndarray:
    """(n, 4, 4) ground-truth T_world_kf: forward steps while turning about the camera's y (down) axis."""
    poses = [start]
    for _ in range(n - 1):
        poses.append(poses[-1] @ make_pose(rot_y(yaw_rad), [0.0, 0.0, step_m]))
    return np.stack(poses)


def noisy_odometry(gt: np.ndarray, rng: np.random.Generator, sig_rad=0.004, sig_m=0.02) -> np.ndarray:
    """Integrated noisy relative motions; the odometry frame is the first keyframe (identity)."""
    delta = inverse(gt[:-1]) @ gt[1:]
    n = len(delta)
    delta = delta @ make_pose(so3_exp(rng.normal(0, sig_rad, (n, 3))), rng.normal(0, sig_m, (n, 3)))
    out = [np.eye(4)]
    for D in delta:
        out.append(out[-1] @ D)
    return np.stack(out)


def true_closures(gt_a, gt_b, rng, every=3, radius_m=6.0, sig_rad=0.02, sig_m=0.2) -> list:
    """(kf_a, kf_b, T_akf_bkf) with small noise for keyframes of a near some keyframe of b."""
    out = []
    for i in range(0, len(gt_a), every):
        dist = np.linalg.norm(gt_b[:, :3, 3] - gt_a[i, :3, 3], axis=1)
        j = int(np.argmin(dist))
        if dist[j] < radius_m:
            noise = make_pose(so3_exp(rng.normal(0, sig_rad, 3)), rng.normal(0, sig_m, 3))
            out.append((i, j, inverse(gt_a[i]) @ gt_b[j] @ noise))
    return out


def wrong_closure(rng, n_a: int, n_b: int) -> tuple:
    """A gross outlier: random keyframes, random yaw, random offset of up to 30 m."""
    t = rng.uniform(-30, 30, 3)
    t[1] = rng.normal(0, 1)
    return int(rng.integers(n_a)), int(rng.integers(n_b)), make_pose(rot_y(rng.uniform(-np.pi, np.pi)), t)


@pytest.fixture(scope="module")
def scene():
    """Robot a drives a curve; robot b drives it back in the other lane (its frame is unknown to a)."""
    rng = np.random.default_rng(0)
    gt_a = route(N, np.eye(4))
    gt_b = gt_a[::-1] @ make_pose(rot_y(np.pi), [3.0, 0.0, 0.0])
    return {
        "gt_a": gt_a, "gt_b": gt_b,
        "odo_a": noisy_odometry(gt_a, rng), "odo_b": noisy_odometry(gt_b, rng),
        "closures": true_closures(gt_a, gt_b, rng),
        "T_shared_odomb": inverse(gt_a[0]) @ gt_b[0],
    }  # fmt: skip


def run(scene, closures, **kwargs):
    """Interleave keyframes of a and b with closures as soon as both keyframes exist."""
    pg = MultiRobotPoseGraph(["a", "b"], **kwargs)
    decisions = []
    for k in range(N):
        pg.add_keyframe("a", k, scene["odo_a"][k])
        pg.add_keyframe("b", k, scene["odo_b"][k])
        for i, j, T in closures:
            if max(i, j) == k:
                decisions.append(pg.add_inter_robot_closure("a", i, "b", j, T, num_inliers=8))
    return pg, decisions


def fused_ate(scene, pg) -> float:
    est = pg.estimate()
    gt = inverse(scene["gt_a"][0]) @ np.r_[scene["gt_a"], scene["gt_b"]]
    return ate(gt, np.r_[est["a"], est["b"]], align="none").rmse


def test_two_robots_fuse_better_than_odometry_and_recover_the_frame(scene):
    pg, decisions = run(scene, scene["closures"])
    assert len(decisions) >= 15 and all(d.accepted for d in decisions)
    assert pg.is_anchored("a") and pg.is_anchored("b")
    T_true = scene["T_shared_odomb"]
    assert np.linalg.norm(T_true[:3, 3]) > 50 and np.degrees(np.arccos(T_true[0, 0])) > 45  # far apart
    err_m, err_deg = pose_error(pg.T_shared_odom("b", 0), T_true)
    assert err_m < 3.0 and err_deg < 4.0
    # odometry only, even with b placed by the TRUE frame, is worse than the fused estimate
    gt = inverse(scene["gt_a"][0]) @ np.r_[scene["gt_a"], scene["gt_b"]]
    odometry_ate = ate(gt, np.r_[scene["odo_a"], T_true @ scene["odo_b"]], align="none").rmse
    fused = fused_ate(scene, pg)
    assert fused < 0.8 * odometry_ate, (fused, odometry_ate)
    # the alignment maps the latest odometry pose onto the latest fused keyframe
    est = pg.estimate()
    np.testing.assert_allclose(pg.T_shared_odom("b") @ scene["odo_b"][-1], est["b"][-1], atol=1e-9)
    s = pg.stats()
    assert s.closures_in_graph == s.closures_accepted == len(decisions) and s.rebuilds == 0
    assert s.num_variables == 2 * N and s.num_factors == 1 + 2 * (N - 1) + len(decisions)


def test_wrong_closures_are_rejected_and_do_not_bend_the_map(scene):
    rng = np.random.default_rng(5)
    closures = list(scene["closures"])
    n_wrong = len(closures) // 3  # 25 % of all closures
    wrong = [wrong_closure(rng, N, N) for _ in range(n_wrong)]
    wrong[0] = (2, 3, wrong[0][2])  # arrives first (k = 3): it anchors b in the wrong place
    mixed = [wrong[0], *sorted(closures + wrong[1:], key=lambda c: rng.random())]
    pg, decisions = run(scene, mixed)
    clean, _ = run(scene, closures)
    assert abs(fused_ate(scene, pg) - fused_ate(scene, clean)) < 0.05
    wrong_ids = {id(c[2]) for c in wrong}
    records = pg.closures()
    for rec, c in zip(records, [c for k in range(N) for c in mixed if max(c[0], c[1]) == k], strict=True):
        expected = ClosureStatus.REJECTED if id(c[2]) in wrong_ids else ClosureStatus.ACCEPTED
        assert rec.status is expected, rec.reason
        if expected is ClosureStatus.REJECTED:
            assert "inconsistent" in rec.reason
    assert sum(not d.accepted for d in decisions) >= n_wrong - 1  # rejected on arrival (all but the first)
    assert pg.stats().rebuilds >= 1 and pg.stats().closures_rejected == n_wrong
    # the same outliers without consistency checks or robust kernel do bend the map
    naive, _ = run(scene, mixed, robust_kernel="none", consistency_trans_m=1e6, consistency_rot_deg=1e6)
    assert fused_ate(scene, naive) > 5 * fused_ate(scene, clean)


def test_closures_between_unanchored_robots_are_replayed():
    rng = np.random.default_rng(3)
    gt_a = route(N, np.eye(4))
    # c drives a's curve back in the other lane and goes on beyond a's start; b only meets c out there
    gt_c = route(2 * N, gt_a[-1] @ make_pose(rot_y(np.pi), [3.0, 0.0, 0.0]), yaw_rad=-0.03)
    gt_b = route(40, gt_c[N + 15] @ make_pose(np.eye(3), [-2.0, 0.0, 0.0]), yaw_rad=-0.03)
    gt = {"a": gt_a, "b": gt_b, "c": gt_c}
    odo = {r: noisy_odometry(g, rng) for r, g in gt.items()}
    pg = MultiRobotPoseGraph(["a", "b", "c"])
    for r in ("a", "b", "c"):
        for k in range(len(odo[r])):
            pg.add_keyframe(r, k, odo[r][k])
    bc = true_closures(gt_b, gt_c, rng)
    assert len(bc) >= 5 and not true_closures(gt_a, gt_b, rng)
    for i, j, T in bc:
        d = pg.add_inter_robot_closure("b", i, "c", j, T)
        assert d.accepted and "stored until" in d.reason
    assert not pg.is_anchored("b") and not pg.is_anchored("c") and set(pg.estimate()) == {"a"}
    with pytest.raises(BackendError, match="not anchored"):
        pg.T_shared_odom("b")
    ac = true_closures(gt_a, gt_c, rng)[:6]
    for i, j, T in ac:
        # given in (c, a) order: the graph stores it the other way round
        assert pg.add_inter_robot_closure("c", j, "a", i, inverse(T)).accepted
    assert pg.is_anchored("b") and pg.is_anchored("c")
    est = pg.estimate()
    for r in ("b", "c"):
        err = ate(inverse(gt_a[0]) @ gt[r], est[r], align="none").rmse
        assert err < 3.0, (r, err)
    assert pg.stats().closures_in_graph == len(bc) + len(ac)


def test_anchoring_places_the_buffered_keyframes_through_the_closure(scene):
    """T_shared_odomB = T_shared_ai · T_ai_bj · T_odomB_bj⁻¹, whichever side of the closure is anchored."""
    pg = MultiRobotPoseGraph(["a", "b", "c"], extra_updates=0)
    odo = {"a": scene["odo_a"], "b": scene["odo_b"], "c": scene["odo_b"] @ make_pose(rot_y(0.3), [1.0, 0, 0])}
    for r in "abc":
        for k in range(10):
            pg.add_keyframe(r, k, odo[r][k])
    assert pg.anchor("a").closure_id is None
    T_ac = make_pose(rot_y(2.0), [5.0, 0.5, -7.0])
    T_shared_odomc = pg.T_shared_kf("a", 4) @ T_ac @ inverse(odo["c"][6])
    d = pg.add_inter_robot_closure("a", 4, "c", 6, T_ac)  # c anchored through a (c: the b side)
    assert pg.anchor("c").closure_id == d.closure_id
    np.testing.assert_allclose(pg.anchor("c").T_shared_odom, T_shared_odomc, atol=1e-9)
    np.testing.assert_allclose(pg.estimate()["c"], T_shared_odomc @ odo["c"][:10], atol=1e-6)
    T_bc = make_pose(rot_y(-1.0), [2.0, 0.0, 3.0])
    T_shared_odomb = pg.T_shared_kf("c", 8) @ inverse(T_bc) @ inverse(odo["b"][2])
    pg.add_inter_robot_closure("b", 2, "c", 8, T_bc)  # b anchored through c (b: the a side)
    np.testing.assert_allclose(pg.anchor("b").T_shared_odom, T_shared_odomb, atol=1e-9)
    np.testing.assert_allclose(pg.estimate()["b"], T_shared_odomb @ odo["b"][:10], atol=1e-6)
    np.testing.assert_allclose(pg.T_shared_odom("b", 0), T_shared_odomb, atol=1e-6)


def test_anchoring_can_require_confirmation(scene):
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    for k in range(N):
        pg.add_keyframe("a", k, scene["odo_a"][k])
        pg.add_keyframe("b", k, scene["odo_b"][k])
    (i, j, T), (k, l, T2) = scene["closures"][:2]
    first = pg.add_inter_robot_closure("a", i, "b", j, T)
    assert first.accepted and "waiting for consistent closures from 2 matches" in first.reason
    assert not pg.is_anchored("b")
    assert pg.add_inter_robot_closure("a", k, "b", l, T2).accepted
    assert pg.is_anchored("b") and pg.stats().closures_in_graph == 2


@pytest.mark.parametrize("factorization", [Factorization.CHOLESKY, Factorization.QR])
def test_deferred_initialisation_works_with_either_factorization(scene, factorization):
    pg = MultiRobotPoseGraph(["a", "b"], factorization=factorization)
    for k in range(N):  # all of b's keyframes arrive before any closure
        pg.add_keyframe("a", k, scene["odo_a"][k])
        pg.add_keyframe("b", k, scene["odo_b"][k])
    assert not pg.is_anchored("b") and pg.stats().num_variables == N
    for i, j, T in scene["closures"]:
        pg.add_inter_robot_closure("a", i, "b", j, T)
    assert pg.stats().num_variables == 2 * N
    assert fused_ate(scene, pg) < 1.0


def test_flipped_closures_with_information_give_the_same_graph(scene):
    info = np.diag([400.0, 900.0, 100.0, 4.0, 1.0, 9.0])  # anisotropic, gtsam order [rot, trans]
    ab = MultiRobotPoseGraph(["a", "b"], robust_kernel="none")
    ba = MultiRobotPoseGraph(["a", "b"], robust_kernel="none")
    for k in range(N):
        for pg in (ab, ba):
            pg.add_keyframe("a", k, scene["odo_a"][k])
            pg.add_keyframe("b", k, scene["odo_b"][k])
    for i, j, T in scene["closures"]:
        ab.add_inter_robot_closure("a", i, "b", j, T, information=info)
        Ad = gtsam.Pose3(gtsam.Rot3.ClosestTo(T[:3, :3]), T[:3, 3]).AdjointMap()  # info of T⁻¹
        info_inv = np.linalg.inv(Ad @ np.linalg.inv(info) @ Ad.T)
        ba.add_inter_robot_closure("b", j, "a", i, inverse(T), information=info_inv)
    for r in ("a", "b"):
        np.testing.assert_allclose(ab.estimate()[r], ba.estimate()[r], atol=1e-6)


def test_g2o_file_is_readable_by_gtsam(scene, tmp_path):
    pg, decisions = run(scene, scene["closures"][:5])
    path = tmp_path / "out" / "graph.g2o"
    pg.write_g2o(path)
    graph, values = gtsam.readG2o(str(path), True)
    assert values.size() == 2 * N
    assert graph.size() == 2 * (N - 1) + len(decisions)
    assert {gtsam.Symbol(k).string() for k in values.keys()} >= {"a0", "a59", "b0", "b59"}
    np.testing.assert_allclose(
        values.atPose3(gtsam.symbol("b", 7)).matrix(), pg.estimate()["b"][7], atol=1e-6
    )


def test_factory_and_bad_input():
    pg = make_pose_graph(["x", "y"], BackendConfig(robust_kernel="huber"))
    assert pg.robust_kernel.value == "huber"
    pg.add_keyframe("x", 0, np.eye(4))
    pg.add_keyframe("y", 0, np.eye(4))
    with pytest.raises(BackendError, match="out of order: expected keyframe 1"):
        pg.add_keyframe("x", 2, np.eye(4))
    with pytest.raises(BackendError, match="unknown robot 'z'"):
        pg.add_keyframe("z", 0, np.eye(4))
    with pytest.raises(BackendError, match="finite"):
        pg.add_keyframe("x", 1, np.full((4, 4), np.nan))
    with pytest.raises(BackendError, match="keyframe 3 of y, which has only 1"):
        pg.add_inter_robot_closure("x", 0, "y", 3, np.eye(4))
    with pytest.raises(BackendError, match="itself"):
        pg.add_inter_robot_closure("x", 0, "x", 0, np.eye(4))
    with pytest.raises(BackendError, match="positive definite"):
        pg.add_inter_robot_closure("x", 0, "y", 0, np.eye(4), information=-np.eye(6))
    with pytest.raises(BackendError, match="robust kernels"):
        MultiRobotPoseGraph(["x"], robust_kernel="l1")
    with pytest.raises(BackendError, match="at least one robot"):
        MultiRobotPoseGraph([])


def test_kitti00_geometry_two_robots_with_outliers(shared_data):
    """Real KITTI 00 ground truth split into two robots that revisit the same streets (noisy odometry)."""
    from shgm_slam.io.trajectories import read_kitti_poses

    kf = read_kitti_poses(shared_data / "kitti" / "poses" / "00.txt")[::5]  # a keyframe every ~4 m
    gt_a, gt_b = kf[0:300], kf[640:]  # frames 0-1495 and 3200-4540
    rng = np.random.default_rng(0)
    odo_a, odo_b = noisy_odometry(gt_a, rng), noisy_odometry(gt_b, rng)
    closures = true_closures(gt_a, gt_b, rng, every=5, radius_m=8.0)
    wrong = [wrong_closure(rng, len(gt_a), len(gt_b)) for _ in range(len(closures) // 3)]
    mixed = sorted(closures + wrong, key=lambda c: rng.random())
    pg = MultiRobotPoseGraph(["a", "b"])
    for k in range(max(len(gt_a), len(gt_b))):
        for r, odo in (("a", odo_a), ("b", odo_b)):
            if k < len(odo):
                pg.add_keyframe(r, k, odo[k])
        for i, j, T in mixed:
            if max(i, j) == k:
                pg.add_inter_robot_closure("a", i, "b", j, T)
    assert len(closures) >= 20 and pg.stats().closures_rejected == len(wrong)
    est = pg.estimate()
    gt = inverse(gt_a[0]) @ np.r_[gt_a, gt_b]
    fused = ate(gt, np.r_[est["a"], est["b"]], align="none").rmse
    odometry = ate(gt, np.r_[odo_a, inverse(gt_a[0]) @ gt_b[0] @ odo_b], align="none").rmse
    assert fused < 0.7 * odometry, (fused, odometry)
    assert ate(gt_b, est["b"]).rmse < ate(gt_b, odo_b).rmse  # b's shape improves too


def test_backend_config_sets_the_anchoring_threshold():
    assert make_pose_graph(["a", "b"], BackendConfig()).min_closures_to_anchor == 2
    assert BackendConfig.model_validate({"min_closures_to_anchor": None}).min_closures_to_anchor == 2  # old dumps
    assert make_pose_graph(["a", "b"], BackendConfig(min_closures_to_anchor=3)).min_closures_to_anchor == 3


def test_closures_of_one_match_do_not_confirm_each_other():
    """With min_closures_to_anchor=2, two closures cut from ONE match do not anchor; a second match does."""
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    for k in range(4):
        pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
    pg.add_inter_robot_closure("a", 0, "b", 0, np.eye(4), num_inliers=20, match_id=1)
    pg.add_inter_robot_closure("a", 2, "b", 2, np.eye(4), num_inliers=20, match_id=1)
    assert not pg.is_anchored("b")
    pg.add_inter_robot_closure("a", 1, "b", 1, np.eye(4), num_inliers=20, match_id=2)
    assert pg.is_anchored("b")


def test_matches_that_share_objects_do_not_anchor_and_object_disjoint_ones_do():
    """With min_closures_to_anchor=2, a second match that finds some of the first match's objects again (an
    aliased street re-found at the next matching step) does not anchor b; a match on other objects does."""
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    for k in range(6):
        pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
    first = {("a", 1), ("a", 2), ("b", 1), ("b", 2)}
    pg.add_inter_robot_closure("a", 0, "b", 0, np.eye(4), match_id=1, support=first)
    pg.add_inter_robot_closure("a", 1, "b", 1, np.eye(4), match_id=2, support={("a", 2), ("a", 3), ("b", 3)})
    assert pg.evidence_between("a", "b") == 1 and not pg.is_anchored("b")
    pg.add_inter_robot_closure("a", 4, "b", 4, np.eye(4), match_id=3, support={("a", 7), ("b", 7)})
    assert pg.evidence_between("b", "a") == 2 and pg.is_anchored("b")


def test_a_decisive_match_anchors_alone_and_a_plain_one_or_a_loop_closure_does_not():
    """With min_closures_to_anchor=2 one match waits for a second on other objects, unless the map server marks it
    decisive (its evidence alone is that of two pieces): then its first accepted closure anchors the robot. Its
    place still rests on one piece of evidence. A loop closure never anchors, decisive or not."""
    for decisive in (False, True):
        pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
        for k in range(6):
            pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
            pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_inter_robot_closure("b", 1, "b", 4, make_pose(np.eye(3), [0.0, 0.0, 6.0]), match_id=1, decisive=True)
        assert not pg.is_anchored("b") and not pg.closures()[0].decisive
        decision = pg.add_inter_robot_closure("a", 2, "b", 2, np.eye(4), match_id=2, support={("a", 1), ("b", 1)},
                                              decisive=decisive)  # fmt: skip
        assert decision.accepted and pg.is_anchored("b") == decisive
        assert pg.evidence_between("a", "b") == 1
        assert pg.anchor_closure("b") == (decision.closure_id if decisive else None)


def test_one_match_cut_into_many_closures_does_not_outvote_two_independent_matches():
    """b drives beside a's track (true offset 0): two matches agree on it; one alias match, cut into three
    mutually consistent closures, puts b 40 m further along. The independent matches win."""
    pg = MultiRobotPoseGraph(["a", "b"])
    for k in range(30):
        pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
    alias = make_pose(np.eye(3), [0.0, 0.0, 40.0])
    pg.add_inter_robot_closure("a", 2, "b", 2, np.eye(4), num_inliers=15, match_id=1)
    for k in (4, 6, 8):
        pg.add_inter_robot_closure("a", k + 20, "b", k, alias, num_inliers=30, match_id=2)
    pg.add_inter_robot_closure("a", 12, "b", 12, np.eye(4), num_inliers=15, match_id=3)
    accepted = [(c.kf_a, c.kf_b) for c in pg.closures() if c.status is ClosureStatus.ACCEPTED]
    assert accepted == [(2, 2), (12, 12)]
    assert np.linalg.norm(pg.estimate()["b"][5][:3, 3] - [0.0, 0.0, 10.0]) < 0.5


def test_agent_added_at_run_time_is_placed_by_closures_to_its_own_robots_earlier_segment(scene):
    """A robot's odometry fails halfway: its second segment is a new agent with an unknown frame, placed by
    closures to the first segment (the robot's own past) and to another robot, like any robot."""
    half = N // 2
    gt_a, odo_b = scene["gt_a"], scene["odo_b"]
    gt_a2 = gt_a[half:]  # segment 2 of a: odometry restarts at keyframe `half`
    odo_a2 = inverse(scene["odo_a"][half]) @ scene["odo_a"][half:]
    pg = MultiRobotPoseGraph(["a", "b"])
    for k in range(half):
        pg.add_keyframe("a", k, scene["odo_a"][k])
    for k in range(N):
        pg.add_keyframe("b", k, odo_b[k])
    for i, j, T in scene["closures"]:
        if i < half:
            pg.add_inter_robot_closure("a", i, "b", j, T, num_inliers=8)
    with pytest.raises(BackendError, match="unknown robot"):
        pg.add_keyframe("a#1", 0, np.eye(4))
    pg.add_robot("a#1")
    assert not pg.is_anchored("a#1")
    for k in range(len(odo_a2)):
        pg.add_keyframe("a#1", k, odo_a2[k])
    # closures of the new segment to b (true ones) and to its own earlier segment (an overlap of 1 keyframe)
    gt_b = scene["gt_b"]
    for i, j, T in true_closures(gt_a2, gt_b, np.random.default_rng(7)):
        pg.add_inter_robot_closure("a#1", i, "b", j, T, num_inliers=8)
    pg.add_inter_robot_closure("a", half - 1, "a#1", 0, inverse(gt_a[half - 1]) @ gt_a2[0], num_inliers=8)
    assert pg.is_anchored("a#1")
    est = pg.estimate()["a#1"]
    err = np.linalg.norm(est[:, :3, 3] - (inverse(gt_a[0]) @ gt_a2)[:, :3, 3], axis=1)
    assert err.max() < 3.0, err
    assert gtsam.Symbol(pg.keys.key("a#1", 0)).string() == "c0"
    assert "c0" in {gtsam.Symbol(int(line.split()[1])).string() for line in pg.to_g2o().splitlines()
                    if line.startswith("VERTEX")}  # fmt: skip
    # the file says which agent each key letter is (nothing in the results folder did)
    assert pg.to_g2o().splitlines()[0] == "# agents (gtsam symbol letter): a=a b=b c=a#1"


def test_closure_keyframes_and_independent_evidence_between_robots():
    gt = route(30, np.eye(4))
    pg = MultiRobotPoseGraph(["a", "b", "c"])
    for r in ("a", "b", "c"):
        for k, T in enumerate(gt):
            pg.add_keyframe(r, k, T)
    assert pg.closure_keyframes("a").tolist() == [0]  # the prior ties the shared frame's first keyframe
    assert pg.closure_keyframes("b").size == 0 and pg.evidence_between("a", "b") == 0
    same = inverse(gt[5]) @ gt[5]
    for kf in (5, 12):  # two closures cut from one match: one source of evidence
        assert pg.add_inter_robot_closure("a", kf, "b", kf, same, num_inliers=8, match_id=1).accepted
    assert pg.evidence_between("a", "b") == pg.evidence_between("b", "a") == 1
    assert pg.add_inter_robot_closure("b", 20, "a", 20, same, num_inliers=8, match_id=2).accepted
    assert pg.evidence_between("a", "b") == 2 and pg.evidence_between("a", "c") == 0
    assert pg.closure_keyframes("a").tolist() == [0, 5, 12, 20]
    assert pg.closure_keyframes("b").tolist() == [5, 12, 20]


def test_closures_of_one_match_update_once_and_give_the_same_estimate(scene):
    rng = np.random.default_rng(7)
    closures = scene["closures"]
    one_by_one, _ = run(scene, closures)
    pg = MultiRobotPoseGraph(["a", "b"])
    for k in range(N):
        pg.add_keyframe("a", k, scene["odo_a"][k])
        pg.add_keyframe("b", k, scene["odo_b"][k])
    for m, group in enumerate((closures[: len(closures) // 2], closures[len(closures) // 2 :])):
        for kf_a, kf_b, T in group:
            pg.add_inter_robot_closure("a", kf_a, "b", kf_b, T, num_inliers=10, match_id=m, update=False)
        pg.update()
    # wrong first, then outvoted inside one batch: its pending factor is removed cleanly
    bad = MultiRobotPoseGraph(["a", "b"])
    for k in range(N):
        bad.add_keyframe("a", k, scene["odo_a"][k])
        bad.add_keyframe("b", k, scene["odo_b"][k])
    i, j, T_wrong = wrong_closure(rng, N, N)
    bad.add_inter_robot_closure("a", i, "b", j, T_wrong, num_inliers=30, match_id=0, update=False)
    for kf_a, kf_b, T in closures[:6]:
        bad.add_inter_robot_closure("a", kf_a, "b", kf_b, T, num_inliers=10, match_id=1, update=False)
    bad.update()
    reference = fused_ate(scene, one_by_one)
    assert fused_ate(scene, pg) == pytest.approx(reference, abs=0.1)
    assert fused_ate(scene, bad) == pytest.approx(fused_ate(scene, run(scene, closures[:6])[0]), abs=0.2)
    assert bad.closures()[0].status is ClosureStatus.REJECTED and not bad.closures()[0].in_graph


def test_odometry_sigmas_grow_with_the_distance_driven():
    pg = MultiRobotPoseGraph(["a"], odometry_sigmas=(0.001, 0.01), odometry_drift=(0.002, 0.02))
    steps = [0.0, 1.0, 3.0]
    T = np.eye(4)
    pg.add_keyframe("a", 0, T)
    for k, step in enumerate(steps[1:], start=1):
        T = T @ make_pose(np.eye(3), np.array([0.0, 0.0, step]))
        pg.add_keyframe("a", k, T)
    edges = [line.split() for line in pg.to_g2o().splitlines() if line.startswith("EDGE")]
    trans_info = [float(e[10]) for e in edges]  # first information entry: x translation
    expected = [1.0 / (0.01 + 0.02 * s) ** 2 for s in steps[1:]]
    np.testing.assert_allclose(trans_info, expected, rtol=1e-4)
    with pytest.raises(BackendError, match="drift"):
        MultiRobotPoseGraph(["a"], odometry_drift=(-1.0, 0.0))


@pytest.mark.parametrize("threshold", [(0.0, 0.2), (1e-3, -1.0), (math.nan, 0.2), (0.1,)])
def test_relinearize_threshold_must_be_two_positive_values(threshold):
    with pytest.raises(BackendError, match="relinearize_threshold"):
        MultiRobotPoseGraph(["a"], relinearize_threshold=threshold)


def test_converge_gives_the_same_estimate_whatever_order_things_arrived_in(scene):
    """The same keyframes and closures, interleaved or all of a first: iSAM2's estimates differ (it
    relinearizes only what moved beyond its threshold), the converged ones agree, and converge lowers
    the graph's error."""
    interleaved, _ = run(scene, scene["closures"])
    a_first = MultiRobotPoseGraph(["a", "b"])
    for k in range(N):
        a_first.add_keyframe("a", k, scene["odo_a"][k])
    for k in range(N):
        a_first.add_keyframe("b", k, scene["odo_b"][k])
    for i, j, T in scene["closures"]:
        a_first.add_inter_robot_closure("a", i, "b", j, T, num_inliers=8)
    before = {r: interleaved.estimate()[r].copy() for r in ("a", "b")}
    error_before = interleaved.graph_error()
    assert interleaved.converge() > 0 and a_first.converge() > 0
    assert 0.0 < interleaved.graph_error() < error_before
    for r in ("a", "b"):
        np.testing.assert_allclose(interleaved.estimate()[r][:, :3, 3], a_first.estimate()[r][:, :3, 3], atol=2e-3)
        k = N // 2
        np.testing.assert_allclose(interleaved.T_shared_kf(r, k), interleaved.estimate()[r][k])
    assert fused_ate(scene, interleaved) == pytest.approx(fused_ate(scene, run(scene, scene["closures"])[0]), abs=0.05)
    moved = max(np.abs(interleaved.estimate()[r][:, :3, 3] - before[r][:, :3, 3]).max() for r in ("a", "b"))
    assert moved > 0  # the solution did change, and a new keyframe hands the answers back to iSAM2
    interleaved.add_keyframe("a", N, scene["odo_a"][-1])
    assert len(interleaved.estimate()["a"]) == N + 1
    assert MultiRobotPoseGraph(["a"]).converge() == 0
    assert MultiRobotPoseGraph(["a"]).graph_error() == 0.0


def test_anchorings_keep_a_robot_once_placed_through_a_closure_that_was_withdrawn():
    """b is first anchored through an alias (b 40 m further along); two independent true matches outvote
    it: b is anchored again through a true closure, and the history keeps both, in order, each once."""
    pg = MultiRobotPoseGraph(["a", "b"])
    for k in range(30):
        pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
    assert pg.anchorings() == [] and pg.anchor_closure("a") is None
    alias = make_pose(np.eye(3), [0.0, 0.0, 40.0])
    first = pg.add_inter_robot_closure("a", 24, "b", 4, alias, num_inliers=30, match_id=1)
    assert pg.anchor_closure("b") == first.closure_id
    pg.add_inter_robot_closure("a", 2, "b", 2, np.eye(4), num_inliers=15, match_id=2)
    pg.add_inter_robot_closure("a", 12, "b", 12, np.eye(4), num_inliers=15, match_id=3)
    history = pg.anchorings()
    assert [robot for robot, _ in history] == ["b", "b"]
    assert history[0][1].closure_id == first.closure_id and history[0][1].status is ClosureStatus.REJECTED
    assert history[1][1].status is ClosureStatus.ACCEPTED and pg.anchor_closure("b") == history[1][1].closure_id
    assert np.linalg.norm(pg.estimate()["b"][5][:3, 3] - [0.0, 0.0, 10.0]) < 0.5


def test_a_decisive_match_that_refinds_the_true_objects_outvotes_two_alias_matches():
    """b drives a's street (true offset 0). Two alias matches on disjoint objects put b 80 m further along and
    place it there (two pieces). The right matches all find the same true objects (one piece however many), but
    one of them is decisive: it counts the two pieces it anchors with, its set has more closures, and b moves
    to its true place (airsim-like files, seed 569: car2 310 m off until the end)."""
    pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
    for k in range(40):
        pg.add_keyframe("a", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
        pg.add_keyframe("b", k, make_pose(np.eye(3), [0.0, 0.0, 2.0 * k]))
    alias = make_pose(np.eye(3), [0.0, 0.0, 80.0])
    for match, k, objects in ((1, 2, {("a", 1), ("a", 2)}), (2, 4, {("a", 3), ("a", 4)})):
        pg.add_inter_robot_closure("a", k, "b", k, alias, num_inliers=15, match_id=match, support=objects)
    assert pg.is_anchored("b")
    assert np.linalg.norm(pg.estimate()["b"][5][:3, 3] - [0.0, 0.0, 90.0]) < 0.5  # placed by the alias
    truth = {("a", 10), ("a", 11), ("a", 12)}
    pg.add_inter_robot_closure("a", 10, "b", 10, np.eye(4), num_inliers=20, match_id=3, support=truth)
    for k in (12, 14, 16, 18):  # the whole overlap matched: decisive, the same true objects
        pg.add_inter_robot_closure("a", k, "b", k, np.eye(4), num_inliers=40, match_id=4, support=truth, decisive=True)
    accepted = sorted(c.kf_b for c in pg.closures() if c.status is ClosureStatus.ACCEPTED)
    assert accepted == [10, 12, 14, 16, 18]
    assert np.linalg.norm(pg.estimate()["b"][5][:3, 3] - [0.0, 0.0, 10.0]) < 0.5
