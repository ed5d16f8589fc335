"""Graph building from ground truth and the ``shgm-slam graph`` command, on a rendered world of plates."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.config import ExtractionConfig, KeyframeConfig, ShgmConfig
from shgm_slam.data import SequenceWriter, open_sequence
from shgm_slam.errors import DataError
from shgm_slam.geometry.camera import pixel_rays
from shgm_slam.geometry.se3 import make_pose, rot_y
from shgm_slam.graph.build import build_graph_from_sequence, select_keyframes
from shgm_slam.io.graph_json import read_graph
from shgm_slam.labels import Label
from shgm_slam.types import Frame, Intrinsics
from tests.spies import record_depth_percentiles

INTR = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=23.5, width=64, height=48)
# fronto-parallel plates: label, centre (x, y, z) in the world, width, height (m); never occlude each other
PLATES = [
    (Label.BUILDING, (-2.0, -2.0, 12.0), 4.0, 3.0),
    (Label.CAR, (3.0, 1.5, 10.0), 3.0, 1.5),
    (Label.POLE, (6.0, -1.5, 14.0), 1.0, 4.0),
    (Label.VEGETATION, (-1.0, 5.0, 16.0), 4.0, 1.5),
]
CAMERA_X = np.arange(0.0, 4.01, 0.5)


def render(x_cam: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth and labels of the plates seen from a camera at (x_cam, 0, 0) looking along +z."""
    rays = pixel_rays(INTR)
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    labels = np.full(depth.shape, 255, np.uint8)
    for label, (x, y, z), w, h in sorted(PLATES, key=lambda p: -p[1][2]):  # far to near
        hit = (np.abs(rays[..., 0] * z - (x - x_cam)) <= w / 2) & (np.abs(rays[..., 1] * z - y) <= h / 2)
        depth[hit], labels[hit] = z, label
    return depth, labels


