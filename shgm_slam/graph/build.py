"""A robot's semantic graph from a sequence with ground-truth poses, depth and labels (no odometry).

This is what ``shgm-slam graph`` runs: keyframes every ``distance_m`` metres or ``angle_deg`` degrees
along the ground-truth trajectory, objects extracted from each keyframe's depth + labels (Sec. III-A),
inserted into a ``SemanticGraph`` in the ground-truth world frame.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shgm_slam.config import ShgmConfig
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import inverse, rotation_angle
from shgm_slam.graph.extraction import extract_objects_from_config
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.scene_scale import resolve_robot_config, sample_scene_scale
from shgm_slam.types import Sequence

ProgressFn = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each keyframe."""


def select_keyframes(poses: np.ndarray, distance_m: float, angle_deg: float) -> np.ndarray:
    """Indices of keyframes along a trajectory: the first pose, then every pose that moved at least
    ``distance_m`` metres or turned at least ``angle_deg`` degrees from the previous keyframe.

    Args:
        poses: (N, 4, 4) ``T_world_cam``.

    Returns:
        (K,) int64 increasing frame indices.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape[0] == 0:
        return np.zeros(0, np.int64)
    keep = [0]
    angle_rad = np.radians(angle_deg)
    for i in range(1, poses.shape[0]):  # sequential by nature; cheap (no images touched)
        T_last_i = inverse(poses[keep[-1]]) @ poses[i]
        if np.linalg.norm(T_last_i[:3, 3]) >= distance_m or rotation_angle(T_last_i) >= angle_rad:
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


def build_graph_from_sequence(
    sequence: Sequence,
    cfg: ShgmConfig,
    *,
    keyframe_every_m: float | None = None,
    depth_predicted: bool = False,
    progress: ProgressFn | None = None,
) -> SemanticGraph:
    """Build the semantic graph of a sequence from its ground-truth poses, depth and labels.

    Args:
        sequence: frames with ``depth_m``, ``label_ids`` and ground-truth ``T_world_cam``.
        cfg: ``extraction``, ``graph`` and ``keyframes`` sections are used; extraction fields left None
            are derived from the sequence's first frames (``scene_scale``).
        keyframe_every_m: overrides ``cfg.keyframes.distance_m``.
        depth_predicted: the depth files were written by a depth model (``perceive.depth_model_of``): thin
            objects are placed as ``cfg.extraction.predicted_depth_percentiles`` says.
        progress: optional ``progress(done, total)`` callback per keyframe.

    Returns:
        The graph in the ground-truth world frame; keyframe ids are the sequence's frame indices.

    Raises:
        DataError: the sequence has no ground-truth poses, depth or labels.
    """
    missing = [
        what
        for what, ok in (
            ("ground-truth poses (poses.txt)", sequence.gt_poses is not None),
            ("depth (depth/)", sequence.has_depth),
            ("labels (semantic/)", sequence.has_labels),
        )
        if not ok
    ]
    if missing:
        raise DataError(
            f"sequence {sequence.name} has no {', no '.join(missing)}; building a graph from ground truth "
            "needs all three (simulate a sequence with `shgm-slam simulate`, or use `shgm-slam run`)"
        )
    gt = np.asarray(sequence.gt_poses, dtype=np.float64)
    distance_m = cfg.keyframes.distance_m if keyframe_every_m is None else keyframe_every_m
    if distance_m <= 0:
        raise ConfigError(f"keyframe spacing must be positive, got {distance_m} m")
    keyframes = select_keyframes(gt, distance_m, cfg.keyframes.angle_deg)
    graph = SemanticGraph(cfg.graph.merge_radius_m, cfg.graph.connectivity_m)
    extraction = resolve_robot_config(cfg, sample_scene_scale(sequence, lambda f: (f.depth_m, f.label_ids))).extraction
    for done, i in enumerate(keyframes.tolist(), start=1):
        frame = sequence[i]
        objects = extract_objects_from_config(frame, extraction, T_world_cam=gt[i], depth_predicted=depth_predicted)
        graph.add_keyframe(i, gt[i], objects)
        if progress is not None:
            progress(done, keyframes.size)
    return graph
