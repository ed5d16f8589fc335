"""Named multi-robot scenarios, deterministic by seed: a world plus one trajectory per robot (camera).

- ``synthia-like``: robots ``forward`` and ``backward``, one car's ~950 m drive seen by a forward and a
  backward camera (SYNTHIA 04-spring, the paper's viewpoint study).
- ``airsim-like``: ``car1`` and ``car2`` (~420 m each; ~250 m of shared street driven in opposite
  directions) and ``uav`` (~600 m at 44-54 m, 50 deg oblique camera), the paper's AirSim set.
- ``disjoint``: ``car_a`` and ``car_b`` in opposite corners, never within 2x the depth range (a negative
  control).
- ``kitti-paths``: real KITTI GT drives with a city grown around all of them; by default ``kitti00`` and
  ``kitti07`` (00 frames 2600-2900, 07 frames 0-350, aligned into one world): a real two-robot overlap.
  Any drives ``SEQ[:START-END]`` (half-open frame ranges) of KITTI 00-10, whole sequences included;
  several robots cut from one sequence (``kitti08a``, ``kitti08b``, ...) share its frame as they are.

Every scenario's poses share one world frame: the ground-truth inter-robot transform is identity.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.errors import SimulationError
from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.corridor import build_corridor_city
from shgm_slam.sim.kitti_paths import DEFAULT_KITTI_ROBOTS, kitti_trajectories
from shgm_slam.sim.shapes import ObjectKind
from shgm_slam.sim.trajectories import (
    UAV_ALTITUDE_M,
    Trajectory,
    arc_length,
    car_trajectories,
    fillet_path,
    lane_path,
    min_distance_m,
    random_route,
    uav_trajectory,
)
from shgm_slam.sim.world import World

CORNER_RADIUS_M = 8.0
LANE_OFFSET_M = 2.2


@dataclass(frozen=True)
class ScenarioOptions:
    """What a scenario builder needs besides its name (rendering options live in ``simulate``).

    Attributes:
        seed: everything random derives from it.
        fps: frame rate of the trajectories (kitti-paths samples KITTI's 10 Hz poses at this rate).
        world_size_m: side of the square city (None: the scenario's default, at least 1 km).
        max_depth_m: depth range of the cameras (``disjoint`` keeps its robots 2x this apart).
        car_speed_mps, uav_speed_mps: cruise speeds.
        kitti_root: folder with ``poses/NN.txt`` (default ``../shared/data/kitti``).
        kitti_robots: KITTI drives as ``SEQ[:START-END]`` (half-open frame ranges); the first drive's
            sequence is the reference frame.
        compact: a small world and short paths (airsim-like: cars 120 m, UAV 150 m) for tests and quick looks.
        uav_altitude_m: (low, high) metres above the ground between which the UAV's altitude varies (airsim-like).
    """

    seed: int = 0
    fps: float = 10.0
    world_size_m: float | None = None
    max_depth_m: float = 200.0
    car_speed_mps: float = 10.0
    uav_speed_mps: float = 7.0
    kitti_root: Path | None = None
    kitti_robots: tuple[str, ...] = DEFAULT_KITTI_ROBOTS
    compact: bool = False
    uav_altitude_m: tuple[float, float] = UAV_ALTITUDE_M


@dataclass
class ScenarioPlan:
    """A built scenario: the world, one trajectory per robot, targets and notes for ``scenario.json``."""

    name: str
    world: World
    robots: list[Trajectory]
    targets_m: dict[str, float] = field(default_factory=dict)
    notes: dict = field(default_factory=dict)


def _city(opt: ScenarioOptions, default_m: float, compact_m: float) -> World:
    size = opt.world_size_m or (compact_m if opt.compact else default_m)
    params = CityParams(size_x_m=size, size_y_m=size)
    if opt.compact:
        params = CityParams(
            size_x_m=size, size_y_m=size, block_min_m=45.0, block_max_m=80.0, outskirts_m=20.0
        )
    return build_city(params, seed=opt.seed)


def _centreline(world: World, rng: np.random.Generator, length_m: float, **kw) -> np.ndarray:
    """Dense (M, 2) centreline (0.25 m spacing) of a random street route of at least ``length_m``."""
    route = random_route(world.streets, rng, length_m + 2 * CORNER_RADIUS_M, **kw)
    return fillet_path(world.streets.nodes_xy[route], CORNER_RADIUS_M)


def _cut(path: np.ndarray, s0: float, s1: float) -> np.ndarray:
    s = arc_length(path)
    return path[(s >= s0) & (s <= s1)]


def _near_centre(world: World) -> int:
    xy = world.streets.nodes_xy
    return int(np.argmin(np.linalg.norm(xy - xy.mean(0), axis=1)))


def synthia_like(opt: ScenarioOptions) -> ScenarioPlan:
    """One car's ~950 m drive, a forward and a backward camera (SYNTHIA's forward/backward views)."""
    rng = np.random.default_rng(opt.seed + 1)
    length = 320.0 if opt.compact else 950.0
    world = _city(opt, 1200.0, 420.0)
    centre = _centreline(world, rng, length)
    lane = lane_path(_cut(centre, 0.0, length), LANE_OFFSET_M)
    robots = car_trajectories(lane, {"forward": False, "backward": True}, opt.car_speed_mps, opt.fps, rng)
    return ScenarioPlan("synthia-like", world, robots, {"forward": length, "backward": length})


def airsim_like(opt: ScenarioOptions) -> ScenarioPlan:
    """Two cars and a UAV (the paper's AirSim set): cars ~420 m sharing ~250 m of street driven in
    opposite directions, the UAV ~600 m: its own approach over the blocks, then along both cars' streets."""
    rng = np.random.default_rng(opt.seed + 2)
    car_len, share, uav_len, own = (120.0, 75.0, 150.0, 30.0) if opt.compact else (420.0, 250.0, 600.0, 100.0)
    world = _city(opt, 1200.0, 420.0)
    total = 2 * car_len - share
    centre = _centreline(world, rng, total, start=_near_centre(world) if not opt.compact else None)
    lane1 = lane_path(_cut(centre, 0.0, car_len), LANE_OFFSET_M)
    lane2 = lane_path(_cut(centre, car_len - share, total)[::-1], LANE_OFFSET_M)
    car1 = car_trajectories(lane1, {"car1": False}, opt.car_speed_mps, opt.fps, rng)[0]
    car2 = car_trajectories(lane2, {"car2": False}, opt.car_speed_mps, opt.fps, rng)[0]
    # the UAV's own approach flies ``own`` metres across the blocks, perpendicular to the street
    s_join = 0.1 * car_len
    along = _cut(centre, s_join, s_join + 1.06 * (uav_len - own))[::20]  # +6 %: smoothing cuts corners
    t = along[1] - along[0]
    side = 1.0 if rng.random() < 0.5 else -1.0
    start = along[0] + side * own * np.array([-t[1], t[0]]) / np.linalg.norm(t)
    uav = uav_trajectory("uav", np.vstack([start, along]), opt.uav_speed_mps, opt.fps, rng,
                         altitude_m=opt.uav_altitude_m)
    _check_clearance(world, uav)
    targets = {"car1": car_len, "car2": car_len, "uav": uav_len}
    notes = {"uav_altitude_m": list(opt.uav_altitude_m)}
    return ScenarioPlan("airsim-like", world, [car1, car2, uav], targets, notes)


def under_rooftops(world: World, positions_xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: each (N, 3) world position (metres, z up) lies inside a building's box (footprint and height)."""
    boxes = [o for o in world.objects if o.kind is ObjectKind.BUILDING]
    if not boxes:
        return np.zeros(len(positions_xyz), dtype=bool)
    centre = np.array([o.centre_xyz for o in boxes])
    half = np.array([o.size_xyz for o in boxes]) / 2.0
    cos, sin = np.cos([o.yaw_rad for o in boxes]), np.sin([o.yaw_rad for o in boxes])
    reach = float(np.linalg.norm(half[:, :2], axis=1).max())
    inside = np.zeros(len(positions_xyz), dtype=bool)
    for i, rows in enumerate(cKDTree(centre[:, :2]).query_ball_point(positions_xyz[:, :2], reach)):
        if not rows:
            continue
        d = positions_xyz[i] - centre[rows]
        x, y = cos[rows] * d[:, 0] + sin[rows] * d[:, 1], -sin[rows] * d[:, 0] + cos[rows] * d[:, 1]
        inside[i] = bool(np.any((np.abs(x) <= half[rows, 0]) & (np.abs(y) <= half[rows, 1])
                                & (np.abs(d[:, 2]) <= half[rows, 2])))  # fmt: skip
    return inside


def _check_clearance(world: World, uav: Trajectory) -> None:
    """SimulationError when the UAV's path runs through buildings (its altitude below their roofs)."""
    inside = under_rooftops(world, uav.positions_xyz)
    if inside.any():
        tops = max(o.centre_xyz[2] + o.size_xyz[2] / 2.0 for o in world.objects if o.kind is ObjectKind.BUILDING)
        z = uav.positions_xyz[:, 2]
        raise SimulationError(
            f"the UAV at {z.min():.0f}-{z.max():.0f} m flies through buildings in {int(inside.sum())} of its "
            f"{len(inside)} frames (this city's roofs reach {tops:.0f} m): fly it higher (--uav-altitude)"
        )


def disjoint(opt: ScenarioOptions) -> ScenarioPlan:
    """Two cars in opposite corners of the city that never see the same place (checked geometrically:
    their tracks stay more than 2x the depth range apart)."""
    rng = np.random.default_rng(opt.seed + 3)
    length = 120.0 if opt.compact else 300.0
    world = _city(opt, 1200.0, 1000.0)
    xy = world.streets.nodes_xy
    lo, hi = xy.min(0), xy.max(0)
    u = (xy - lo) / np.maximum(hi - lo, 1e-9)
    corner_a, corner_b = np.all(u < 0.34, axis=1), np.all(u > 0.66, axis=1)
    need = 2.0 * opt.max_depth_m
    for _ in range(20):
        robots = []
        for name, allowed in (("car_a", corner_a), ("car_b", corner_b)):
            centre = _centreline(world, rng, length, allowed=allowed)
            lane = lane_path(_cut(centre, 0.0, length), LANE_OFFSET_M)
            robots += car_trajectories(lane, {name: False}, opt.car_speed_mps, opt.fps, rng)
        gap = min_distance_m(robots[0], robots[1])
        if gap > need:
            return ScenarioPlan(
                "disjoint",
                world,
                robots,
                {"car_a": length, "car_b": length},
                {"min_distance_m": round(gap, 1), "required_m": need},
            )
    raise SimulationError(
        f"disjoint: robots came within {gap:.0f} m (need > {need:.0f} m = 2x depth range); "
        "use a larger --world-size or a smaller depth range"
    )


def kitti_paths(opt: ScenarioOptions) -> ScenarioPlan:
    """Real KITTI ground-truth drives in one world (``sim.kitti_paths``), with a city grown around all of them."""
    robots, notes = kitti_trajectories(opt.kitti_root, opt.kitti_robots, opt.fps)
    world = build_corridor_city([r.positions_xyz[:, :2] for r in robots], seed=opt.seed)
    targets = {r.name: round(r.path_length_m, 1) for r in robots}
    return ScenarioPlan("kitti-paths", world, robots, targets, {"kitti_alignment": notes})


SCENARIOS: dict[str, Callable[[ScenarioOptions], ScenarioPlan]] = {
    "synthia-like": synthia_like,
    "airsim-like": airsim_like,
    "disjoint": disjoint,
    "kitti-paths": kitti_paths,
}
"""Registry: scenario name -> builder."""


def build_scenario(name: str, options: ScenarioOptions | None = None) -> ScenarioPlan:
    """Build scenario ``name`` (see ``SCENARIOS``); unknown names raise ``SimulationError`` listing them."""
    if name not in SCENARIOS:
        raise SimulationError(f"unknown scenario {name!r}; known scenarios: {', '.join(SCENARIOS)}")
    opt = options or ScenarioOptions()
    if opt.fps <= 0 or not np.isfinite(opt.fps):
        raise SimulationError(f"fps must be positive, got {opt.fps}")
    if opt.world_size_m is not None and opt.world_size_m < 150:
        raise SimulationError(f"world size {opt.world_size_m} m is too small; use at least 150 m")
    return SCENARIOS[name](opt)
