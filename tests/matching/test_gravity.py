"""``matching/gravity.py``: the vertical two graphs share, read from their nodes, and the match it chooses."""

from __future__ import annotations

import json
from types import SimpleNamespace

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


def test_georeferenced_map_files_match_as_well_as_at_the_origin(map_pairs, tmp_path):
    """Map layers come in projected coordinates (UTM: hundreds of kilometres east, thousands north, a
    terrain height): both graphs moved there together, written to graph files and matched through the CLI,
    are localized as often as at the origin, with no wrong claim and no far-apart negative accepted (the
    vertical is still read from the graphs, the clique distances keep their precision)."""
    M = make_pose(rot_z(0.7), np.array([512_345.6, 5_403_210.9, 312.0]))
    runner = CliRunner()

    def localized(pair, T_frame: np.ndarray, name: str) -> tuple[bool, bool, int]:
        """(accepted, accepted and within the benchmark's tolerance of the truth, the rotation freedom chosen)
        in the frame ``T_frame``."""
        path_a = write_graph(tmp_path / f"{name}_a.json", pair.graph_a.transformed(T_frame))
        path_b = write_graph(tmp_path / f"{name}_b.json", pair.graph_b.transformed(T_frame))
        doc = json.loads(runner.invoke(app, ["match", str(path_a), str(path_b), "--json"]).output)
        if not doc["success"]:
            return False, False, doc["dof"]
        T_map = np.linalg.inv(T_frame) @ np.asarray(doc["T_a_b"]) @ T_frame  # back in the benchmark's frame
        result = SimpleNamespace(success=True, T_a_b=T_map, T_a_b_hypothesis=T_map)
        return True, pair.overlapping and score(result, pair)[0], doc["dof"]

    far = [localized(p, M, f"{p.index}_{p.overlapping}") for p in map_pairs]
    near = [localized(p, np.eye(4), f"{p.index}_{p.overlapping}_o") for p in map_pairs]
    for p, (accepted, right, dof), at_origin in zip(map_pairs, far, near, strict=True):
        assert right or not accepted, f"pair {p.index}: a wrong claim at georeferenced coordinates"
        assert dof == at_origin[2]  # the vertical read from the graphs does not depend on where they lie
    overlapping = [k for k, p in enumerate(map_pairs) if p.overlapping]
    assert sum(far[k][1] for k in overlapping) >= sum(near[k][1] for k in overlapping) - 1
    assert sum(far[k][1] for k in overlapping) >= 0.8 * len(overlapping)
