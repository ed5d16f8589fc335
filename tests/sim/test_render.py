"""Renderer against analytic geometry: depth of a known box face, labels at known pixels, depth points on
the mesh surface, and consistent reprojection between two views."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import SimulationError
from shgm_slam.geometry.camera import backproject, project
from shgm_slam.geometry.se3 import inverse, rot_y, transform_points
from shgm_slam.labels import Label
from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.render import Renderer, make_intrinsics
from shgm_slam.sim.shapes import ObjectKind
from shgm_slam.sim.trajectories import camera_poses
from shgm_slam.sim.world import ObjectList, assemble_world


def one_box_world():
    objs = ObjectList()
    objs.add_on_ground(ObjectKind.WALL, 10.0, 0.0, (2.0, 4.0, 3.0))  # one box, front face at x = 9
    return assemble_world(objs.objects)


def look_along_x(height_m: float = 1.5) -> np.ndarray:
    return camera_poses(np.array([[0.0, 0.0, height_m]]), np.array([[1.0, 0.0, 0.0]]))[0]


@pytest.mark.parametrize("threads", [1, 2])
def test_depth_of_box_face_is_analytic(threads):
    K = make_intrinsics(161, 61, hfov_deg=60.0)  # odd sizes: the centre pixel looks exactly along +x
    with Renderer(one_box_world(), K, threads=threads) as r:
        view = r.render(look_along_x())
    cv, cu = int(K.cy), int(K.cx)
    assert abs(view.depth_m[cv, cu] - 9.0) < 1e-3
    assert view.label_ids[cv, cu] == Label.WALL and view.object_ids[cv, cu] == 0
    face = view.label_ids == Label.WALL
    np.testing.assert_allclose(view.depth_m[face], 9.0, atol=1e-3)  # fronto-parallel face: constant z-depth
    assert view.label_ids[cv, 0] == Label.SKY and view.depth_m[cv, 0] == 0.0
    # the face spans y in [-2, 2] at 9 m: columns cx -+ fx * 2 / 9
    cols = np.flatnonzero(face[cv])
    assert abs(cols.min() - (K.cx - K.fx * 2 / 9)) <= 1.0 and abs(cols.max() - (K.cx + K.fx * 2 / 9)) <= 1.0
    # ...and z in [0, 3]: rows cy + fy * (1.5 - z) / 9
    rows = np.flatnonzero(face[:, cu])
    assert (
        abs(rows.min() - (K.cy - K.fy * 1.5 / 9)) <= 1.0 and abs(rows.max() - (K.cy + K.fy * 1.5 / 9)) <= 1.0
    )
    assert (
        view.image_rgb.dtype == np.uint8 and view.image_rgb[cv, 0, 2] > view.image_rgb[cv, 0, 0]
    )  # blue sky


def test_max_depth_clips_to_invalid():
    K = make_intrinsics(41, 21)
    with Renderer(one_box_world(), K, max_depth_m=5.0) as r:
        view = r.render(look_along_x())
    assert np.all(view.depth_m == 0.0)
    assert (view.label_ids == Label.WALL).any()  # still visible and labelled


def test_backprojected_depth_lies_on_the_mesh():
    objs = ObjectList()
    objs.add(ObjectKind.ROAD, (0.0, 0.0, -0.05), (60.0, 60.0, 0.1))
    objs.add_on_ground(ObjectKind.CAR, 8.0, 1.0, (4.5, 1.8, 1.5), 0.4)
    objs.add_on_ground(ObjectKind.TREE, 12.0, -3.0, (4.0, 4.0, 8.0), 1.0)
    objs.add_on_ground(ObjectKind.STREET_LAMP, 15.0, 3.0, (1.8, 0.3, 8.0), -2.0)
    world = assemble_world(objs.objects)
    K = make_intrinsics(96, 48)
    T = camera_poses(np.array([[0.0, 0.5, 1.65]]), np.array([[1.0, -0.05, 0.0]]), np.radians(5.0))[0]
    with Renderer(world, K) as r:
        view = r.render(T)
    pts_cam, idx = backproject(view.depth_m, K)
    pts = transform_points(T, pts_cam)
    dist = distance_to_object_surface(world, pts, view.object_ids.ravel()[idx])
    assert len(pts) > 1000 and np.max(dist) < 2e-3


def distance_to_object_surface(world, pts: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the nearest triangle of its own object (point-in-triangle
    projections only, so a point off every face of its object gets inf)."""
    out = np.full(len(pts), np.inf)
    for o in np.unique(obj):
        rows = np.flatnonzero(obj == o)
        tri = world.vertices_xyz[world.faces[world.tri_object == o]]  # (F, 3, 3)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        p = pts[rows][:, None, :]  # (P, 1, 3)
        d = np.einsum("pfi,fi->pf", p - a, n)
        q = p - d[..., None] * n  # projections onto the planes
        inside = np.ones(d.shape, bool)
        for v0, v1 in ((a, b), (b, c), (c, a)):  # same side of every edge as the normal says
            inside &= np.einsum("pfi,fi->pf", np.cross(v1 - v0, q - v0), n) >= -1e-6
        out[rows] = np.where(inside, np.abs(d), np.inf).min(axis=1)
    return out


