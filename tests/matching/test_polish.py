"""The accepted alignment's robust refit: it corrects a yaw that wrong partners pulled, never a decision."""

from __future__ import annotations

import numpy as np

from shgm_slam.config import DescriptorConfig, MatchingConfig
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y, transform_points
from shgm_slam.matching import match_graphs
from shgm_slam.matching.labelled_tree import LabelledTree
from shgm_slam.matching.polish import MIN_SCALE_M, TUKEY_C, biweight, polish_alignment
from shgm_slam.matching.pose import fit_pose
from shgm_slam.matching.verification import partner_pairs

from .synthetic import city_pair, graph_of

UP = np.array([0.0, -1.0, 0.0])  # KITTI camera frame: y down


def _street(seed: int) -> tuple:
    """A 60 m street (objects every 4 m along x, either side; KITTI frame: x-z ground, up -y) mapped by A,
    and B, which missed four objects on the street's +z side and instead mapped four A missed, each 4 m
    from one it missed, of the same label (0.4 m noise): four wrong partners a 6 m gate takes in, all on
    one side. Returns (a, b, T_a_b true)."""
    rng = np.random.default_rng(seed)
    x = np.arange(0.0, 60.0, 4.0)
    side = np.where(np.arange(x.size) % 2 == 0, -6.0, 6.0)
    world = np.stack([x, -rng.uniform(0.0, 4.0, x.size), side], axis=1)
    labels = np.tile(np.array([5, 7, 8], dtype=np.int64), x.size)[: x.size]
    decoy_rows = np.flatnonzero(side > 0)[-4:]
    decoys = world[decoy_rows] + np.array([4.0, 0.0, 0.0])
    pos_a = world + rng.normal(0.0, 0.4, world.shape)
    seen_b = np.setdiff1d(np.arange(x.size), decoy_rows)
    pos_b_world = np.vstack([world[seen_b] + rng.normal(0.0, 0.4, (seen_b.size, 3)), decoys])
    labels_b = np.concatenate([labels[seen_b], labels[decoy_rows]])
    T_b_world = make_pose(rot_y(0.7), np.array([30.0, 0.0, -12.0]))
    pos_b = transform_points(T_b_world, pos_b_world)
    ones_a, ones_b = np.ones(len(pos_a)), np.ones(len(pos_b))
    a = graph_of(pos_a, labels, ones_a, np.arange(len(pos_a)))
    b = graph_of(pos_b, labels_b, ones_b, np.arange(len(pos_b)) + 1000)
    return a, b, inverse(T_b_world)


def _displacement_m(T_est: np.ndarray, T_true: np.ndarray, b) -> float:
    """Largest distance between B's nodes mapped by the estimate and by the truth, metres."""
    p = b.positions_xyz
    return float(np.linalg.norm(transform_points(T_est, p) - transform_points(T_true, p), axis=1).max())


def test_biweight_is_one_at_zero_zero_beyond_its_data_scaled_cutoff_and_decreasing() -> None:
    d = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 50.0])
    w = biweight(d)
    cutoff = TUKEY_C * max(float(np.median(d)), MIN_SCALE_M)
    assert w[0] == 1.0 and np.all(np.diff(w) <= 0)
    assert np.all(w[d >= cutoff] == 0.0) and np.all(w[d < cutoff] > 0.0)
    assert biweight(np.zeros(0)).shape == (0,)
    # exact partners: the floor keeps a fit (every weight 1, not 0/0)
    assert np.all(biweight(np.zeros(5)) == 1.0)


def test_wrong_partners_in_the_gate_do_not_pull_the_polished_alignment() -> None:
    off, off_ls = [], []
    for seed in range(3, 9):
        a, b, T_true = _street(seed)
        tree_a = LabelledTree(a.positions_xyz, a.label_ids)
        T_start = T_true @ make_pose(rot_y(np.radians(2.0)), np.zeros(3))  # 2 deg off: 2 m at the street's end
        T = polish_alignment(T_start, a, b, tree_a, 3.0, gravity_aligned=True, up=UP)
        # the plain least-squares fit on the same gate's partners at the truth keeps the four wrong ones
        pairs, _ = partner_pairs(tree_a, transform_points(T_true, b.positions_xyz), b.label_ids, 6.0)
        T_ls = fit_pose(b.positions_xyz[pairs[:, 1]], a.positions_xyz[pairs[:, 0]], None, True, UP)
        off.append(_displacement_m(T, T_true, b))
        off_ls.append(_displacement_m(T_ls, T_true, b))
    assert np.all(np.array(off) < np.array(off_ls)), (off, off_ls)
    assert np.mean(off) < 0.6 and np.mean(off) < 0.5 * np.mean(off_ls), (off, off_ls)


def test_the_polish_changes_the_transform_of_an_accepted_match_but_never_its_decision() -> None:
    a, b, T_true = city_pair(seed=4, noise_m=0.8)
    base = MatchingConfig(gravity_aligned=True)
    on = match_graphs(a, b, DescriptorConfig(), base)
    off = match_graphs(a, b, DescriptorConfig(), base.model_copy(update={"polish": False}))
    assert on.success and off.success
    assert on.llr == off.llr and on.llr_threshold == off.llr_threshold
    assert np.array_equal(on.inliers, off.inliers) and on.rmse_m == off.rmse_m
    assert not np.array_equal(on.T_a_b, off.T_a_b)
    np.testing.assert_array_equal(on.T_a_b_hypothesis, on.T_a_b)
    centroid = b.positions_xyz.mean(axis=0, keepdims=True)
    err_on = np.linalg.norm(transform_points(on.T_a_b, centroid) - transform_points(T_true, centroid))
    assert err_on < 0.5


def test_too_few_partners_leave_the_alignment_as_it_was() -> None:
    a, b, T_true = _street(seed=5)
    far = T_true @ make_pose(np.eye(3), np.array([500.0, 0.0, 0.0]))  # nothing of B lands near A
    tree_a = LabelledTree(a.positions_xyz, a.label_ids)
    T = polish_alignment(far, a, b, tree_a, 3.0, gravity_aligned=True, up=UP)
    np.testing.assert_array_equal(T, far)
