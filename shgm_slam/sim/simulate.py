"""``simulate``: build a scenario, render every robot's frames and stream them to disk.

Output folder::

    <out>/world.json       every object's ground truth (shgm-world/1) + robot frames (all identity)
    <out>/scenario.json    name, seed, resolution, fps, intrinsics, corruption, robots, measured overlaps
    <out>/<robot>/         one sequence per robot: image_2/ depth/ semantic/ calib.txt times.txt poses.txt

Frames stream to disk one by one (a writer thread encodes PNGs while the next frame renders), so memory
stays bounded whatever the sequence length.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import psutil

from shgm_slam.data.sequence import SequenceWriter
from shgm_slam.errors import ConfigError, SimulationError
from shgm_slam.io.export import ResultsWriter
from shgm_slam.sim.corruption import CorruptionLevels, apply_corruption
from shgm_slam.sim.render import Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, ScenarioPlan, build_scenario
from shgm_slam.sim.trajectories import (
    CAR_CAMERA_HEIGHT_M,
    UAV_ALTITUDE_M,
    Trajectory,
    min_distance_m,
    shared_view_length_m,
)
from shgm_slam.types import Frame, Intrinsics

log = logging.getLogger(__name__)

SCENARIO_FORMAT = "shgm-scenario/1"
OVERLAP_RADIUS_M = 20.0
DEFAULT_MAX_DEPTH_M = 200.0
"""Depth range of the rendered cameras unless asked otherwise (metres; farther is written as 0)."""
MIN_MAX_DEPTH_M = 10.0
"""Shortest depth range rendered: a car's camera 1.65 m up sees the road from about 6 m on (82 deg, 640x192),
so a shorter range writes (almost) no valid depth."""
MIN_UAV_ALTITUDE_M = 5.0
"""Lowest UAV altitude asked for; whether the path clears the roofs it crosses is checked on the built scenario
(``scenarios.under_rooftops``)."""
UAV_VIEW_REACH = 1.4
"""The UAV camera's optical axis (50 deg below the horizon) meets the ground 1.31x its altitude away: its
highest altitude times this must stay within the depth range."""
ProgressFn = Callable[[str, int, int], None]
"""``progress(robot, frames_done, robot_frames)`` after every written frame."""


@dataclass
class RobotResult:
    """One written robot sequence."""

    name: str
    kind: str
    frames: int
    path_length_m: float
    target_length_m: float | None
    folder: Path


@dataclass
class ScenarioResult:
    """What ``simulate`` wrote and measured."""

    scenario: str
    out_dir: Path
    seed: int
    intrinsics: Intrinsics
    fps: float
    robots: list[RobotResult]
    shared_view_m: dict[str, dict[str, float]]
    min_distance_m: dict[str, dict[str, float]]
    world_objects: int
    world_triangles: int
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def sequences(self) -> dict[str, Path]:
        """Robot name -> its sequence folder."""
        return {r.name: r.folder for r in self.robots}

    @property
    def total_frames(self) -> int:
        return sum(r.frames for r in self.robots)

    @property
    def frames_per_s(self) -> float:
        """Rendered-and-written frames per second of wall time (world building excluded)."""
        return self.total_frames / max(self.timings_s.get("render_write", 0.0), 1e-9)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"640x192"`` (``--resolution``) -> (640, 192); raises ``SimulationError`` on anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SimulationError(
            f"--resolution {text!r}: write the image size as WIDTHxHEIGHT pixels, e.g. 640x192"
        ) from None
    if w < 8 or h < 8 or w > 8192 or h > 8192:
        raise SimulationError(f"--resolution {w}x{h} is out of range: give WIDTHxHEIGHT with 8..8192 pixels per "
                              "side, e.g. 640x192")  # fmt: skip
    return w, h


def parse_altitude(text: str) -> tuple[float, float]:
    """``"80-90"`` (or one altitude, ``"80"``) -> (80.0, 90.0) metres; raises ``ConfigError`` on anything else."""
    try:
        values = tuple(float(v) for v in text.split("-"))
    except ValueError:
        values = ()
    if len(values) not in (1, 2) or not all(np.isfinite(values)):
        raise ConfigError(f"bad UAV altitude {text!r}; write LOW-HIGH metres (e.g. 80-90) or one altitude (e.g. 80)")
    return (values[0], values[-1])


def overlap_stats(robots: list[Trajectory]) -> tuple[dict, dict]:
    """Pairwise shared-view lengths (``shared_view_length_m``, metres of the row robot) and minimum
    camera distances (metres) between every ordered pair of robots."""
    shared = {
        a.name: {b.name: round(shared_view_length_m(a, b, OVERLAP_RADIUS_M), 1) for b in robots if b is not a}
        for a in robots
    }
    dist = {a.name: {b.name: round(min_distance_m(a, b), 2) for b in robots if b is not a} for a in robots}
    return shared, dist


def _write_robot(
    renderer: Renderer,
    traj: Trajectory,
    folder: Path,
    corruption: CorruptionLevels,
    rng: np.random.Generator,
    progress: ProgressFn | None,
    overwrite: bool,
) -> None:
    K = renderer.intrinsics
    with SequenceWriter(folder, K, overwrite=overwrite) as writer, ThreadPoolExecutor(1) as io:
        pending: deque = deque()
        for k in range(len(traj)):
            T = traj.T_world_cam[k]
            view = renderer.render(T)
            depth, labels = apply_corruption(view.depth_m, view.label_ids, corruption, rng, view.object_ids)
            frame = Frame(k, float(traj.timestamps_s[k]), K, view.image_rgb, depth, labels, T.copy(), k)
            pending.append(io.submit(writer.write, frame))
            while len(pending) > 3:  # bounded queue: memory does not grow with sequence length
                pending.popleft().result()
            if progress is not None:
                progress(traj.name, k + 1, len(traj))
        for job in pending:
            job.result()


WORLD_BYTES_PER_M2 = 200.0
"""Memory a generated city takes per square metre of its side squared (objects, meshes and the ray tracer's
scene; measured: ~1 GB for a 2 km side, ~5 GB for 5 km)."""

WORLD_BASE_BYTES = 0.25e9
"""Memory of a simulation besides the city (Python, numpy, the renderer), bytes."""


def world_memory_bytes(world_size_m: float) -> float:
    """About how much memory simulating a city of ``world_size_m`` side takes, bytes."""
    return WORLD_BASE_BYTES + WORLD_BYTES_PER_M2 * world_size_m**2


def available_memory_bytes() -> float | None:
    """Memory available to a new process now (psutil), or None where it cannot be read."""
    try:
        return float(psutil.virtual_memory().available)
    except (OSError, RuntimeError, AttributeError):
        return None


def check_world_memory(world_size_m: float) -> None:
    """Refuse a world larger than this machine's available memory holds (the ray tracer crashes, not errs,
    when it runs out).

    Raises:
        ConfigError: the estimate (``world_memory_bytes``) is above the memory available.
    """
    need, have = world_memory_bytes(world_size_m), available_memory_bytes()
    if have is not None and need > have:
        fits = ((have - WORLD_BASE_BYTES) / WORLD_BYTES_PER_M2) ** 0.5 if have > WORLD_BASE_BYTES else 0.0
        raise ConfigError(
            f"--world-size {world_size_m:g} m: a city that large takes about {need / 1e9:.0f} GB of memory and "
            f"{have / 1e9:.1f} GB is available; choose at most about {fits:.0f} m"
        )


def _remove_stale_robots(out: Path, keep: set[str]) -> None:
    """Remove the sequence folders an earlier scenario in ``out`` (its ``scenario.json``) rendered for robots
    this one does not have: left beside the new robots, they would still read as valid sequences.

    Raises:
        SimulationError: the old ``scenario.json`` is unreadable or a folder cannot be removed.
    """
    path = out / "scenario.json"
    if not path.is_file():
        return
    try:
        old = json.loads(path.read_text())
        folders = {str(r["folder"]) for r in old["robots"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SimulationError(f"cannot read {path} to replace its scenario ({exc}); remove {out} first") from None
    for name in sorted(folders - keep):
        folder = out / name
        if Path(name).name != name or not folder.is_dir():  # only a folder of its own, directly in ``out``
            continue
        try:
            shutil.rmtree(folder)
        except OSError as exc:
            raise SimulationError(f"cannot remove {folder} of the scenario replaced: {exc.strerror}") from None
        log.info("removed %s: the scenario replaced had that robot, this one does not", folder)


def simulate(
    scenario: str,
    out_dir: Path | str,
    *,
    seed: int = 0,
    resolution: tuple[int, int] = (640, 192),
    fps: float = 10.0,
    max_frames: int | None = None,
    corruption: CorruptionLevels | None = None,
    world_size_m: float | None = None,
    hfov_deg: float = 82.0,
    max_depth_m: float = DEFAULT_MAX_DEPTH_M,
    compact: bool = False,
    uav_speed_mps: float = 7.0,
    uav_altitude_m: tuple[float, float] | None = None,
    kitti_root: Path | None = None,
    kitti_robots: tuple[str, ...] | None = None,
    overwrite: bool = False,
    threads: int = 2,
    supersample: int = 1,
    progress: ProgressFn | None = None,
) -> ScenarioResult:
    """Build scenario ``scenario`` (see ``sim.scenarios.SCENARIOS``) and write it to ``out_dir``.

    Args:
        resolution: (width, height) pixels; intrinsics from ``hfov_deg`` (KITTI-like 82 deg).
        fps: trajectory frame rate; ``max_frames`` cuts every robot's sequence (quick runs).
        corruption: depth/label corruption levels (default none: perfect ground truth).
        max_depth_m: depth beyond is written as 0 (invalid).
        compact: small world and short paths (tests, previews).
        uav_altitude_m: airsim-like only: (low, high) metres above the ground between which the UAV's altitude
            varies (default ``trajectories.UAV_ALTITUDE_M``, 44-54 m).
        kitti_root, kitti_robots: kitti-paths only: the folder with ``poses/NN.txt`` and the drives as
            ``SEQ[:START-END]``, half-open frame ranges (default ``sim.kitti_paths.DEFAULT_KITTI_ROBOTS``;
            the first drive's sequence is the reference; drives of one sequence share its frame).
        overwrite: replace an existing output folder's sequences.
        threads: ray-casting threads.
        supersample: each pixel's colour from supersample x supersample rays (``render.Renderer``).
        progress: called after every frame.
    """
    out = Path(out_dir)
    if max_frames is not None and max_frames < 1:
        raise SimulationError(f"max_frames must be at least 1, got {max_frames}")
    if out.exists() and not out.is_dir():
        raise SimulationError(f"cannot write the scenario to {out}: it is a file; choose a folder")
    if (out / "scenario.json").exists() and not overwrite:
        raise SimulationError(
            f"{out} already holds a simulated scenario; choose a new folder or pass --overwrite"
        )
    if world_size_m is not None:
        check_world_memory(world_size_m)
    if kitti_robots and scenario != "kitti-paths":
        raise ConfigError(f"KITTI drives (--kitti-drive) only apply to the kitti-paths scenario, not {scenario!r}")
    if not max_depth_m >= MIN_MAX_DEPTH_M:  # NaN too
        raise ConfigError(
            f"max depth {max_depth_m:g} m: a car's camera {CAR_CAMERA_HEIGHT_M:g} m up sees the road from about "
            f"6 m on, so nearly every pixel would be invalid; render at least {MIN_MAX_DEPTH_M:g} m (--max-depth)"
        )
    if uav_altitude_m is not None:
        check_uav_altitude(scenario, uav_altitude_m, max_depth_m)
    elif scenario == "airsim-like" and UAV_ALTITUDE_M[1] * UAV_VIEW_REACH > max_depth_m:  # the default UAV's ground
        low, high = UAV_ALTITUDE_M
        raise ConfigError(
            f"max depth {max_depth_m:g} m: the airsim-like UAV flies at {low:g}-{high:g} m by default and sees the "
            f"ground up to {high * UAV_VIEW_REACH:.0f} m away; raise --max-depth to that, or lower --uav-altitude"
        )
    corruption = corruption or CorruptionLevels()
    intrinsics = make_intrinsics(*resolution, hfov_deg=hfov_deg)
    t0 = time.perf_counter()
    opts = ScenarioOptions(
        seed=seed,
        fps=fps,
        world_size_m=world_size_m,
        max_depth_m=max_depth_m,
        kitti_root=kitti_root,
        **({"kitti_robots": tuple(kitti_robots)} if kitti_robots else {}),
        compact=compact,
        uav_speed_mps=uav_speed_mps,
        **({"uav_altitude_m": tuple(uav_altitude_m)} if uav_altitude_m is not None else {}),
    )
    plan: ScenarioPlan = build_scenario(scenario, opts)
    robots = [r.truncated(max_frames) for r in plan.robots]
    started = [r.name for r in robots if (out / r.name).is_dir() and any((out / r.name).iterdir())]
    if started and not overwrite:  # no scenario.json: a render that was stopped
        raise SimulationError(
            f"{out} holds an unfinished render ({', '.join(started)} but no scenario.json); pass --overwrite to "
            "render it again, or choose a new folder"
        )
    if overwrite:
        _remove_stale_robots(out, {r.name for r in robots})
    t1 = time.perf_counter()
    try:
        results = ResultsWriter(out)
    except OSError as exc:
        raise SimulationError(f"cannot create {out}: {exc.strerror}; choose a writable folder") from None
    frames_gt = {r.name: {"T_world_robot": np.eye(4).tolist()} for r in robots}
    results.write_json(
        "world.json",
        plan.world.to_json(
            {
                "robots": frames_gt,
                "ground_truth_T_a_b": "identity for every robot pair: all poses.txt are in this world frame",
            }
        ),
    )
    renderer = Renderer(plan.world, intrinsics, max_depth_m=max_depth_m, threads=threads, supersample=supersample)
    with renderer:
        t2 = time.perf_counter()
        for i, traj in enumerate(robots):
            rng = np.random.default_rng([seed, i, 77])
            _write_robot(renderer, traj, out / traj.name, corruption, rng, progress, overwrite)
    t3 = time.perf_counter()
    shared, dist = overlap_stats(robots)
    result = ScenarioResult(
        scenario,
        out,
        seed,
        intrinsics,
        fps,
        [
            RobotResult(
                r.name,
                r.kind.value,
                len(r),
                round(r.path_length_m, 1),
                plan.targets_m.get(r.name),
                out / r.name,
            )
            for r in robots
        ],
        shared,
        dist,
        len(plan.world.objects),
        plan.world.num_triangles,
        {
            "build_world": round(t1 - t0, 3),
            "prepare_renderer": round(t2 - t1, 3),
            "render_write": round(t3 - t2, 3),
        },
    )
    results.write_json("scenario.json", scenario_json(result, plan, corruption, max_depth_m, hfov_deg, supersample))
    return result


def check_uav_altitude(scenario: str, altitude_m: tuple[float, float], max_depth_m: float) -> None:
    """ConfigError unless ``altitude_m`` is a (low, high) UAV altitude range, metres, that ``scenario`` has a UAV
    for and its camera sees the ground within ``max_depth_m`` of (``UAV_VIEW_REACH``)."""
    if scenario != "airsim-like":
        raise ConfigError(
            f"a UAV altitude (--uav-altitude) applies to the airsim-like scenario (its UAV), not {scenario!r}"
        )
    low, high = (float(v) for v in altitude_m)
    if not (MIN_UAV_ALTITUDE_M <= low <= high) or high * UAV_VIEW_REACH > max_depth_m:
        raise ConfigError(
            f"UAV altitude {low:g}-{high:g} m: needs {MIN_UAV_ALTITUDE_M:g} m <= low <= high and the ground in view, "
            f"high <= max depth / {UAV_VIEW_REACH:g} = {max_depth_m / UAV_VIEW_REACH:.0f} m (raise --max-depth)"
        )


def scenario_json(
    result: ScenarioResult,
    plan: ScenarioPlan,
    corruption: CorruptionLevels,
    max_depth_m: float,
    hfov_deg: float,
    supersample: int = 1,
) -> dict:
    """``scenario.json`` content (format ``shgm-scenario/1``)."""
    K = result.intrinsics
    return {
        "format": SCENARIO_FORMAT,
        "name": result.scenario,
        "seed": result.seed,
        "resolution": [K.width, K.height],
        "fps": result.fps,
        "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "hfov_deg": hfov_deg},
        "max_depth_m": max_depth_m,
        "supersample": supersample,
        "corruption": corruption.__dict__,
        "robots": [
            {
                "name": r.name,
                "kind": r.kind,
                "frames": r.frames,
                "path_length_m": r.path_length_m,
                "target_length_m": r.target_length_m,
                "folder": r.name,
            }
            for r in result.robots
        ],
        "ground_truth_T_a_b": "identity (all poses.txt share the world frame of world.json)",
        "overlap": {
            "definition": (
                "shared_view_m[a][b]: metres robot a travels while its view centre (where its optical axis "
                f"meets the ground, or 15 m ahead for level cameras) is within {OVERLAP_RADIUS_M:.0f} m of a "
                "view centre of robot b"
            ),
            "shared_view_m": result.shared_view_m,
            "min_camera_distance_m": result.min_distance_m,
        },
        "world": {"objects": result.world_objects, "triangles": result.world_triangles},
        "notes": plan.notes,
        "timings_s": result.timings_s,
    }