def test_two_views_reproject_consistently():
    """A point seen in view A, moved through the GT poses into view B, lands on a pixel with its depth.

    Only non-ground points whose projection falls within 0.15 px of a pixel centre are compared (ground
    depth changes by metres per pixel near the horizon); 5 cm of pose error already fails this test.
    """
    world = build_city(CityParams(size_x_m=260.0, size_y_m=260.0, block_min_m=45, block_max_m=70), seed=3)
    x, y = world.streets.nodes_xy[len(world.streets.nodes_xy) // 2]
    K = make_intrinsics(240, 96)
    Ts = camera_poses(
        np.array([[x + 2.2, y - 30, 1.65], [x + 2.2, y - 27.5, 1.65]]), np.array([[0, 1.0, 0]] * 2)
    )
    Ts[1, :3, :3] = Ts[1, :3, :3] @ rot_y(0.1)  # and a small turn about the camera's vertical axis
    with Renderer(world, K) as r:
        a, b = r.render(Ts[0]), r.render(Ts[1])
    pts_cam, idx = backproject(a.depth_m, K, min_depth_m=1.0, max_depth_m=60.0)
    label_a = a.label_ids.ravel()[idx]
    keep = ~np.isin(label_a, [Label.ROAD, Label.SIDEWALK, Label.TERRAIN])
    in_b = transform_points(inverse(Ts[1]) @ Ts[0], pts_cam[keep])
    uv, front = project(in_b, K)
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    ok = (
        front
        & (u >= 0)
        & (u < K.width)
        & (v >= 0)
        & (v < K.height)
        & (np.abs(uv - np.rint(uv)).max(1) < 0.15)
    )
    assert ok.sum() > 300
    rel = np.abs(b.depth_m[v[ok], u[ok]] - in_b[ok, 2]) / in_b[ok, 2]
    assert np.mean(rel < 0.005) > 0.88  # the rest sit on occlusion boundaries
    assert np.mean(b.label_ids[v[ok], u[ok]] == label_a[keep][ok]) > 0.9


def test_bad_inputs_are_clear_errors():
    with pytest.raises(SimulationError, match="too small"):
        make_intrinsics(4, 4)
    with Renderer(one_box_world(), make_intrinsics(16, 16)) as r, pytest.raises(SimulationError, match="4x4"):
        r.render(np.eye(3))
    with pytest.raises(SimulationError, match="no triangles"):
        Renderer(assemble_world([]), make_intrinsics(16, 16))
    with pytest.raises(SimulationError, match="supersample"):
        Renderer(one_box_world(), make_intrinsics(16, 16), supersample=0)


def test_supersampled_colour_averages_the_pixel_and_keeps_its_centre_geometry():
    """With 4 x 4 rays per pixel the colour is the pixel's area mean: the pixel the wall's edge crosses gets a
    colour between the sky's and the wall's, the image's mean colour stays; depth, labels and object ids are
    those of the ray through each pixel's centre, as without supersampling."""
    K = make_intrinsics(161, 61, hfov_deg=60.0)
    with Renderer(one_box_world(), K, threads=1) as plain_r, Renderer(one_box_world(), K, supersample=4) as ss_r:
        plain, ss = plain_r.render(look_along_x()), ss_r.render(look_along_x())
    np.testing.assert_array_equal(ss.depth_m, plain.depth_m)
    np.testing.assert_array_equal(ss.label_ids, plain.label_ids)
    np.testing.assert_array_equal(ss.object_ids, plain.object_ids)
    cv = int(K.cy)
    edge = K.cx - K.fx * 2 / 9  # the wall's left edge, 49.0 here: pixel 49 is about half sky, half wall
    col = round(edge)
    assert plain.label_ids[cv, col - 1] == Label.SKY and plain.label_ids[cv, col + 1] == Label.WALL
    sky, wall = plain.image_rgb[cv, col - 1].astype(int), plain.image_rgb[cv, col + 1].astype(int)
    mixed = ss.image_rgb[cv, col].astype(int)
    channel = int(np.argmax(np.abs(sky - wall)))
    lo, hi = sorted((sky[channel], wall[channel]))
    assert lo + 0.2 * (hi - lo) < mixed[channel] < hi - 0.2 * (hi - lo)
    assert abs(ss.image_rgb.mean() - plain.image_rgb.mean()) < 2.0
