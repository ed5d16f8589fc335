"""A city grown around given drive paths (e.g. real KITTI trajectories): roads follow the paths and
buildings, trees, lamps, signs, fences and parked cars line them, never on any path.

Every road runs on ``EXTEND_M`` beyond both ends of its drive, straight along the drive's last heading,
so a camera at the start or end of a drive looks down a street, as it would on a real road, not onto
empty terrain where the generated city stops (which left pseudo-LiDAR clouds with nothing but ground
ahead and broke the odometry in the last seconds of every drive).

Ground: a terrain plane, sidewalk ribbons (|offset| <= road half width + sidewalk) and road ribbons
2 cm above them along every road centreline (the drive path shifted left by the lane offset), so
wherever roads overlap the road wins. Objects are proposed along both sides of every road and kept
only when their footprint clears *every* road and every object placed before.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.labels import Label
from shgm_slam.sim.shapes import Material, MeshPiece, ObjectKind
from shgm_slam.sim.trajectories import lane_path, resample_path, tangents
from shgm_slam.sim.world import ObjectList, World, assemble_world

K = ObjectKind
ROAD_HALF_M = 6.5
SIDEWALK_M = 4.0
LANE_OFFSET_M = 2.0
EXTEND_M = 120.0
"""Roads (and what lines them) continue this far beyond each drive's ends: beyond the farthest a camera
uses (KISS-ICP's 100 m range) so no view ends in empty terrain."""
HEADING_M = 10.0
"""The heading a road continues with: the mean direction of the drive's first / last this many metres."""


def extend_path(path_xy: np.ndarray, extend_m: float = EXTEND_M, heading_m: float = HEADING_M) -> np.ndarray:
    """A dense (M, 2) path (1 m spacing) continued straight for ``extend_m`` beyond both ends, along the
    mean heading of its first / last ``heading_m``; a path shorter than 1 m is returned as it is."""
    if len(path_xy) < 2 or np.linalg.norm(path_xy[-1] - path_xy[0]) < 1.0:
        return path_xy
    k = int(min(heading_m, len(path_xy) - 1))
    steps = np.arange(1.0, extend_m + 0.5)[:, None]
    head = path_xy[k] - path_xy[0]
    tail = path_xy[-1] - path_xy[-1 - k]
    head = head / max(np.linalg.norm(head), 1e-9)
    tail = tail / max(np.linalg.norm(tail), 1e-9)
    return np.concatenate([path_xy[0] - steps[::-1] * head, path_xy, path_xy[-1] + steps * tail])


def _ribbon(centre_xy: np.ndarray, half_width_m: float, z_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat strip of +-``half_width_m`` around a dense (M, 2) centreline: (2M, 3) vertices, faces up."""
    t = tangents(centre_xy)
    left = np.stack([-t[:, 1], t[:, 0]], 1)
    a, b = centre_xy + half_width_m * left, centre_xy - half_width_m * left
    v = np.column_stack([np.stack([a, b], 1).reshape(-1, 2), np.full(2 * len(centre_xy), z_m)])
    i = 2 * np.arange(len(centre_xy) - 1)
    faces = np.concatenate([np.stack([i, i + 1, i + 2], 1), np.stack([i + 1, i + 3, i + 2], 1)])
    return v, faces  # counter-clockwise seen from above for a path heading along +x: (a, b, a')


class _Corridor:
    def __init__(self, paths_xy: list[np.ndarray], seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        dense = [extend_path(resample_path(p, 1.0)) for p in paths_xy]
        self.centres = [lane_path(p, -LANE_OFFSET_M) for p in dense]
        self.road_tree = cKDTree(np.concatenate(self.centres))
        self.path_tree = cKDTree(np.concatenate(dense))
        self.obj = ObjectList()
        self.placed_xy: list[np.ndarray] = []
        self.placed_r: list[float] = []

    def clear(self, pts_xy: np.ndarray, min_road_m: float, radius_m: float, min_path_m: float = 2.5) -> bool:
        """True when all (P, 2) footprint samples are >= ``min_road_m`` from every road centreline and
        ``min_path_m`` from every drive path, and a circle of ``radius_m`` around their mean does not hit
        an object placed before."""
        if (
            self.road_tree.query(pts_xy)[0].min() < min_road_m
            or self.path_tree.query(pts_xy)[0].min() < min_path_m
        ):
            return False
        c = pts_xy.mean(0)
        if self.placed_xy:
            d = np.linalg.norm(np.array(self.placed_xy) - c, axis=1)
            if np.any(d < np.array(self.placed_r) + radius_m):
                return False
        self.placed_xy.append(c)
        self.placed_r.append(radius_m)
        return True

    def box_samples(self, c, t, n, length, depth) -> np.ndarray:
        a = np.linspace(-0.5, 0.5, max(2, int(length) + 1))  # about 1 m apart
        b = np.linspace(-0.5, 0.5, max(2, int(depth) + 1))
        A, B = np.meshgrid(a, b)
        return c + length * A.reshape(-1, 1) * t + depth * B.reshape(-1, 1) * n

    def build(self) -> World:
        rng = self.rng
        allc = np.concatenate(self.centres)
        lo, hi = allc.min(0) - 400, allc.max(0) + 400
        self.obj.add(K.TERRAIN, ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, -0.07), (*(hi - lo), 0.1))
        pieces: list[MeshPiece] = []
        for centre in self.centres:
            for kind, half, z, label in (
                (K.SIDEWALK, ROAD_HALF_M + SIDEWALK_M, 0.0, Label.SIDEWALK),
                (K.ROAD, ROAD_HALF_M, 0.02, Label.ROAD),
            ):
                v, f = _ribbon(centre, half, z)
                bb0, bb1 = v.min(0), v.max(0)
                oid = self.obj.add(kind, (bb0 + bb1) / 2, np.maximum(bb1 - bb0, 0.02))
                pieces.append(MeshPiece(v, f, label, np.full(len(f), oid)))
            dashes = centre[::9][::2]  # centre-line dashes, 3 m long every 18 m
            tt = tangents(centre)[::9][::2]
            for p, t in zip(dashes, tt, strict=True):
                v, f = _ribbon(np.stack([p - 1.5 * t, p, p + 1.5 * t]), 0.08, 0.03)
                pieces.append(
                    MeshPiece(v, f, Label.ROAD, np.full(len(f), pieces[-1].object_ids[0]), Material.MARKING)
                )
        for centre in self.centres:
            tang = tangents(centre)
            for side in (1.0, -1.0):
                normal = side * np.stack([-tang[:, 1], tang[:, 0]], 1)  # away from the road
                self.line_side(centre, tang, normal, rng)
        return assemble_world(self.obj.objects, pieces, seed=self.seed)

    def line_side(self, centre, tang, normal, rng) -> None:
        """Propose objects along one side of one road (dense (M, 2) centreline, 1 m spacing)."""
        M = len(centre)
        obj = self.obj
        # buildings and gaps (fences / walls) along the frontage
        s = int(rng.integers(0, 10))
        while s < M - 10:
            if rng.random() < 0.2:
                g = rng.uniform(5, 12)
                k = min(int(s + g / 2), M - 1)
                kind = K.FENCE if rng.random() < 0.6 else K.WALL
                c = centre[k] + normal[k] * (ROAD_HALF_M + SIDEWALK_M + 0.8)
                if self.clear(self.box_samples(c, tang[k], normal[k], g, 0.3), ROAD_HALF_M + 2.0, 0.5):
                    obj.add_on_ground(
                        kind,
                        c[0],
                        c[1],
                        (g, 0.1 if kind is K.FENCE else 0.3, rng.uniform(1.2, 2.2)),
                        np.arctan2(tang[k, 1], tang[k, 0]),
                    )
                s += int(g) + 1
                continue
            f, d = rng.uniform(12, 28), rng.uniform(10, 20)
            k = min(int(s + f / 2), M - 1)
            setback = ROAD_HALF_M + SIDEWALK_M + 1.0 + rng.uniform(0, 4)
            c = centre[k] + normal[k] * (setback + d / 2)
            if self.clear(self.box_samples(c, tang[k], normal[k], f, d), ROAD_HALF_M + 2.0, 0.3 * min(f, d)):
                obj.add_on_ground(
                    K.BUILDING,
                    c[0],
                    c[1],
                    (f, d, float(np.clip(rng.lognormal(2.5, 0.35), 5, 30))),
                    np.arctan2(tang[k, 1], tang[k, 0]),
                )
            s += int(f) + int(rng.integers(0, 3))
        # street furniture on the sidewalk, parked cars on the road edge
        for s in np.arange(rng.uniform(0, 8), M - 1, 9.0):
            k = int(s)
            if rng.random() < 0.75:
                c = centre[k] + normal[k] * (ROAD_HALF_M + 1.5)
                if self.clear(c[None], ROAD_HALF_M + 0.5, 1.5):
                    h, dia = rng.uniform(6, 11), rng.uniform(3.5, 6)
                    obj.add_on_ground(K.TREE, c[0], c[1], (dia, dia, h), rng.uniform(0, 2 * np.pi))
        for s in np.arange(rng.uniform(0, 30), M - 1, 30.0):
            k = int(s)
            pole = centre[k] + normal[k] * (ROAD_HALF_M + 0.5)
            if self.clear(pole[None], ROAD_HALF_M - 0.5, 0.4):
                c = pole - 0.9 * normal[k]
                obj.add(
                    K.STREET_LAMP,
                    (c[0], c[1], 4.0),
                    (1.8, 0.3, 8.0),
                    np.arctan2(-normal[k, 1], -normal[k, 0]),
                )
        for s in np.arange(rng.uniform(0, 60), M - 1, 60.0):
            k = int(s)
            q = centre[k] + normal[k] * (ROAD_HALF_M + 0.8)
            if self.clear(q[None], ROAD_HALF_M - 0.5, 0.5):
                h = rng.uniform(2.4, 3.0)
                obj.add_on_ground(K.POLE, q[0], q[1], (0.08, 0.08, h))
                yaw = np.arctan2(-tang[k, 1], -tang[k, 0])
                obj.add(K.TRAFFIC_SIGN, (q[0], q[1], h - 0.35), (0.05, 0.7, 0.7), yaw)
        s = rng.uniform(0, 10)
        while s < M - 6:
            k = int(s)
            if rng.random() < 0.5:
                length = rng.uniform(3.9, 4.8)
                c = centre[k] + normal[k] * (ROAD_HALF_M - 1.2)
                pts = self.box_samples(c, tang[k], normal[k], length, 1.8)
                if self.clear(pts, 0.0, 2.2, min_path_m=2.3):
                    obj.add_on_ground(
                        K.CAR,
                        c[0],
                        c[1],
                        (length, 1.8, rng.uniform(1.4, 1.6)),
                        np.arctan2(tang[k, 1], tang[k, 0]),
                    )
            s += rng.uniform(5.5, 9)


def build_corridor_city(paths_xy: list[np.ndarray], seed: int = 0) -> World:
    """A world around drive paths ((M, 2) camera tracks in the world, driving on the right lane)."""
    return _Corridor([np.asarray(p, float) for p in paths_xy], seed).build()
