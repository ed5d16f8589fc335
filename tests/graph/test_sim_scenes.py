"""Extraction and graph building on rendered frames of the simulated world, checked against world.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import ExtractionConfig, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.geometry.camera import project
from shgm_slam.geometry.se3 import inverse, transform_points
from shgm_slam.graph.build import build_graph_from_sequence
from shgm_slam.graph.extraction import extract_objects_from_config
from shgm_slam.labels import Label

COMPACT = (Label.CAR, Label.POLE, Label.VEGETATION, Label.TRAFFIC_SIGN, Label.TRAFFIC_LIGHT)
"""Object classes whose visible-surface centroid lies near the object's centre (not facades or ground)."""


def world_objects(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) labels, (n, 3) centres and (n,) half diagonals of the ground-truth objects (world frame)."""
    objects = json.loads((root / "world.json").read_text())["objects"]
    labels = np.array([o["label"] for o in objects])
    centres = np.array([o["position"] for o in objects], dtype=np.float64)
    half_diag = np.linalg.norm(np.array([o["size"] for o in objects], dtype=np.float64), axis=1) / 2
    return labels, centres, half_diag


def nearest_same_label(labels, centres, label: int, point: np.ndarray) -> tuple[int, float]:
    same = np.flatnonzero(labels == label)
    d = np.linalg.norm(centres[same] - point, axis=1)
    return int(same[np.argmin(d)]), float(d.min())


@pytest.mark.parametrize("robot", ["car1", "car2"])
def test_extraction_finds_the_world_objects_in_rendered_frames(tiny_scenario, robot):
    labels, centres, half_diag = world_objects(tiny_scenario)
    seq = open_sequence(tiny_scenario / robot)
    cfg = ExtractionConfig()
    close, dists, found, near_cars = [], [], set(), set()
    for i in range(0, len(seq), 3):
        frame = seq[i]
        objs = extract_objects_from_config(frame, cfg)
        for label, centroid in zip(objs.label_ids, objs.centroids_world, strict=True):
            if label in COMPACT:
                j, d = nearest_same_label(labels, centres, label, centroid)
                close.append(d < half_diag[j] + 1.0)
                dists.append(d)
                found.add(j)
        # cars 4-15 m ahead whose centre projects well inside the image should be found
        p_cam = transform_points(inverse(frame.T_world_cam), centres)
        uv, in_front = project(p_cam, frame.intrinsics)
        W, H = frame.intrinsics.size_wh
        inside = (uv[:, 0] > 0.06 * W) & (uv[:, 0] < 0.94 * W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
        near = in_front & (p_cam[:, 2] > 4) & (p_cam[:, 2] < 15) & inside & (labels == Label.CAR)
        near_cars |= set(np.flatnonzero(near).tolist())
    assert len(dists) > 20
    assert np.mean(close) >= 0.95  # centroids lie on their objects
    assert np.median(dists) < 2.0
    assert near_cars and len(near_cars & found) >= 0.8 * len(near_cars)


def test_graph_from_a_simulated_sequence_sits_on_the_world_objects(tiny_scenario):
    labels, centres, _ = world_objects(tiny_scenario)
    seq = open_sequence(tiny_scenario / "car1")
    graph = build_graph_from_sequence(seq, ShgmConfig())
    a = graph.arrays()
    assert len(graph.keyframe_ids) >= 10 and len(a) >= 20 and a.num_edges >= len(a)
    rows = np.flatnonzero(np.isin(a.label_ids, COMPACT))
    d = np.array([nearest_same_label(labels, centres, a.label_ids[r], a.positions_xyz[r])[1] for r in rows])
    assert rows.size >= 10
    assert np.median(d) < 2.0 and np.percentile(d, 90) < 3.5
    # repeated sightings were merged into nodes instead of piling up
    observations = sum(graph.node_state(i).num_observations for i in a.node_ids)
    assert len(a) < 0.5 * observations
