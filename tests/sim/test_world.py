"""World layout and mesh: determinism by seed, ids and labels, triangles inside their object boxes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shgm_slam.errors import SimulationError
from shgm_slam.labels import Label
from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.shapes import KIND_LABEL, Material, ObjectKind
from shgm_slam.sim.world import ObjectList, assemble_world

SMALL = CityParams(size_x_m=300.0, size_y_m=260.0, block_min_m=45.0, block_max_m=80.0, outskirts_m=15.0)


def test_city_is_deterministic_by_seed():
    a, b, c = build_city(SMALL, seed=4), build_city(SMALL, seed=4), build_city(SMALL, seed=5)
    assert json.dumps(a.to_json()) == json.dumps(b.to_json())
    np.testing.assert_array_equal(a.vertices_xyz, b.vertices_xyz)
    assert json.dumps(a.to_json()) != json.dumps(c.to_json())


def test_city_has_every_class_and_consistent_ids():
    w = build_city(SMALL, seed=1)
    assert [o.id for o in w.objects] == list(range(len(w.objects)))
    kinds = {o.kind for o in w.objects}
    assert {
        ObjectKind.BUILDING,
        ObjectKind.TREE,
        ObjectKind.CAR,
        ObjectKind.STREET_LAMP,
        ObjectKind.ROAD,
        ObjectKind.SIDEWALK,
        ObjectKind.TERRAIN,
        ObjectKind.TRAFFIC_SIGN,
    } <= kinds
    present = set(np.unique(w.tri_label).tolist())
    assert {
        Label.ROAD,
        Label.SIDEWALK,
        Label.BUILDING,
        Label.POLE,
        Label.VEGETATION,
        Label.TERRAIN,
        Label.CAR,
        Label.TRAFFIC_SIGN,
    } <= present
    assert np.array_equal(np.unique(w.tri_object), np.arange(len(w.objects)))  # every object has triangles
    own = w.tri_material != Material.MARKING  # markings belong to the road object
    labels = np.array([o.label for o in w.objects])
    assert np.array_equal(
        w.tri_label[own & (w.tri_material != Material.LIGHT)],
        labels[w.tri_object[own & (w.tri_material != Material.LIGHT)]],
    )
    assert all(o.label == KIND_LABEL[o.kind] for o in w.objects)
    doc = w.to_json()
    assert doc["format"] == "shgm-world/1" and len(doc["objects"]) == len(w.objects)
    assert set(doc["objects"][0]) >= {"id", "label", "label_name", "kind", "position", "size", "yaw"}


def test_triangles_lie_inside_their_object_box():
    w = build_city(SMALL, seed=2)
    _, centres, sizes, yaws = w.objects_array()
    keep = w.tri_material != Material.MARKING
    obj = w.tri_object[keep]
    v = w.vertices_xyz[w.faces[keep]]  # (F, 3, 3)
    d = v - centres[obj][:, None]
    c, s = np.cos(yaws[obj])[:, None], np.sin(yaws[obj])[:, None]
    local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    slack = 0.06 * sizes[obj][:, None] + 1e-6  # tree crowns bulge a little (radial jitter)
    assert np.all(np.abs(local) <= 0.5 * sizes[obj][:, None] + slack)


def test_small_hand_made_world():
    objs = ObjectList()
    objs.add_on_ground(ObjectKind.BUILDING, 10.0, 0.0, (2.0, 4.0, 3.0))
    w = assemble_world(objs.objects)
    assert w.num_triangles == 24  # main box + roof unit
    np.testing.assert_allclose(w.bounds_xyz, [[9, -2, 0], [11, 2, 3]])


def test_too_small_city_is_a_clear_error():
    with pytest.raises(SimulationError, match="too small"):
        build_city(CityParams(size_x_m=100.0, size_y_m=100.0))
