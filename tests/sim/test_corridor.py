"""The city grown around drive paths (``sim.corridor``): roads and their objects continue past each drive's
ends, so no camera at a drive's end looks onto empty terrain, and nothing stands on a drive."""

from __future__ import annotations

import numpy as np

from shgm_slam.labels import Label
from shgm_slam.sim.corridor import EXTEND_M, build_corridor_city, extend_path
from shgm_slam.sim.trajectories import resample_path


def test_extend_path_continues_straight_along_the_end_headings():
    arc = np.stack([np.linspace(0, 50, 51), 0.002 * np.linspace(0, 50, 51) ** 2], 1)  # bends left
    dense = resample_path(arc, 1.0)
    ext = extend_path(dense, 30.0)
    assert len(ext) == len(dense) + 60
    np.testing.assert_allclose(ext[30 : 30 + len(dense)], dense)
    tail = ext[-31:]
    steps = np.diff(tail, axis=0)
    np.testing.assert_allclose(np.linalg.norm(steps, axis=1), 1.0, atol=1e-9)  # 1 m spacing kept
    np.testing.assert_allclose(steps, steps[0][None].repeat(len(steps), 0), atol=1e-9)  # straight
    assert steps[0] @ (dense[-1] - dense[-11]) > 0  # onward, not back
    head = ext[:31]
    assert (dense[0] - head[0]) @ (dense[10] - dense[0]) > 0  # behind the start


def test_extend_path_leaves_a_standing_robot_alone():
    still = np.zeros((3, 2))
    np.testing.assert_array_equal(extend_path(still), still)


def test_objects_line_the_road_beyond_the_drive_and_never_stand_on_it():
    path = np.stack([np.linspace(0.0, 150.0, 151), np.zeros(151)], 1)
    world = build_corridor_city([path], seed=3)
    centres = np.array([o.centre_xyz for o in world.objects])
    labels = np.array([o.label for o in world.objects])
    things = ~np.isin(labels, [Label.ROAD, Label.SIDEWALK, Label.TERRAIN])
    ahead = things & (centres[:, 0] > 150 + 10) & (centres[:, 0] < 150 + EXTEND_M - 10)
    behind = things & (centres[:, 0] < -10) & (centres[:, 0] > -EXTEND_M + 10)
    assert (labels[ahead] == Label.BUILDING).sum() >= 3 and (labels[ahead] == Label.VEGETATION).sum() >= 3
    assert (labels[behind] == Label.BUILDING).sum() >= 3
    on_lane = things & (np.abs(centres[:, 1]) < 2.0) & (centres[:, 0] > -EXTEND_M) & (centres[:, 0] < 150 + EXTEND_M)
    assert not on_lane.any()
    road = world.tri_label == Label.ROAD
    road_x = world.vertices_xyz[world.faces[road].ravel(), 0]
    assert road_x.max() > 150 + EXTEND_M - 5 and road_x.min() < -EXTEND_M + 5
