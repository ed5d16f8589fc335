"""Where robots look from (``server.viewpoints``): camera heights measured from the graphs, flat ground
that gives no evidence between a car and a UAV, and closures whose translation sigma grows with the views'
elevation gap."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import ShgmConfig
from shgm_slam.geometry import se3
from shgm_slam.graph.extraction import ObjectObservations
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.labels import FLAT_GROUND_LABELS, VIEWPOINT_DEPENDENT_LABELS, Label
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.viewpoints import (
    camera_height_m,
    closure_information,
    elevation_gap_rad,
    up_is_level,
    up_spread_rad,
    views_differ,
)

UP = np.array([0.0, 0.0, 1.0])


def test_camera_height_is_measured_over_flat_ground_only():
    rng = np.random.default_rng(2)
    nodes = np.column_stack([rng.uniform(0, 50, (30, 2)), np.r_[np.zeros(20), rng.uniform(1, 8, 10)]])
    labels = np.r_[np.full(20, Label.SIDEWALK), np.full(10, Label.POLE)]
    cameras = nodes + [0.0, -10.0, 45.0] + np.c_[np.zeros((30, 2)), rng.normal(0, 0.2, 30)]
    R = se3.rot_x(0.4) @ se3.rot_z(1.0)  # any odometry frame: "up" comes with it
    assert camera_height_m(cameras @ R.T, nodes @ R.T, labels, R @ UP) == pytest.approx(45.0, abs=0.2)
    assert camera_height_m(cameras, nodes, np.full(30, Label.POLE), UP) is None  # no flat ground mapped
    assert camera_height_m(cameras, nodes, labels, None) is None


def test_views_differ_between_a_car_and_a_uav_not_between_two_cars():
    assert views_differ(1.6, 45.0, 4.0) and views_differ(45.0, 1.6, 4.0)
    assert not views_differ(1.6, 1.9, 4.0) and not views_differ(40.0, 55.0, 4.0)
    assert not views_differ(None, 45.0, 4.0)
    assert views_differ(0.0, 1.0, 4.0)  # a camera at ground level: 0.1 m floor


def test_the_elevation_gap_of_a_car_and_a_uav_widens_only_the_translation_sigma():
    """A car sees objects 10-40 m ahead nearly level, a UAV 50 m up sees them from high above: the gap is
    their elevation difference, in each robot's own frame and "up"; two cars have none."""
    rng = np.random.default_rng(4)
    objects = np.column_stack([rng.uniform(10, 40, 20), rng.uniform(-8, 8, 20), rng.uniform(0.5, 3.0, 20)])

    def rays(camera):
        r = objects - camera
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    car, uav = rays(np.array([0.0, 0.0, 1.5])), rays(np.array([-30.0, 0.0, 50.0]))
    R_b = se3.rot_z(1.0) @ se3.rot_x(0.3)  # the UAV's graph frame: turned and tilted against the car's
    gap = elevation_gap_rad(car, uav @ R_b.T, UP, R_b @ UP)
    expected = np.median(np.abs(np.arcsin(car[:, 2]) - np.arcsin(uav[:, 2])))
    assert gap == pytest.approx(expected) and 0.5 < gap < 1.2
    assert elevation_gap_rad(car, car, UP, UP) == 0.0
    assert elevation_gap_rad(car, uav, None, UP) == 0.0 and elevation_gap_rad(car[:0], uav[:0], UP, UP) == 0.0
    info = closure_information(0.1, 3.0, gap, 2.6)
    np.testing.assert_allclose(np.diag(info)[:3], 0.1**-2)  # rotation: as configured
    np.testing.assert_allclose(np.diag(info)[3:], (3.0 * (1.0 + 2.6 * gap)) ** -2)
    np.testing.assert_allclose(closure_information(0.1, 3.0, 0.0, 2.6), np.diag([0.1**-2] * 3 + [3.0**-2] * 3))


