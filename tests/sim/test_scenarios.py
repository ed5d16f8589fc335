"""Scenario sanity: path lengths near the paper's, measured overlaps, disjointness, and cars that never
drive through objects."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shgm_slam.errors import ConfigError, DataError, SimulationError
from shgm_slam.sim.scenarios import SCENARIOS, ScenarioOptions, build_scenario
from shgm_slam.sim.shapes import ObjectKind
from shgm_slam.sim.trajectories import RobotKind, min_distance_m, shared_view_length_m

ELEVATED = {ObjectKind.STREET_LAMP, ObjectKind.SIGNAL_POLE, ObjectKind.TRAFFIC_LIGHT, ObjectKind.TRAFFIC_SIGN}


def footprint_clearance_m(world, positions_xy: np.ndarray) -> float:
    """Smallest horizontal distance from a camera position to a ground-standing object's footprint
    (lamps and signal poles count by their pole only, their arms overhang the road up high)."""
    objs = [o for o in world.objects if not o.is_stuff and o.kind not in ELEVATED]
    centres = np.array([o.centre_xyz[:2] for o in objs])
    half = np.array([o.size_xyz[:2] for o in objs]) / 2
    yaw = np.array([o.yaw_rad for o in objs])
    poles = [o for o in world.objects if o.kind in (ObjectKind.STREET_LAMP, ObjectKind.SIGNAL_POLE)]
    pole_xy = np.array(
        [
            np.array(o.centre_xyz[:2])
            - 0.5 * o.size_xyz[0] * np.array([np.cos(o.yaw_rad), np.sin(o.yaw_rad)])
            for o in poles
        ]
    )
    best = np.inf
    tree = cKDTree(centres)
    for p in positions_xy:
        rows = tree.query_ball_point(p, 40.0)
        if rows:
            d = p - centres[rows]
            c, s = np.cos(yaw[rows]), np.sin(yaw[rows])
            local = np.abs(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1))
            best = min(best, float(np.linalg.norm(np.maximum(local - half[rows], 0.0), axis=1).min()))
        best = min(best, float(np.linalg.norm(pole_xy - p, axis=1).min()))
    return best


@pytest.fixture(scope="module")
def airsim():
    return build_scenario("airsim-like", ScenarioOptions(seed=0))


def test_airsim_like_lengths_and_overlaps(airsim):
    assert [r.name for r in airsim.robots] == ["car1", "car2", "uav"]
    for r in airsim.robots:
        target = {"car1": 420.0, "car2": 420.0, "uav": 600.0}[r.name]
        assert abs(r.path_length_m - target) <= 0.15 * target
    for a in airsim.robots:
        for b in airsim.robots:
            if a is not b:
                assert shared_view_length_m(a, b) > 200.0, (a.name, b.name)
    car1, car2, uav = airsim.robots
    assert shared_view_length_m(car1, car2) < car1.path_length_m - 50  # each has a part of its own
    assert shared_view_length_m(uav, car1) < uav.path_length_m - 50
    z = uav.positions_xyz[:, 2]
    assert uav.kind is RobotKind.UAV and z.min() >= 30.0 and z.max() <= 60.0
    tops = max(
        o.centre_xyz[2] + o.size_xyz[2] / 2 for o in airsim.world.objects if o.kind is ObjectKind.BUILDING
    )
    assert z.min() > tops + 5.0  # flies over every building


def test_cars_never_drive_through_objects(airsim):
    for r in airsim.robots[:2]:
        assert footprint_clearance_m(airsim.world, r.positions_xyz[:, :2]) > 0.9


def test_synthia_like_forward_and_backward_views():
    plan = build_scenario("synthia-like", ScenarioOptions(seed=1))
    fwd, back = plan.robots
    assert (fwd.name, back.name) == ("forward", "backward")
    assert abs(fwd.path_length_m - 950.0) <= 0.15 * 950.0
    np.testing.assert_allclose(fwd.positions_xyz, back.positions_xyz)
    assert np.all(np.einsum("ni,ni->n", fwd.T_world_cam[:, :3, 2], back.T_world_cam[:, :3, 2]) < -0.99)
    assert footprint_clearance_m(plan.world, fwd.positions_xyz[:, :2]) > 0.9


def test_disjoint_robots_never_see_the_same_place():
    opt = ScenarioOptions(seed=2, max_depth_m=200.0)
    plan = build_scenario("disjoint", opt)
    a, b = plan.robots
    assert min_distance_m(a, b) > 2 * opt.max_depth_m
    assert shared_view_length_m(a, b) == 0.0
    with pytest.raises(SimulationError, match="2x depth range"):
        build_scenario("disjoint", ScenarioOptions(seed=2, max_depth_m=1000.0))


def test_seed_determinism():
    a = build_scenario("airsim-like", ScenarioOptions(seed=7, compact=True))
    b = build_scenario("airsim-like", ScenarioOptions(seed=7, compact=True))
    c = build_scenario("airsim-like", ScenarioOptions(seed=8, compact=True))
    for ra, rb in zip(a.robots, b.robots, strict=True):
        np.testing.assert_array_equal(ra.T_world_cam, rb.T_world_cam)
    assert not np.array_equal(a.robots[0].T_world_cam[:5], c.robots[0].T_world_cam[:5])


def test_unknown_scenario_lists_the_known_ones():
    with pytest.raises(SimulationError) as err:
        build_scenario("synthia")
    for name in SCENARIOS:
        assert name in str(err.value)


def test_kitti_paths_aligns_real_drives(shared_data):
    plan = build_scenario("kitti-paths", ScenarioOptions(kitti_root=shared_data / "kitti"))
    k00, k07 = plan.robots
    assert (k00.name, k07.name, len(k00), len(k07)) == ("kitti00", "kitti07", 301, 351)  # half-open 2600-2901
    note = plan.notes["kitti_alignment"]["kitti07"]
    assert note["overlap_length_m"] > 150.0 and note["rmse_m"] < 2.0
    assert shared_view_length_m(k07, k00) > 150.0
    assert (
        footprint_clearance_m(plan.world, np.concatenate([k00.positions_xyz, k07.positions_xyz])[:, :2]) > 0.9
    )


def test_kitti_paths_without_data_is_a_clear_error(tmp_path):
    with pytest.raises(DataError, match="KITTI ground truth"):
        build_scenario("kitti-paths", ScenarioOptions(kitti_root=tmp_path))
    with pytest.raises(ConfigError, match="SEQ:START-END"):
        build_scenario("kitti-paths", ScenarioOptions(kitti_root=tmp_path, kitti_robots=("07:abc",)))


def test_a_uav_below_the_roofs_is_refused_and_one_above_them_flies_its_altitude():
    from shgm_slam.sim.scenarios import under_rooftops

    low = ScenarioOptions(seed=16, uav_altitude_m=(20.0, 26.0))  # its approach crosses blocks with 36 m roofs
    with pytest.raises(SimulationError, match="flies through buildings"):
        build_scenario("airsim-like", low)
    plan = build_scenario("airsim-like", ScenarioOptions(seed=16, uav_altitude_m=(85.0, 95.0)))
    uav = next(r for r in plan.robots if r.kind is RobotKind.UAV)
    z = uav.positions_xyz[:, 2]
    assert 85.0 <= z.min() and z.max() <= 95.0 and z.max() - z.min() > 5.0
    assert not under_rooftops(plan.world, uav.positions_xyz).any()
    building = next(o for o in plan.world.objects if o.kind is ObjectKind.BUILDING)
    centre = np.array(building.centre_xyz)
    top = centre + np.array([0.0, 0.0, building.size_xyz[2] / 2.0 + 1.0])
    assert under_rooftops(plan.world, np.stack([centre, top])).tolist() == [True, False]
