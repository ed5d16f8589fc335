"""depth_to_cloud: exact back-projection, Euclidean range limits, invalid pixels, labels, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import DataError
from shgm_slam.geometry.camera import project
from shgm_slam.labels import Label
from shgm_slam.odometry.clouds import depth_edges, depth_to_cloud, sampling_spacing_m, trusted_depth
from shgm_slam.types import Intrinsics

INTR = Intrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)


def _depth(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(1.0, 20.0, (INTR.height, INTR.width)).astype(np.float32)


def test_points_reproject_to_their_pixels_with_their_depth():
    rng = np.random.default_rng(0)
    depth = _depth(rng)
    pts, labels = depth_to_cloud(depth, INTR, stride=1, min_range_m=0.0, max_range_m=100.0)
    assert labels is None
    assert pts.shape == (INTR.width * INTR.height, 3) and pts.dtype == np.float64
    uv, in_front = project(pts, INTR)
    assert in_front.all()
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    np.testing.assert_allclose(uv, np.c_[u, v], atol=1e-9)
    np.testing.assert_allclose(pts[:, 2], depth[v, u], rtol=1e-6)


def test_invalid_depth_is_skipped_and_range_is_euclidean():
    rng = np.random.default_rng(1)
    depth = _depth(rng)
    depth[0, :4] = [np.nan, np.inf, -3.0, 0.0]
    pts, _ = depth_to_cloud(depth, INTR, stride=1, min_range_m=0.0, max_range_m=100.0)
    assert pts.shape[0] == INTR.width * INTR.height - 4
    assert np.isfinite(pts).all() and (pts[:, 2] > 0).all()

    pts, _ = depth_to_cloud(depth, INTR, stride=1, min_range_m=5.0, max_range_m=12.0)
    r = np.linalg.norm(pts, axis=1)
    assert r.min() >= 5.0 and r.max() <= 12.0
    # a corner pixel with z just under the limit has a Euclidean range above it and must be dropped
    corner = np.full((INTR.height, INTR.width), 11.9, np.float32)
    kept, _ = depth_to_cloud(corner, INTR, stride=1, min_range_m=0.0, max_range_m=12.0)
    assert 0 < kept.shape[0] < corner.size


def test_stride_and_labels_follow_the_kept_pixels():
    rng = np.random.default_rng(2)
    depth = _depth(rng)
    depth[2, 4] = 0.0  # one invalid pixel on the stride-2 grid
    labels = (np.arange(depth.size) % 19).reshape(depth.shape).astype(np.uint8)
    pts, lab = depth_to_cloud(depth, INTR, stride=2, min_range_m=0.0, max_range_m=100.0, label_ids=labels)
    assert pts.shape[0] == (INTR.height // 2) * (INTR.width // 2) - 1 == lab.shape[0]
    uv, _ = project(pts, INTR)
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert (u % 2 == 0).all() and (v % 2 == 0).all()
    np.testing.assert_array_equal(lab, labels[v, u])


def test_all_invalid_depth_gives_an_empty_cloud():
    pts, lab = depth_to_cloud(
        np.zeros((INTR.height, INTR.width), np.float32), INTR, stride=2, min_range_m=0.5, max_range_m=30.0,
        label_ids=np.zeros((INTR.height, INTR.width), np.uint8),
    )  # fmt: skip
    assert pts.shape == (0, 3) and lab.shape == (0,)


@pytest.mark.parametrize(
    ("depth_shape", "labels_shape", "stride", "ranges", "message"),
    [
        ((24, 30), None, 1, (0.0, 10.0), "intrinsics"),
        ((24, 32), (24, 30), 1, (0.0, 10.0), "label image"),
        ((24, 32), None, 0, (0.0, 10.0), "stride"),
        ((24, 32), None, 1, (10.0, 5.0), "min_range_m"),
        ((24,), None, 1, (0.0, 10.0), "(H, W)"),
    ],
)
def test_bad_input_raises_data_error(depth_shape, labels_shape, stride, ranges, message):
    labels = None if labels_shape is None else np.zeros(labels_shape, np.uint8)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")):
        depth_to_cloud(
            np.ones(depth_shape, np.float32), INTR, stride=stride,
            min_range_m=ranges[0], max_range_m=ranges[1], label_ids=labels,
        )  # fmt: skip


def test_spacing_of_a_fronto_parallel_wall_is_depth_times_stride_over_f():
    depth = np.full((INTR.height, INTR.width), 8.0, np.float32)
    for stride in (1, 2, 3):
        pts, _ = depth_to_cloud(depth, INTR, stride=stride, min_range_m=0.0, max_range_m=100.0)
        spacing = sampling_spacing_m(pts, INTR, stride=stride)
        assert spacing.shape == (pts.shape[0],)
        np.testing.assert_allclose(spacing, 8.0 * stride / INTR.fx, rtol=1e-9)


def test_ground_spacing_grows_with_range_and_edges_take_their_surface_spacing():
    height_m = 1.5
    v = np.arange(INTR.height, dtype=np.float64)[:, None] - INTR.cy
    ground = np.where(v > 0.5, INTR.fy * height_m / np.maximum(v, 1e-9), 0.0) * np.ones((1, INTR.width))
    depth = ground.astype(np.float32)
    depth[14:18, 10:14] = 3.0  # a small box standing in front of the ground
    pts, _ = depth_to_cloud(depth, INTR, stride=1, min_range_m=0.0, max_range_m=1000.0)
    spacing = sampling_spacing_m(pts, INTR, stride=1)
    on_box = np.isclose(pts[:, 2], 3.0)
    np.testing.assert_allclose(spacing[on_box], 3.0 / INTR.fx, rtol=1e-6)  # edges included
    road = ~on_box
    order = np.argsort(pts[road, 2])
    assert np.all(np.diff(spacing[road][order][:: INTR.width]) >= -1e-9)  # farther rows: sparser
    # on the ground the row-to-row gap dominates: about z^2 / (f * h)
    far = road & (pts[:, 2] > 20.0)
    assert np.all(spacing[far] > 0.5 * pts[far, 2] ** 2 / (INTR.fy * height_m))


def test_isolated_points_and_points_behind_the_camera_have_infinite_spacing():
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    depth[5, 5] = depth[12, 20] = 4.0
    pts, _ = depth_to_cloud(depth, INTR, stride=1, min_range_m=0.0, max_range_m=100.0)
    assert np.isinf(sampling_spacing_m(pts, INTR, stride=1)).all()
    assert np.isinf(sampling_spacing_m(np.array([[0.0, 0.0, -2.0]]), INTR, stride=1)).all()
    assert sampling_spacing_m(np.zeros((0, 3)), INTR, stride=2).shape == (0,)
    with pytest.raises(DataError, match="points must be"):
        sampling_spacing_m(np.zeros((4, 2)), INTR, stride=1)


def _plane_depth(intr: Intrinsics, normal: np.ndarray, offset: float) -> np.ndarray:
    """Exact z-depth of the plane ``normal . p = offset`` (camera frame), 0 where it is behind."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    with np.errstate(divide="ignore"):
        z = offset / (rays @ normal)
    return np.where(z > 0, z, 0.0).astype(np.float32)