def _drive(name: str, height_m: float, pos: np.ndarray, labels: np.ndarray, T_odom_world: np.ndarray | None = None):
    """Keyframe messages of a robot flying or driving along x at ``height_m`` (odometry = truth, z up, its
    camera looking along x), seeing the objects within 60 m; ``T_odom_world`` turns the world into the robot's
    odometry frame (default: the world's, z up)."""
    graph = SemanticGraph(5.0, 10.0)
    T_frame = np.eye(4) if T_odom_world is None else T_odom_world
    R_world_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # x fwd, y down -> z up
    for k, x in enumerate(np.arange(0.0, 120.0, 4.0)):
        T_world = se3.make_pose(R_world_cam, np.array([x, 0.0, height_m]))
        seen = np.linalg.norm(pos[:, :2] - T_world[:2, 3], axis=1) < 60.0
        cam = se3.transform_points(se3.inverse(T_world), pos[seen])
        T, odom = T_frame @ T_world, se3.transform_points(T_frame, pos[seen])
        obs = ObjectObservations(labels[seen], cam, odom, np.full(seen.sum(), 2000), np.ones((seen.sum(), 3)))
        yield KeyframeMessage(name, k, k, 0.5 * k, T, graph.add_keyframe(k, T, obs), T_frame[:3, :3] @ UP)


def test_the_map_server_drops_viewpoint_dependent_evidence_between_a_car_and_a_uav_only():
    rng = np.random.default_rng(7)
    n = 80
    pos = np.column_stack([rng.uniform(0, 120, n), rng.choice([-1.0, 1.0], n) * rng.uniform(4, 25, n), np.zeros(n)])
    labels = rng.choice([Label.ROAD, Label.SIDEWALK, Label.TERRAIN, Label.POLE, Label.CAR], n).astype(np.int64)
    pos[~np.isin(labels, FLAT_GROUND_LABELS), 2] = rng.uniform(0.5, 4.0, (~np.isin(labels, FLAT_GROUND_LABELS)).sum())
    cfg = ShgmConfig()
    cfg.backend.match_every_keyframes = 1000  # only the viewpoints are tested here
    server = MapServer(["car1", "car2", "uav"], cfg)
    for name, h in (("car1", 1.6), ("car2", 1.8), ("uav", 45.0)):
        for msg in _drive(name, h, pos, labels):
            server.receive(msg)
    assert server.camera_height_m("car1") == pytest.approx(1.6, abs=0.05)
    assert server.camera_height_m("uav") == pytest.approx(45.0, abs=0.05)
    assert server.evidence_free_labels("car1", "uav") == tuple(VIEWPOINT_DEPENDENT_LABELS)
    assert server.evidence_free_labels("uav", "car2") == tuple(VIEWPOINT_DEPENDENT_LABELS)
    assert set(FLAT_GROUND_LABELS) <= set(VIEWPOINT_DEPENDENT_LABELS)
    assert server.evidence_free_labels("car1", "car2") == ()


