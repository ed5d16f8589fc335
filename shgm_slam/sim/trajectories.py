"""Robot trajectories: cars driving the street network and UAVs flying over it.

Routes are node walks on the ``StreetNetwork``; their corners are rounded with circular fillets, cars
keep to the right lane at a lane offset, slow down in curves (lateral acceleration limit) and carry
forward/backward cameras 1.65 m above the road; UAVs fly smoothed paths at 30-60 m with an oblique
camera. Poses are ``T_world_cam`` (KITTI camera axes: x right, y down, z forward) in the world frame
(z up), so every robot of a scenario shares one frame (ground-truth inter-robot transform = identity).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.ndimage import gaussian_filter1d, minimum_filter1d
from scipy.spatial import cKDTree

from shgm_slam.errors import SimulationError
from shgm_slam.sim.world import StreetNetwork

CAR_CAMERA_HEIGHT_M = 1.65
UAV_ALTITUDE_M = (44.0, 54.0)
"""Range a UAV's altitude above the ground varies in, metres (the paper's AirSim set flies at about 50 m)."""


class RobotKind(str, Enum):
    CAR = "car"
    UAV = "uav"


@dataclass
class Trajectory:
    """Camera poses of one robot: (N, 4, 4) ``T_world_cam`` and (N,) timestamps in seconds."""

    name: str
    kind: RobotKind
    T_world_cam: np.ndarray
    timestamps_s: np.ndarray

    def __len__(self) -> int:
        return int(self.T_world_cam.shape[0])

    @property
    def positions_xyz(self) -> np.ndarray:
        """(N, 3) camera centres in the world, metres."""
        return self.T_world_cam[:, :3, 3]

    @property
    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions_xyz, axis=0), axis=1).sum())

    def truncated(self, max_frames: int | None) -> Trajectory:
        if max_frames is None or max_frames >= len(self):
            return self
        return Trajectory(self.name, self.kind, self.T_world_cam[:max_frames], self.timestamps_s[:max_frames])


def camera_poses(
    positions_xyz: np.ndarray, forward_xyz: np.ndarray, pitch_down_rad=0.0, roll_rad=0.0
) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam`` of cameras at (N, 3) positions looking along (N, 3) horizontal-ish
    directions, pitched down by ``pitch_down_rad`` and rolled by ``roll_rad`` (scalars or (N,))."""
    f = np.asarray(forward_xyz, float).copy()
    f[:, 2] = 0.0
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(f, up)
    pitch = np.broadcast_to(np.asarray(pitch_down_rad, float), len(f))[:, None]
    roll = np.broadcast_to(np.asarray(roll_rad, float), len(f))[:, None]
    z_cam = np.cos(pitch) * f - np.sin(pitch) * up
    down = -(np.sin(pitch) * f + np.cos(pitch) * up)
    x_cam = np.cos(roll) * right + np.sin(roll) * down
    y_cam = np.cos(roll) * down - np.sin(roll) * right
    T = np.tile(np.eye(4), (len(f), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x_cam, y_cam, z_cam, positions_xyz
    return T


def random_route(
    streets: StreetNetwork,
    rng: np.random.Generator,
    min_length_m: float,
    *,
    start: int | None = None,
    allowed: np.ndarray | None = None,
    straight_bias: float = 0.55,
    attempts: int = 200,
) -> list[int]:
    """A walk of intersections (no U-turns, no revisits) at least ``min_length_m`` long.

    ``allowed`` is an optional (N,) bool mask of usable nodes. Raises ``SimulationError`` when the
    network has no such walk after ``attempts`` tries.
    """
    xy = streets.nodes_xy
    ok = np.ones(len(xy), bool) if allowed is None else np.asarray(allowed, bool)
    nbrs = [streets.neighbours(i) for i in range(len(xy))]
    for _ in range(attempts):
        node = int(rng.choice(np.flatnonzero(ok))) if start is None else start
        route, length = [node], 0.0
        while length < min_length_m:
            cand = [int(c) for c in nbrs[route[-1]] if ok[c] and c not in route]
            if not cand:
                break
            if len(route) > 1:
                heading = xy[route[-1]] - xy[route[-2]]
                step = xy[cand] - xy[route[-1]]
                straight = [
                    c for c, d in zip(cand, step, strict=True) if heading[0] * d[1] - heading[1] * d[0] == 0
                ]
                if straight and rng.random() < straight_bias:
                    cand = straight
            nxt = cand[int(rng.integers(len(cand)))]
            length += float(np.linalg.norm(xy[nxt] - xy[route[-1]]))
            route.append(nxt)
        if length >= min_length_m:
            return route
    raise SimulationError(f"no street route of {min_length_m:.0f} m found; use a larger world (--world-size)")


def fillet_path(corners_xy: np.ndarray, radius_m: float, step_m: float = 0.25) -> np.ndarray:
    """Densely sampled (M, 2) path through (K, 2) corners with circular arcs of ``radius_m`` at turns."""
    pts = [corners_xy[0]]
    for k in range(1, len(corners_xy) - 1):
        a, b, c = corners_xy[k - 1], corners_xy[k], corners_xy[k + 1]
        u, w = (b - a) / np.linalg.norm(b - a), (c - b) / np.linalg.norm(c - b)
        turn = np.arctan2(u[0] * w[1] - u[1] * w[0], u @ w)
        if abs(turn) < 1e-6:
            pts.append(b)
            continue
        d = min(radius_m * np.tan(abs(turn) / 2), 0.45 * np.linalg.norm(b - a), 0.45 * np.linalg.norm(c - b))
        r = d / np.tan(abs(turn) / 2)
        p0 = b - u * d
        normal = np.array([-u[1], u[0]]) * np.sign(turn)  # towards the arc centre
        centre = p0 + normal * r
        a0 = np.arctan2(p0[1] - centre[1], p0[0] - centre[0])
        ang = a0 + np.sign(turn) * np.linspace(0, abs(turn), max(3, int(abs(turn) * r / step_m)))
        pts.extend(centre + r * np.stack([np.cos(ang), np.sin(ang)], 1))
    pts.append(corners_xy[-1])
    return resample_path(np.array(pts), step_m)


def resample_path(path_xy: np.ndarray, step_m: float) -> np.ndarray:
    """(M, D) points at constant arc-length spacing ``step_m`` along a (K, D) polyline."""
    s = arc_length(path_xy)
    si = np.arange(0.0, s[-1] + 1e-9, step_m)
    return np.stack([np.interp(si, s, path_xy[:, d]) for d in range(path_xy.shape[1])], 1)


def arc_length(path: np.ndarray) -> np.ndarray:
    """(K,) cumulative arc length of a (K, D) polyline, metres."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def tangents(path_xy: np.ndarray) -> np.ndarray:
    """(M, 2) unit tangents of a densely sampled path."""
    t = np.gradient(path_xy, axis=0)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def lane_path(centre_xy: np.ndarray, offset_m: float) -> np.ndarray:
    """Shift a dense (M, 2) centreline ``offset_m`` to the right of its direction of travel."""
    t = tangents(centre_xy)
    return centre_xy + offset_m * np.stack([t[:, 1], -t[:, 0]], 1)


def timed_samples(
    path_xy: np.ndarray,
    speed_mps: float,
    fps: float,
    rng: np.random.Generator,
    *,
    lateral_accel_mps2: float = 2.0,
    speed_jitter: float = 0.08,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a dense (M, 2) path at ``fps`` for a vehicle cruising at ``speed_mps`` that slows in curves.

    Returns (N, 2) positions and (N, 2) unit headings, one per frame.
    """
    step = 0.25
    path_xy = resample_path(path_xy, step)  # uniform spacing (lane offsets stretch the outside of curves)
    t = tangents(path_xy)
    heading = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
    curvature = np.abs(np.gradient(heading, step))
    v_curve = np.sqrt(lateral_accel_mps2 / np.maximum(curvature, 1e-6))
    v_curve = gaussian_filter1d(minimum_filter1d(v_curve, max(3, int(20 / step))), max(1.0, 6 / step))
    s = np.arange(len(path_xy)) * step
    phase = rng.uniform(0, 2 * np.pi)
    v = np.minimum(speed_mps * (1 + speed_jitter * np.sin(2 * np.pi * s / 170 + phase)), v_curve)
    v = np.maximum(v, 0.3 * speed_mps)
    time = np.concatenate([[0.0], np.cumsum(step / v[:-1])])
    tk = np.arange(0.0, time[-1], 1.0 / fps)
    sk = np.interp(tk, time, s)
    pos = np.stack([np.interp(sk, s, path_xy[:, 0]), np.interp(sk, s, path_xy[:, 1])], 1)
    hd = np.interp(sk, s, heading)
    return pos, np.stack([np.cos(hd), np.sin(hd)], 1)


def car_trajectories(
    lane_xy: np.ndarray,
    names: dict[str, bool],
    speed_mps: float,
    fps: float,
    rng: np.random.Generator,
) -> list[Trajectory]:
    """Cameras on one car driving ``lane_xy`` (dense (M, 2) path): ``names`` maps camera name to
    ``True`` for a backward-looking camera. Body pitch/roll wobble is shared by all cameras."""
    pos, fwd = timed_samples(lane_xy, speed_mps, fps, rng)
    n = len(pos)
    wobble = gaussian_filter1d(rng.normal(0, 1, (2, n)), 4.0, axis=1)
    wobble *= np.radians(0.4) / np.maximum(wobble.std(axis=1, keepdims=True), 1e-9)
    p3 = np.column_stack([pos, np.full(n, CAR_CAMERA_HEIGHT_M)])
    out = []
    for name, backward in names.items():
        f3 = np.column_stack([-fwd if backward else fwd, np.zeros(n)])
        pitch = -wobble[0] if backward else wobble[0]
        out.append(
            Trajectory(name, RobotKind.CAR, camera_poses(p3, f3, pitch, wobble[1]), np.arange(n) / fps)
        )
    return out


def uav_trajectory(
    name: str,
    path_xy: np.ndarray,
    speed_mps: float,
    fps: float,
    rng: np.random.Generator,
    *,
    altitude_m: tuple[float, float] = UAV_ALTITUDE_M,
    pitch_down_deg: float = 50.0,
    smooth_m: float = 12.0,
) -> Trajectory:
    """A UAV flying a (K, 2) path (smoothed with a ``smooth_m`` Gaussian) at a slowly varying altitude
    inside ``altitude_m`` with a camera looking ``pitch_down_deg`` below the horizon along its track."""
    dense = resample_path(path_xy, 0.5)
    pad = int(3 * smooth_m / 0.5)
    padded = np.concatenate([np.repeat(dense[:1], pad, 0), dense, np.repeat(dense[-1:], pad, 0)])
    dense = resample_path(gaussian_filter1d(padded, smooth_m / 0.5, axis=0)[pad:-pad], 0.5)
    pos, fwd = timed_samples(dense, speed_mps, fps, rng, lateral_accel_mps2=1.5, speed_jitter=0.05)
    n = len(pos)
    s = arc_length(pos)
    lo, hi = altitude_m
    z = lo + (hi - lo) * (0.5 + 0.5 * np.sin(2 * np.pi * s / 400 + rng.uniform(0, 2 * np.pi)))
    roll = gaussian_filter1d(rng.normal(0, 1, n), 5.0) * np.radians(1.0)
    T = camera_poses(
        np.column_stack([pos, z]), np.column_stack([fwd, np.zeros(n)]), np.radians(pitch_down_deg), roll
    )
    return Trajectory(name, RobotKind.UAV, T, np.arange(n) / fps)


def view_centres(T_world_cam: np.ndarray, ahead_m: float = 15.0, max_ground_m: float = 100.0) -> np.ndarray:
    """(N, 2) ground points a camera looks at: where its optical axis meets z = 0 when that is within
    ``max_ground_m``, otherwise ``ahead_m`` along the axis' horizontal direction (ground robots)."""
    pos = T_world_cam[:, :3, 3]
    axis = T_world_cam[:, :3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(axis[:, 2] < -1e-3, -pos[:, 2] / axis[:, 2], np.inf)
    horiz = axis[:, :2] / np.maximum(np.linalg.norm(axis[:, :2], axis=1, keepdims=True), 1e-9)
    ground = pos[:, :2] + axis[:, :2] * np.where(np.isfinite(t), t, 0.0)[:, None]
    return np.where((t <= max_ground_m)[:, None], ground, pos[:, :2] + ahead_m * horiz)


def shared_view_length_m(a: Trajectory, b: Trajectory, radius_m: float = 20.0) -> float:
    """Overlap of ``a`` with ``b``: the distance ``a`` travels while its view centre lies within
    ``radius_m`` of some view centre of ``b`` (both see the same place; not symmetric)."""
    ca, cb = view_centres(a.T_world_cam), view_centres(b.T_world_cam)
    near = cKDTree(cb).query(ca, distance_upper_bound=radius_m)[0] <= radius_m
    steps = np.linalg.norm(np.diff(a.positions_xyz[:, :2], axis=0), axis=1)
    return float(steps[near[1:] & near[:-1]].sum())


def min_distance_m(a: Trajectory, b: Trajectory) -> float:
    """Smallest horizontal distance between any camera position of ``a`` and any of ``b`` (metres)."""
    return float(cKDTree(b.positions_xyz[:, :2]).query(a.positions_xyz[:, :2])[0].min())
