"""Hybrid odometry on the exactly rendered corridor: follows the path on true depth, hands the step to
the visual odometry when the depth flickers; KISS-ICP's fused-step hook keeps what it is given."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import OdometryConfig, OdometryKind
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import inverse, make_pose, rot_y
from shgm_slam.metrics import AlignMode, ate
from shgm_slam.odometry.clouds import depth_to_cloud
from shgm_slam.odometry.hybrid import HybridOdometrySource
from shgm_slam.odometry.kiss import KissOdometry
from shgm_slam.odometry.sources import make_odometry
from shgm_slam.types import Frame
from tests.odometry.corridor import INTRINSICS, path, render

STRIDE = 2


def config(kind: OdometryKind, **overrides) -> OdometryConfig:
    """The corridor's camera slides sideways as it weaves (not a car's planar circular motion)."""
    return OdometryConfig(kind=kind, voxel_size_m=0.5, max_range_m=60.0, cloud_stride=STRIDE, shuffle_points=False,
                          visual_max_depth_m=60.0, visual_depth_window_px=1, visual_planar_motion=False,
                          **overrides)  # fmt: skip


def run(kind: OdometryKind, poses: np.ndarray, depth_fn=lambda d, i: d, **overrides):
    src = make_odometry(config(kind, **overrides), len(poses))
    est, weights = [], []
    for i, T in enumerate(poses):
        gray, depth = render(T)
        depth = depth_fn(depth, i)
        frame = Frame(i, 0.1 * i, INTRINSICS, image_rgb=np.repeat(gray[..., None], 3, axis=2))
        pts, _ = depth_to_cloud(depth, INTRINSICS, stride=STRIDE, min_range_m=0.5, max_range_m=60.0)
        est.append(src.update(frame, pts, depth).T_odom_cam)
        weights.append(getattr(src, "icp_weight", np.nan))
    gt = inverse(poses[0]) @ poses
    return np.stack(est), gt, np.array(weights)


@pytest.fixture(scope="module")
def corridor() -> np.ndarray:
    return path(40, step_m=0.8)


def test_true_depth_follows_the_corridor_where_icp_alone_cannot(corridor):
    est, gt, weights = run(OdometryKind.HYBRID, corridor)
    assert ate(gt, est, align=AlignMode.NONE).rmse < 0.3
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.6  # over 31 m
    # four flat walls: nothing along the corridor for ICP to hold on to; its turns are noisy too, so the
    # visual odometry carries the steps
    icp_alone, _, _ = run(OdometryKind.KISS_ICP, corridor, image_flow_check=False)
    assert ate(gt, icp_alone, align=AlignMode.NONE).rmse > 5.0
    assert np.nanmean(weights[20:]) < 0.5
    # KISS-ICP checked against the image motion (the default) keeps the steps the image tracks give where it slips
    kiss, _, _ = run(OdometryKind.KISS_ICP, corridor)
    assert ate(gt, kiss, align=AlignMode.NONE).rmse < 0.3


def flicker(depth: np.ndarray, i: int) -> np.ndarray:
    """Depth whose left and right halves are scaled differently every frame (a network's flicker):
    the cloud's walls move against each other, which turns an ICP registration."""
    rng = np.random.default_rng(100 + i)
    left, right = np.exp(rng.normal(0, 0.08, 2))
    scale = np.where(np.arange(depth.shape[1]) < depth.shape[1] // 2, left, right).astype(np.float32)
    return depth * scale[None, :]


def test_flickering_depth_hands_the_step_to_the_visual_odometry(corridor):
    kiss, gt, _ = run(OdometryKind.KISS_ICP, corridor, flicker, image_flow_check=False)
    visual, _, _ = run(OdometryKind.VISUAL, corridor, flicker)
    hybrid, _, weights = run(OdometryKind.HYBRID, corridor, flicker)
    checked, _, _ = run(OdometryKind.KISS_ICP, corridor, flicker)  # KISS-ICP's slips replaced by image steps
    err = {name: ate(gt, e, align=AlignMode.NONE).rmse for name, e in
           (("kiss", kiss), ("visual", visual), ("hybrid", hybrid), ("checked", checked))}  # fmt: skip
    assert np.nanmean(weights[20:]) < 0.5  # ICP's turns are the noisier ones
    assert err["hybrid"] < 0.2 * err["kiss"]
    assert err["hybrid"] < 1.5 * err["visual"] + 0.1
    assert err["checked"] < 0.2 * err["kiss"]


def test_kiss_keeps_the_fused_step_it_is_given():
    _, depth = render(np.eye(4))
    pts, _ = depth_to_cloud(depth, INTRINSICS, stride=4, min_range_m=0.5, max_range_m=60.0)
    odo = KissOdometry(voxel_size_m=0.5, max_range_m=60.0)
    step = make_pose(rot_y(0.01), [0.0, 0.0, 0.5])
    odo.register(pts)
    for _ in range(3):
        reg = odo.register(pts, step, lambda _icp_step: step)
        assert reg.ok
    np.testing.assert_allclose(reg.T_odom_cam, step @ step @ step, atol=1e-9)
    np.testing.assert_allclose(odo.predicted_delta, step, atol=1e-12)  # the next prediction continues it


def test_hybrid_needs_image_and_depth_and_valid_settings():
    src = make_odometry(config(OdometryKind.HYBRID), 3)
    assert isinstance(src, HybridOdometrySource)
    with pytest.raises(DataError, match="RGB image and a depth image"):
        src.update(Frame(0, 0.0, INTRINSICS), np.zeros((0, 3)), None)
    with pytest.raises(ConfigError):
        HybridOdometrySource(KissOdometry(), lambda: None, cloud_stride=0, max_depth_m=40.0, edge_rel_jump=0.1)