def test_the_spread_of_the_normals_is_their_circular_standard_deviation():
    rng = np.random.default_rng(9)
    assert up_spread_rad(20 * UP, 20) == pytest.approx(0.0, abs=1e-6)
    assert up_spread_rad(np.zeros(3), 0) is None
    sigma = np.radians(5.0)  # small tilts: the spread is about the 2-D standard deviation of the tilt
    tilt = rng.normal(0.0, sigma, (4000, 2))
    normals = np.column_stack([np.sin(tilt[:, 0]), np.sin(tilt[:, 1]), np.ones(4000)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert up_spread_rad(normals.sum(axis=0), len(normals)) == pytest.approx(np.sqrt(2.0) * sigma, rel=0.05)


def test_an_up_is_level_when_its_spread_moves_the_objects_less_than_the_radius():
    assert up_is_level(np.radians(0.6), 32.0, 3.0)  # a car: 0.3 m at its objects
    assert not up_is_level(np.radians(10.0), 97.0, 3.0)  # a UAV on a network's depth: 17 m
    assert up_is_level(np.radians(1.0), 97.0, 3.0)  # the same UAV on rendered depth: 1.7 m
    assert not up_is_level(None, 30.0, 3.0) and not up_is_level(0.01, None, 3.0)


def _car_and_drifting_uav(T_odom_world: np.ndarray | None = None) -> MapServer:
    """A map server that took a car's keyframes and a UAV's whose normals tilt 20 degrees over its flight (its
    odometry frame turned from the world's by ``T_odom_world``)."""
    rng = np.random.default_rng(8)
    n = 60
    pos = np.column_stack([rng.uniform(0, 120, n), rng.choice([-1.0, 1.0], n) * rng.uniform(4, 25, n),
                           rng.uniform(0.0, 4.0, n)])  # fmt: skip
    labels = rng.choice([Label.SIDEWALK, Label.POLE, Label.CAR], n).astype(np.int64)
    server = MapServer(["car1", "uav"], ShgmConfig())
    for msg in _drive("car1", 1.6, pos, labels):
        server.receive(msg)
    R = np.eye(3) if T_odom_world is None else T_odom_world[:3, :3]
    msgs = list(_drive("uav", 45.0, pos, labels, T_odom_world))
    for k, msg in enumerate(msgs):
        tilt = se3.rot_x(np.radians(20.0) * k / (len(msgs) - 1))
        server.receive(KeyframeMessage(msg.robot, msg.kf_index, msg.frame_index, msg.timestamp_s, msg.T_odom_kf,
                                       msg.graph_update, R @ tilt @ UP))  # fmt: skip
    return server


def test_a_robot_whose_normals_drift_is_not_matched_gravity_aligned():
    """The UAV's odometry tilts 20 degrees over its flight (its normals in the odometry frame turn with it):
    its mean "up" cannot stand for its whole graph, so it is matched in 6-DoF; the cars' stay level."""
    server = _car_and_drifting_uav()
    assert server.up_spread_rad("car1") == pytest.approx(0.0, abs=1e-6) and server.gravity_aligned("car1")
    assert np.degrees(server.up_spread_rad("uav")) > 5.0 and not server.gravity_aligned("uav")


def test_a_tilted_robot_is_matched_in_6dof_in_frames_whose_z_is_up(monkeypatch):
    """A UAV whose odometry frame is its first camera's (y down, as a KITTI camera) and whose normals drift is
    matched in 6-DoF, but in frames turned so that z is its mean up: the chance model then shifts hypotheses
    along the ground, not across the street and up into the air (the configured -y of a camera frame is
    neither robot's vertical here)."""
    import shgm_slam.server.map_server as ms

    seen = []
    real = ms.match_graphs

    def spy(a, b, descriptor_cfg, matching_cfg, **kw):
        seen.append((a.positions_xyz.copy(), b.positions_xyz.copy(), matching_cfg))
        return real(a, b, descriptor_cfg, matching_cfg, **kw)

    monkeypatch.setattr(ms, "match_graphs", spy)
    server = _car_and_drifting_uav(se3.make_pose(se3.rot_x(np.radians(-90.0)), np.zeros(3)))  # z up -> y down
    assert not server.gravity_aligned("uav")
    pairs = [(a, b, cfg) for a, b, cfg in seen if not cfg.gravity_aligned]
    assert pairs, "the car and the tilted UAV were never matched"
    for a, b, cfg in pairs:
        assert cfg.up_axis == (0.0, 0.0, 1.0)
        for points in (a, b):
            centred = points - points.mean(axis=0)
            thinnest = np.linalg.eigh(centred.T @ centred)[1][:, 0]
            assert abs(thinnest[2]) > np.cos(np.radians(15.0))  # each graph's own vertical is near z