@pytest.fixture(scope="module")
def plate_sequence(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("plates") / "seq"
    rgb = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    with SequenceWriter(root, INTR) as writer:
        for i, x in enumerate(CAMERA_X):
            depth, labels = render(x)
            T = make_pose(np.eye(3), np.array([x, 0.0, 0.0]))
            frame = Frame(i, 0.1 * i, INTR, image_rgb=rgb, depth_m=depth, label_ids=labels, T_world_cam=T)
            writer.write(frame)
    return root


def plate_config() -> ShgmConfig:
    extraction = ExtractionConfig(min_blob_fraction=0.002)
    return ShgmConfig(extraction=extraction, keyframes=KeyframeConfig(distance_m=1.0))


def test_select_keyframes_by_distance_and_angle():
    poses = np.stack([make_pose(np.eye(3), np.array([0.4 * i, 0, 0])) for i in range(11)])
    np.testing.assert_array_equal(select_keyframes(poses, 1.0, 30.0), [0, 3, 6, 9])
    turning = np.stack([make_pose(rot_y(np.radians(10.0 * i)), np.zeros(3)) for i in range(7)])
    np.testing.assert_array_equal(select_keyframes(turning, 1.0, 25.0), [0, 3, 6])


def test_build_finds_each_plate_once_at_its_centre(plate_sequence):
    seen = []
    graph = build_graph_from_sequence(
        open_sequence(plate_sequence), plate_config(), progress=lambda done, n: seen.append((done, n))
    )
    assert graph.keyframe_ids == [0, 2, 4, 6, 8]
    assert seen[-1] == (5, 5)
    a = graph.arrays()
    assert len(a) == len(PLATES)
    for label, centre, _, _ in PLATES:
        row = int(np.flatnonzero(a.label_ids == label)[0])
        np.testing.assert_allclose(a.positions_xyz[row], centre, atol=0.3)  # under a pixel at these depths
        assert graph.node_state(int(a.node_ids[row])).num_observations == 5
    d = np.linalg.norm(a.positions_xyz[:, None] - a.positions_xyz[None], axis=2)
    assert a.num_edges == int(np.triu(d < 10.0, 1).sum()) > 0


def test_build_requires_ground_truth_depth_and_labels(tmp_path):
    rgb = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    with SequenceWriter(tmp_path / "nolabels", INTR, write_labels=False) as writer:
        depth, _ = render(0.0)
        writer.write(Frame(0, 0.0, INTR, image_rgb=rgb, depth_m=depth))
    with pytest.raises(DataError, match=r"no ground-truth poses .* no labels"):
        build_graph_from_sequence(open_sequence(tmp_path / "nolabels"), plate_config())


def test_graph_command_writes_a_readable_graph(plate_sequence, tmp_path):
    cfg_path = tmp_path / "cfg.yaml"
    cfg_path.write_text(plate_config().to_yaml())
    out = tmp_path / "graph.json"
    args = ["graph", f"{plate_sequence}:0-5", "--out", str(out), "--config", str(cfg_path)]
    args += ["--connectivity", "3"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "4 nodes" in " ".join(result.output.split()) and str(out) in result.output.replace("\n", "")
    g = read_graph(out)
    assert len(g) == 4 and g.num_edges == 0  # plates are farther apart than 3 m
    assert json.loads(out.read_text())["format"] == "shgm-graph/1"


def test_graph_command_reports_bad_input_in_one_line(tmp_path):
    result = CliRunner().invoke(app, ["graph", str(tmp_path / "nowhere"), "--out", str(tmp_path / "g.json")])
    assert result.exit_code == 2
    assert "does not exist" in " ".join(result.output.split())
    result = CliRunner().invoke(app, ["graph", str(tmp_path), "--out", "g.json", "--merge-radius", "-1"])
    assert result.exit_code == 2 and "merge-radius" in result.output


def test_depth_a_model_wrote_places_thin_objects_as_configured(plate_sequence, tmp_path, monkeypatch):
    """A perceived copy (``perceive.json`` names a depth model) builds with the predicted-depth percentiles,
    through ``build_graph_from_sequence`` and the ``graph`` command; rendered depth keeps the mean."""
    import shutil

    import shgm_slam.graph.extraction as extraction_module

    seen = record_depth_percentiles(monkeypatch, extraction_module)
    cfg = plate_config()
    build_graph_from_sequence(open_sequence(plate_sequence), cfg, depth_predicted=True)
    assert seen and all(s == cfg.extraction.predicted_depth_percentiles for s in seen)
    seen.clear()
    plain = build_graph_from_sequence(open_sequence(plate_sequence), cfg)
    assert seen and all(s is None for s in seen)
    perceived = tmp_path / "perceived"
    shutil.copytree(plate_sequence, perceived)
    (perceived / "perceive.json").write_text('{"format": "shgm-perceive/1", "depth_model": {"path": "d.onnx"}}')
    seen.clear()
    out = tmp_path / "g.json"
    result = CliRunner().invoke(app, ["graph", str(perceived), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert seen and all(s == ShgmConfig().extraction.predicted_depth_percentiles for s in seen)
    # fronto-parallel plates have one depth per plate: any percentile is the mean, the same graph
    ours = build_graph_from_sequence(open_sequence(perceived), cfg, depth_predicted=True).arrays()
    np.testing.assert_allclose(ours.positions_xyz, plain.arrays().positions_xyz, atol=1e-5)


def test_graph_command_refuses_to_write_a_graph_without_objects(plate_sequence, tmp_path):
    cfg = plate_config()
    cfg.extraction.max_depth_m = 0.6  # every plate lies farther: no object in range
    cfg_path = tmp_path / "cfg.yaml"
    cfg_path.write_text(cfg.to_yaml())
    out = tmp_path / "graph.json"
    result = CliRunner().invoke(app, ["graph", f"{plate_sequence}:0-5", "--out", str(out), "--config", str(cfg_path)])
    assert result.exit_code == 2 and "gave no object" in " ".join(result.output.split()), result.output
    assert not out.exists()
