"""Object extraction on hand-made depth + label images, checked against analytic answers and a reference
flood fill."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import ExtractionConfig
from shgm_slam.errors import DataError
from shgm_slam.geometry.camera import backproject
from shgm_slam.geometry.se3 import make_pose, rot_y, transform_points
from shgm_slam.graph.extraction import MAX_EXTENT_SAMPLES, extract_objects, extract_objects_from_config
from shgm_slam.labels import Label
from shgm_slam.types import Frame, Intrinsics

H, W = 60, 80
INTR = Intrinsics(fx=100.0, fy=100.0, cx=39.5, cy=29.5, width=W, height=H)
LABELS = (Label.BUILDING, Label.CAR, Label.POLE)


def blank() -> tuple[np.ndarray, np.ndarray]:
    """Depth 0 (invalid) and label 255 everywhere."""
    return np.zeros((H, W), np.float32), np.full((H, W), 255, np.uint8)


def extract(depth, labels, T=None, min_px=1, **kw):
    fraction = (min_px - 0.5) / (H * W)
    return extract_objects(depth, labels, INTR, T, labels=LABELS, min_blob_fraction=fraction, **kw)


def test_depth_step_splits_same_label_region():
    depth, labels = blank()
    labels[10:30, 10:60] = Label.CAR
    depth[10:30, 10:35] = 8.0
    depth[10:30, 35:60] = 9.5  # 1.5 m step > 1 m: two cars
    objs = extract(depth, labels)
    assert len(objs) == 2
    assert sorted(objs.pixel_counts.tolist()) == [500, 500]
    depth[10:30, 35:60] = 8.6  # 0.6 m step: one object
    assert len(extract(depth, labels)) == 1
    assert len(extract(depth, labels, depth_step_m=0.5)) == 2


def test_different_labels_never_join():
    depth, labels = blank()
    depth[5:25, 5:45] = 10.0
    labels[5:25, 5:25] = Label.BUILDING
    labels[5:25, 25:45] = Label.POLE
    objs = extract(depth, labels)
    assert sorted(objs.label_ids.tolist()) == [Label.BUILDING, Label.POLE]


def test_diagonal_contact_is_two_objects():
    depth, labels = blank()
    depth[:] = 10.0
    labels[10:20, 10:20] = Label.CAR
    labels[20:30, 20:30] = Label.CAR  # touches the first only at a corner
    objs = extract(depth, labels)
    assert len(objs) == 2
    labels[20, 19] = Label.CAR  # one 4-neighbour bridge joins them
    assert len(extract(depth, labels)) == 1


def test_small_blobs_are_dropped():
    depth, labels = blank()
    depth[:] = 12.0
    labels[0:10, 0:10] = Label.BUILDING  # 100 px
    labels[30:35, 30:35] = Label.BUILDING  # 25 px
    assert len(extract(depth, labels, min_px=1)) == 2
    objs = extract(depth, labels, min_px=26)
    assert objs.pixel_counts.tolist() == [100]
    assert len(extract(depth, labels, min_px=101)) == 0


def test_invalid_depth_and_range_are_ignored_and_never_crash():
    depth, labels = blank()
    labels[:, :] = Label.BUILDING
    depth[:, :] = 10.0
    depth[:, 40] = np.nan  # a column of NaN cuts the region in two
    depth[0:5, :] = np.inf
    depth[5:10, :] = -1.0
    depth[10:12, :] = 45.0  # beyond max_depth_m
    objs = extract(depth, labels)
    valid = (H - 12) * W - (H - 12)
    assert len(objs) == 2 and objs.pixel_counts.sum() == valid
    assert np.isfinite(objs.centroids_cam).all() and np.isfinite(objs.extents_m).all()
    depth[:] = np.nan
    assert len(extract(depth, labels)) == 0


def test_labels_outside_the_kept_set_are_ignored():
    depth, labels = blank()
    depth[:] = 10.0
    labels[:, :] = Label.SKY
    labels[20:40, 20:40] = Label.CAR
    objs = extract(depth, labels)
    assert objs.label_ids.tolist() == [Label.CAR] and objs.pixel_counts.tolist() == [400]


def test_centroid_and_extent_of_fronto_parallel_patch_match_geometry():
    """A 2 m x 1 m plate at 10 m, centred at (0.5, -0.25, 10): centroid and extents in camera and world."""
    z, half_w, half_h, centre = 10.0, 1.0, 0.5, np.array([0.5, -0.25, 10.0])
    v, u = np.mgrid[0:H, 0:W]
    x, y = (u - INTR.cx) * z / INTR.fx, (v - INTR.cy) * z / INTR.fy
    inside = (np.abs(x - centre[0]) <= half_w) & (np.abs(y - centre[1]) <= half_h)
    depth, labels = blank()
    depth[inside], labels[inside] = z, Label.BUILDING
    T = make_pose(rot_y(0.7), np.array([3.0, -1.0, 5.0]))
    objs = extract(depth, labels, T=T)
    assert len(objs) == 1
    pixel_m = z / INTR.fx
    np.testing.assert_allclose(objs.centroids_cam[0], centre, atol=pixel_m)
    np.testing.assert_allclose(objs.centroids_world[0], transform_points(T, centre[None])[0], atol=pixel_m)
    # 5-95 percentile spread of a uniform plate = 0.9 of its size (to a pixel)
    np.testing.assert_allclose(objs.extents_m[0], [0.9 * 2 * half_w, 0.9 * 2 * half_h, 0.0], atol=2 * pixel_m)


def _reference_objects(depth, labels, min_px, step=1.0, max_depth=30.0, min_depth=0.5):
    """Union-find over the explicit 4-neighbour edge list (slow, obviously correct)."""
    ok = np.isfinite(depth) & (depth > min_depth) & (depth <= max_depth) & np.isin(labels, LABELS)
    parent = np.arange(depth.size)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for r in range(H):
        for c in range(W):
            for r2, c2 in ((r, c + 1), (r + 1, c)):
                if r2 < H and c2 < W and ok[r, c] and ok[r2, c2] and labels[r, c] == labels[r2, c2]:
                    if abs(float(depth[r, c]) - float(depth[r2, c2])) < step:
                        parent[find(r * W + c)] = find(r2 * W + c2)
    roots = np.array([find(i) for i in range(depth.size)])
    points, pixel = backproject(np.where(ok, depth, 0.0), INTR, min_depth_m=min_depth, max_depth_m=max_depth)
    objects = []
    for root in np.unique(roots[pixel]):
        mine = roots[pixel] == root
        if mine.sum() >= min_px:
            label = labels.ravel()[pixel[mine][0]]
            objects.append((mine.sum(), label, *points[mine].mean(axis=0)))
    return np.array(sorted(objects)).reshape(-1, 5)


@pytest.mark.parametrize("seed", [0, 1])
def test_matches_reference_flood_fill_on_random_scene(seed):
    rng = np.random.default_rng(seed)
    # piecewise-constant labels and depths with ramps, steps and invalid holes
    labels = np.asarray(LABELS, np.uint8)[rng.integers(0, 3, (H // 6, W // 8))].repeat(6, 0).repeat(8, 1)
    depth = (rng.uniform(2, 28, (H // 10, W // 10)).repeat(10, 0).repeat(10, 1)).astype(np.float32)
    depth += np.linspace(0, 3, W, dtype=np.float32)[None]  # slow ramp: 0.04 m per pixel, joins along rows
    depth[rng.random((H, W)) < 0.03] = np.nan
    labels[rng.random((H, W)) < 0.03] = Label.SKY
    objs = extract(depth, labels, min_px=5)
    got = np.array(sorted(zip(objs.pixel_counts, objs.label_ids, *objs.centroids_cam.T, strict=True)))
    expected = _reference_objects(depth, labels, 5)
    assert len(objs) == len(expected) > 10
    np.testing.assert_array_equal(got[:, :2], expected[:, :2])  # pixel counts and labels
    np.testing.assert_allclose(got[:, 2:], expected[:, 2:], atol=1e-4)  # centroids = mean back-projection


def test_bad_shapes_give_data_errors():
    depth, labels = blank()
    with pytest.raises(DataError, match="same shape"):
        extract(depth, labels[:-1])
    with pytest.raises(DataError, match="intrinsics"):
        extract_objects(depth, labels, INTR.scaled(40, 30), None, labels=LABELS)


def test_from_config_uses_frame_pose_and_complains_about_missing_inputs():
    depth, labels = blank()
    depth[:] = 10.0
    labels[:] = Label.BUILDING
    T = make_pose(np.eye(3), np.array([1.0, 2.0, 3.0]))
    frame = Frame(0, 0.0, INTR, depth_m=depth, label_ids=labels, T_world_cam=T)
    objs = extract_objects_from_config(frame, ExtractionConfig())
    assert len(objs) == 1
    np.testing.assert_allclose(objs.centroids_world[0] - objs.centroids_cam[0], [1.0, 2.0, 3.0])
    frame.label_ids = None
    with pytest.raises(DataError, match="no labels"):
        extract_objects_from_config(frame, ExtractionConfig())


def test_sampled_extents_and_thin_objects_on_a_larger_image():
    """Big images: extents from a strided pixel grid; objects the grid misses use all their pixels."""
    h, w, z = 300, 400, 10.0
    stride = int(np.sqrt(h * w / MAX_EXTENT_SAMPLES))
    assert stride > 1
    pole_u = 350 - 350 % stride + 1  # a column the sampling grid skips
    intr = Intrinsics(fx=200.0, fy=200.0, cx=199.5, cy=149.5, width=w, height=h)
    depth = np.full((h, w), z, np.float32)
    labels = np.full((h, w), Label.SKY, np.uint8)
    labels[0:200, 0:300] = Label.BUILDING
    labels[50:250, pole_u] = Label.POLE  # one pixel wide
    objs = extract_objects(depth, labels, intr, None, labels=LABELS, min_blob_fraction=100 / (h * w))
    assert objs.label_ids.tolist() == [Label.BUILDING, Label.POLE]
    px = z / intr.fx
    grid_step = (stride + 1) * px
    np.testing.assert_allclose(objs.extents_m[0], [0.9 * 300 * px, 0.9 * 200 * px, 0.0], atol=grid_step)
    np.testing.assert_allclose(objs.extents_m[1], [0.0, 0.9 * 200 * px, 0.0], atol=px)  # every pixel: exact
    np.testing.assert_allclose(objs.centroids_cam[1], [(pole_u - intr.cx) * px, (149.5 - intr.cy) * px, z])


def test_depth_percentiles_put_a_blended_thin_object_at_its_near_part_and_leave_others_alone():
    """A pole 2 px wide at 10 m whose predicted depth blurs towards the facade behind it over 3 more columns
    (as a network's output does: no 1 m depth step, one object), beside a car at 8 m: with the 25th percentile
    for poles the pole's node is at 10 m on the ray through its centroid (the mean puts it at 10.8 m); the
    car keeps its mean."""
    depth, labels = blank()
    ramp = np.array([10.0, 10.0, 10.9, 11.4, 11.8], np.float32)
    depth[10:50, 20:25], labels[10:50, 20:25] = ramp, Label.POLE
    depth[30:45, 50:70], labels[30:45, 50:70] = 8.0, Label.CAR
    mean = extract(depth, labels)
    near = extract(depth, labels, depth_percentiles={Label.POLE: 25.0})
    pole = int(np.flatnonzero(mean.label_ids == Label.POLE)[0])
    car = int(np.flatnonzero(mean.label_ids == Label.CAR)[0])
    assert len(mean) == 2
    assert mean.centroids_cam[pole, 2] == pytest.approx(ramp.mean(), abs=1e-4)
    assert near.centroids_cam[pole, 2] == pytest.approx(10.0)  # nearest rank of 200 px: a 10 m pixel
    ray = mean.centroids_cam[pole] / np.linalg.norm(mean.centroids_cam[pole])  # same ray, nearer
    np.testing.assert_allclose(near.centroids_cam[pole] / np.linalg.norm(near.centroids_cam[pole]), ray)
    np.testing.assert_array_equal(near.centroids_cam[car], mean.centroids_cam[car])
    np.testing.assert_array_equal(near.label_ids, mean.label_ids)
    np.testing.assert_array_equal(near.pixel_counts, mean.pixel_counts)
    T = make_pose(rot_y(0.3), np.array([1.0, 0.0, 2.0]))
    moved = extract(depth, labels, T=T, depth_percentiles={Label.POLE: 25.0})
    np.testing.assert_allclose(moved.centroids_world, transform_points(T, near.centroids_cam))
    same = extract(depth, labels, depth_percentiles={Label.BUILDING: 10.0})  # no such object: unchanged
    np.testing.assert_array_equal(same.centroids_cam, mean.centroids_cam)
    far = extract(depth, labels, depth_percentiles={Label.POLE: 100.0, Label.CAR: 0.0})  # the ends: max, min
    assert far.centroids_cam[pole, 2] == pytest.approx(11.8) and far.centroids_cam[car, 2] == pytest.approx(8.0)
