"""``matching/gravity.py``: the vertical two graphs share, read from their nodes, and the match it chooses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.bench.localization_sparse import SparseOptions, make_pairs, score
from shgm_slam.cli import app
from shgm_slam.config import DescriptorConfig, Dof, GraphConfig, MatchingConfig
from shgm_slam.geometry.se3 import make_pose, rot_x, rot_z
from shgm_slam.io.graph_json import write_graph
from shgm_slam.matching import match_graphs
from shgm_slam.matching.gravity import choose_dof, flat_axis, shared_up_axis
from shgm_slam.sim.city import CityParams, build_city


def _map_layout(seed: int, n: int = 60) -> np.ndarray:
    """(n, 3) objects of a z-up map: 200 x 60 m of street, 0-12 m high."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 200, n), rng.uniform(0, 60, n), rng.uniform(0, 12, n)])


def _turned(points: np.ndarray, R: np.ndarray) -> np.ndarray:
    return points @ R.T


def test_a_map_lies_flat_along_its_vertical_whatever_its_yaw():
    points = _map_layout(0)
    assert flat_axis(points) == 2
    assert flat_axis(_turned(points, rot_z(1.1))) == 2  # a turn about the vertical keeps it
    kitti = points[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # the KITTI camera frame: y down
    assert flat_axis(kitti) == 1


@pytest.mark.parametrize("tilt_deg", [8.0, 30.0, 45.0])
def test_a_tilted_or_round_graph_has_no_flat_axis(tilt_deg):
    tilted = _turned(_map_layout(1), rot_x(np.radians(tilt_deg)))
    assert flat_axis(tilted) is None
    blob = np.random.default_rng(2).normal(0.0, 30.0, (80, 3))
    assert flat_axis(blob) is None
    assert flat_axis(_map_layout(3)[:3]) is None  # three nodes say nothing about a plane


def test_the_shared_vertical_keeps_the_configured_sign():
    a, b = _map_layout(4), _turned(_map_layout(5), rot_z(-2.0))
    np.testing.assert_array_equal(shared_up_axis(a, b), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(shared_up_axis(a, b, np.array([0.0, 0.0, -1.0])), [0.0, 0.0, -1.0])
    np.testing.assert_array_equal(shared_up_axis(a, b, np.array([0.0, -1.0, 0.0])), [0.0, 0.0, 1.0])
    assert shared_up_axis(a, a[:, [0, 2, 1]]) is None  # flat along different axes


def test_choose_dof():
    cfg = MatchingConfig()  # KITTI camera frame: up -y, 6-DoF
    a, b = _map_layout(6), _turned(_map_layout(7), rot_z(0.7))
    auto, note = choose_dof(Dof.AUTO, a, b, cfg)
    assert auto.gravity_aligned and auto.up_axis == (0.0, 0.0, 1.0) and "4-DoF about +z" in note
    six, note = choose_dof(Dof.SIX, a, b, cfg)
    assert not six.gravity_aligned and six.up_axis == (0.0, 0.0, 1.0) and "6-DoF" in note
    tilted = _turned(b, rot_x(0.5))
    free, note = choose_dof(Dof.AUTO, a, tilted, cfg)
    assert not free.gravity_aligned and free.up_axis == (0.0, 0.0, 1.0) and "of A" in note
    blob = np.random.default_rng(8).normal(0.0, 30.0, (80, 3))
    assert choose_dof(Dof.AUTO, blob, tilted, cfg)[0] == cfg
    four, note = choose_dof(Dof.FOUR, blob, tilted, cfg)
    assert four.gravity_aligned and four.up_axis == cfg.up_axis and "--dof 4" in note
    configured = cfg.model_copy(update={"gravity_aligned": True})
    assert choose_dof(Dof.AUTO, blob, tilted, configured)[0] == configured


@pytest.fixture(scope="module")
def map_pairs():
    """Map-like pairs of the sparse benchmark (z-up) on tuning world 15."""
    return make_pairs(build_city(CityParams(), seed=15), 15, SparseOptions(), GraphConfig().connectivity_m)


def test_z_up_maps_with_the_default_config_accept_no_far_apart_negative(map_pairs):
    """With the default up (-y, KITTI's camera) the chance model shifted hypotheses across the street and into
    the air on a z-up map, found no repeats and accepted an alias between two far-apart streets; read from the
    graphs, the vertical is +z and the alias is rejected, while the overlapping pairs are still localized."""
    cfg = MatchingConfig()
    negatives = [p for p in map_pairs if not p.overlapping]
    overlapping = [p for p in map_pairs if p.overlapping]
    old = [match_graphs(p.graph_a, p.graph_b, DescriptorConfig(), cfg).success for p in negatives]
    assert any(old)  # what the default up did
    for p in negatives:
        chosen, _ = choose_dof(Dof.AUTO, p.graph_a.positions_xyz, p.graph_b.positions_xyz, cfg)
        assert not match_graphs(p.graph_a, p.graph_b, DescriptorConfig(), chosen).success
    right = 0
    for p in overlapping:
        chosen, _ = choose_dof(Dof.AUTO, p.graph_a.positions_xyz, p.graph_b.positions_xyz, cfg)
        result = match_graphs(p.graph_a, p.graph_b, DescriptorConfig(), chosen)
        assert score(result, p)[0] or not result.success  # no wrong claim
        right += result.success
    assert right >= 0.8 * len(overlapping)


def test_match_cli_reports_the_rotation_freedom(map_pairs, tmp_path):
    cfg = MatchingConfig()

    def localized(p) -> bool:
        chosen, _ = choose_dof(Dof.AUTO, p.graph_a.positions_xyz, p.graph_b.positions_xyz, cfg)
        result = match_graphs(p.graph_a, p.graph_b, DescriptorConfig(), chosen)
        return result.success and score(result, p)[0]

    pair = next(p for p in map_pairs if p.overlapping and localized(p))
    path_a = write_graph(tmp_path / "a.json", pair.graph_a)
    path_b = write_graph(tmp_path / "b.json", pair.graph_b)
    runner = CliRunner()
    doc = json.loads(runner.invoke(app, ["match", str(path_a), str(path_b), "--json"]).output)
    assert doc["dof"] == 4 and doc["up_axis"] == [0.0, 0.0, 1.0] and doc["success"]
    doc = json.loads(runner.invoke(app, ["match", str(path_a), str(path_b), "--json", "--dof", "6"]).output)
    assert doc["dof"] == 6 and "up_axis" not in doc
    text = runner.invoke(app, ["match", str(path_a), str(path_b)]).output
    assert "4-DoF about +z" in text
    T = make_pose(rot_x(0.4), np.zeros(3))
    tilted = write_graph(tmp_path / "tilted.json", pair.graph_b.transformed(T))
    doc = json.loads(runner.invoke(app, ["match", str(path_a), str(tilted), "--json"]).output)
    assert doc["dof"] == 6
