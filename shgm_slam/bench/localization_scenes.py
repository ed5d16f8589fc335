"""Scenes of the localization benchmark: rendered keyframes cached on disk, graphs built from them.

Rendering dominates the benchmark's cost, so every robot's keyframes (ground-truth poses, depth,
labels and object ids) are ray-cast once per (scenario, world seed, resolution) and kept under the
cache folder as memory-mapped ``.npy`` stacks. Everything downstream is recomputed from the cache in
seconds: perception-like corruption (``sim.corruption``, seeded per frame), object extraction with any
``ExtractionConfig`` and graph building with any ``GraphConfig``, which is what the ablations vary.

Keyframes follow the system's rule (``graph.build.select_keyframes``: every ``keyframe_every_m`` metres
or ``keyframe_angle_deg`` degrees along the ground-truth trajectory). Poses and graphs are in the
simulated world frame (z up, metres), shared by all robots: the ground-truth ``T_a_b`` is identity.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shgm_slam.config import ExtractionConfig, GraphConfig
from shgm_slam.errors import SimulationError
from shgm_slam.graph.build import select_keyframes
from shgm_slam.graph.extraction import ObjectObservations, extract_objects
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.io.json_text import to_json_text
from shgm_slam.sim.corruption import CorruptionLevels, apply_corruption
from shgm_slam.sim.render import Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario
from shgm_slam.sim.trajectories import RobotKind
from shgm_slam.types import GraphArrays, Intrinsics

CACHE_VERSION = 1
"""Bump when the cached arrays change meaning (old caches are then re-rendered)."""

ProgressFn = Callable[[str, int, int], None]
"""``progress(what, done, total)`` while rendering."""


@dataclass(frozen=True)
class SceneSpec:
    """Which world to render: a scenario of ``sim.scenarios`` at one seed and image size.

    Attributes:
        scenario: ``synthia-like``, ``airsim-like`` or ``disjoint``.
        seed: world and trajectory seed.
        resolution: (width, height) pixels.
        compact: the scenario's small variant (quick runs, tests).
        keyframe_every_m, keyframe_angle_deg: keyframe rule along the ground-truth path.
        max_depth_m: renderer depth range (farther = invalid).
    """

    scenario: str
    seed: int = 0
    resolution: tuple[int, int] = (640, 192)
    compact: bool = False
    keyframe_every_m: float = 2.0
    keyframe_angle_deg: float = 15.0
    max_depth_m: float = 200.0

    @property
    def folder_name(self) -> str:
        w, h = self.resolution
        tag = "-compact" if self.compact else ""
        return f"{self.scenario}-seed{self.seed}-{w}x{h}{tag}-kf{self.keyframe_every_m:g}m-v{CACHE_VERSION}"


@dataclass
class RenderedRobot:
    """One robot's rendered keyframes (K of them), arrays memory-mapped from the cache.

    Attributes:
        name, kind: robot name and kind (car / uav).
        intrinsics: camera of the images.
        frame_indices: (K,) int64 frame index of each keyframe in the robot's trajectory.
        T_world_cam: (K, 4, 4) float64 ground-truth poses, world frame (z up).
        depth_m: (K, H, W) float16 z-depth, metres, 0 = invalid.
        label_ids: (K, H, W) uint8 Cityscapes train ids.
        object_ids: (K, H, W) int32 world object ids (-1 = sky), segments for label corruption.
        path_length_m: length of the whole trajectory, metres.
    """

    name: str
    kind: RobotKind
    intrinsics: Intrinsics
    frame_indices: np.ndarray
    T_world_cam: np.ndarray
    depth_m: np.ndarray
    label_ids: np.ndarray
    object_ids: np.ndarray
    path_length_m: float

    def __len__(self) -> int:
        return int(self.frame_indices.shape[0])


def _render_robot(
    renderer: Renderer, T_world_cam: np.ndarray, folder: Path, name: str, progress: ProgressFn | None
) -> None:
    """Write the stacks of one robot's keyframes into ``folder`` (streamed through memmaps)."""
    K = renderer.intrinsics
    n, shape = T_world_cam.shape[0], (T_world_cam.shape[0], K.height, K.width)
    folder.mkdir(parents=True, exist_ok=True)
    depth = np.lib.format.open_memmap(folder / "depth.npy", "w+", np.float16, shape)
    labels = np.lib.format.open_memmap(folder / "labels.npy", "w+", np.uint8, shape)
    objects = np.lib.format.open_memmap(folder / "objects.npy", "w+", np.int32, shape)
    for k in range(n):
        view = renderer.render(T_world_cam[k])
        depth[k], labels[k], objects[k] = view.depth_m, view.label_ids, view.object_ids
        if progress is not None:
            progress(name, k + 1, n)
    for arr in (depth, labels, objects):
        arr.flush()
    del depth, labels, objects


