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
from shgm_slam.labels import FLAT_GROUND_LABELS, Label
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.viewpoints import camera_height_m, closure_information, elevation_gap_rad, views_differ

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


def _drive(name: str, height_m: float, pos: np.ndarray, labels: np.ndarray):
    """Keyframe messages of a robot flying or driving along x at ``height_m`` (odometry = truth, z up, its
    camera looking along x), seeing the objects within 60 m."""
    graph = SemanticGraph(5.0, 10.0)
    R_world_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # x fwd, y down -> z up
    for k, x in enumerate(np.arange(0.0, 120.0, 4.0)):
        T = se3.make_pose(R_world_cam, np.array([x, 0.0, height_m]))
        seen = np.linalg.norm(pos[:, :2] - T[:2, 3], axis=1) < 60.0
        cam = se3.transform_points(se3.inverse(T), pos[seen])
        obs = ObjectObservations(labels[seen], cam, pos[seen], np.full(seen.sum(), 2000), np.ones((seen.sum(), 3)))
        yield KeyframeMessage(name, k, k, 0.5 * k, T, graph.add_keyframe(k, T, obs), UP.copy())


def test_the_map_server_drops_flat_ground_evidence_between_a_car_and_a_uav_only():
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
    assert server.evidence_free_labels("car1", "uav") == tuple(FLAT_GROUND_LABELS)
    assert server.evidence_free_labels("uav", "car2") == tuple(FLAT_GROUND_LABELS)
    assert server.evidence_free_labels("car1", "car2") == ()