@pytest.mark.parametrize("normal", [np.array([0.0, 1.0, 0.0]), np.array([0.6, 0.3, 0.74]), np.array([0.0, 0.0, 1.0])])
def test_planes_have_no_depth_edges_even_at_grazing_angles(normal):
    intr = Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)
    depth = _plane_depth(intr, normal / np.linalg.norm(normal), 1.6)
    valid = depth > 0
    edges = depth_edges(depth, 0.1)
    pad = np.pad(valid, 1, constant_values=True)  # beyond the image the plane is extrapolated
    inner = valid & pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]  # 4 valid neighbours
    assert not edges[inner].any()
    assert not edges[~valid].any()


def test_an_occlusion_is_an_edge_and_trusted_depth_drops_it_with_its_margin():
    depth = np.full((24, 32), 20.0, np.float32)
    depth[:, 16:] = 8.0  # a near wall on the right
    depth[:3] = 0.0  # sky
    labels = np.full((24, 32), 2, np.uint8)
    labels[10:14, 4:6] = Label.POLE
    edges = depth_edges(depth, 0.1)
    assert edges[5:, 15:17].all() and not edges[5:, 2:13].any() and not edges[5:, 19:30].any()
    assert edges[3, 5]  # next to the sky (no neighbour): an edge
    trusted = trusted_depth(depth, labels, max_depth_m=15.0, edge_rel_jump=0.1, edge_margin_px=1)
    assert (trusted[5:, :16] == 0).all()  # the far wall is beyond the range cap
    assert (trusted[5:, 16:18] == 0).all() and (trusted[5:, 19:30] == 8.0).all()  # edge + margin dropped
    assert (trusted[:3] == 0).all()
    trusted = trusted_depth(depth, labels, max_depth_m=50.0, edge_rel_jump=0.1, edge_margin_px=0)
    assert (trusted[10:14, 4:6] == 0).all() and (trusted[15:20, 4:6] == 20.0).all()  # thin structure dropped
    with pytest.raises(DataError, match="differ in size"):
        trusted_depth(depth, labels[:-1], max_depth_m=50.0, edge_rel_jump=0.1, edge_margin_px=0)