def load_scene(
    spec: SceneSpec, cache_dir: Path, progress: ProgressFn | None = None
) -> dict[str, RenderedRobot]:
    """The rendered keyframes of every robot of ``spec``, rendering them into ``cache_dir`` first if needed.

    Returns:
        robot name -> ``RenderedRobot`` (arrays memory-mapped read-only).

    Raises:
        SimulationError: the scenario cannot be built or the cache folder cannot be written.
    """
    folder = Path(cache_dir) / spec.folder_name
    meta_path = folder / "meta.json"
    if not meta_path.is_file():
        if folder.exists():
            shutil.rmtree(folder)  # an interrupted render: start over
        plan = build_scenario(
            spec.scenario, ScenarioOptions(seed=spec.seed, compact=spec.compact, max_depth_m=spec.max_depth_m)
        )
        intrinsics = make_intrinsics(*spec.resolution)
        robots_meta = []
        try:
            with Renderer(plan.world, intrinsics, max_depth_m=spec.max_depth_m, threads=2) as renderer:
                for traj in plan.robots:
                    kf = select_keyframes(traj.T_world_cam, spec.keyframe_every_m, spec.keyframe_angle_deg)
                    sub = folder / traj.name
                    _render_robot(renderer, traj.T_world_cam[kf], sub, traj.name, progress)
                    np.save(sub / "frames.npy", kf)
                    np.save(sub / "poses.npy", traj.T_world_cam[kf])
                    robots_meta.append(
                        {
                            "name": traj.name,
                            "kind": traj.kind.value,
                            "path_length_m": round(traj.path_length_m, 2),
                            "keyframes": int(kf.size),
                        }
                    )
        except OSError as exc:
            raise SimulationError(f"cannot write the benchmark cache {folder}: {exc}") from None
        meta = {
            "version": CACHE_VERSION,
            "spec": spec.__dict__ | {"resolution": list(spec.resolution)},
            "intrinsics": intrinsics.__dict__,
            "robots": robots_meta,
        }
        meta_path.write_text(to_json_text(meta) + "\n")
    meta = json.loads(meta_path.read_text())
    intrinsics = Intrinsics(**meta["intrinsics"])
    out = {}
    for r in meta["robots"]:
        sub = folder / r["name"]
        out[r["name"]] = RenderedRobot(
            r["name"], RobotKind(r["kind"]), intrinsics, np.load(sub / "frames.npy"), np.load(sub / "poses.npy"),
            np.load(sub / "depth.npy", mmap_mode="r"), np.load(sub / "labels.npy", mmap_mode="r"),
            np.load(sub / "objects.npy", mmap_mode="r"), float(r["path_length_m"]),
        )  # fmt: skip
    return out


def extract_keyframes(
    robot: RenderedRobot,
    cfg: ExtractionConfig,
    corruption: CorruptionLevels | None = None,
    seed: int = 0,
    rows: Sequence[int] | np.ndarray | None = None,
) -> list[ObjectObservations]:
    """Objects of the robot's keyframes (Sec. III-A), after optional perception-like corruption.

    Args:
        robot: rendered keyframes.
        cfg: extraction parameters.
        corruption: depth/label corruption levels (None or inactive = perfect depth and labels).
        seed: corruption seed; keyframe k uses the generator ``[seed, k]`` so any subset is reproducible.
        rows: keyframe rows to extract (default all).

    Returns:
        One ``ObjectObservations`` per requested keyframe (world-frame centroids from the GT pose).
    """
    rows = np.arange(len(robot)) if rows is None else np.asarray(rows, dtype=np.int64)
    levels = corruption or CorruptionLevels()
    out = []
    for k in rows.tolist():
        depth = np.asarray(robot.depth_m[k], dtype=np.float32)
        labels = np.asarray(robot.label_ids[k])
        if levels.active:
            rng = np.random.default_rng([seed, k])
            depth, labels = apply_corruption(depth, labels, levels, rng, np.asarray(robot.object_ids[k]))
        out.append(extract_objects(
            depth, labels, robot.intrinsics, robot.T_world_cam[k], labels=cfg.labels,
            max_depth_m=cfg.max_depth_m, min_depth_m=cfg.min_depth_m, depth_step_m=cfg.depth_step_m,
            min_blob_fraction=cfg.min_blob_fraction,
        ))  # fmt: skip
    return out


def build_graph(
    observations: Sequence[ObjectObservations],
    T_world_cam: np.ndarray,
    cfg: GraphConfig,
    keyframe_ids: Sequence[int] | np.ndarray | None = None,
) -> GraphArrays:
    """The incremental semantic graph (``SemanticGraph``) of a run of keyframes, as arrays.

    Args:
        observations: objects of each keyframe (``extract_keyframes``).
        T_world_cam: (K, 4, 4) the keyframes' ground-truth poses.
        cfg: merge radius and connectivity.
        keyframe_ids: ids of the keyframes (default 0..K-1).
    """
    graph = SemanticGraph(cfg.merge_radius_m, cfg.connectivity_m)
    ids = range(len(observations)) if keyframe_ids is None else [int(i) for i in keyframe_ids]
    for kf_id, T, objects in zip(ids, T_world_cam, observations, strict=True):
        graph.add_keyframe(kf_id, T, objects)
    return graph.arrays()
