"""Procedural city on an irregular street grid: blocks of buildings, parks and parking lots.

Streets run along x and y with random block sizes, wider avenues every few lines and some segments
closed into pedestrian plazas. Blocks carry sidewalks, buildings of varied footprint and height
(taller downtown), backyard terrain, walls and fences in the gaps, street trees with grass strips,
lamps, utility poles, parked cars, trucks and buses; signalized intersections get traffic lights,
crosswalks and signs. Like a real city it repeats itself. Deterministic by seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from shgm_slam.errors import SimulationError
from shgm_slam.labels import Label
from shgm_slam.sim.city_streets import SIDEWALK_TOP_M, TERRAIN_TOP_M, StreetDressing
from shgm_slam.sim.shapes import Material, MeshPiece, ObjectKind, box_piece
from shgm_slam.sim.world import ObjectList, StreetNetwork, World, assemble_world

K = ObjectKind


@dataclass(frozen=True)
class CityParams:
    """Layout parameters of the procedural city (metres unless stated)."""

    size_x_m: float = 1200.0
    size_y_m: float = 1200.0
    block_min_m: float = 55.0
    block_max_m: float = 130.0
    street_width_m: float = 12.0
    lane_width_m: float = 10.0  # narrow side streets (no parking)
    avenue_width_m: float = 16.0
    avenue_every: int = 3
    sidewalk_width_m: float = 4.0
    closed_street_fraction: float = 0.07
    park_fraction: float = 0.1
    parking_fraction: float = 0.05
    max_building_height_m: float = 36.0
    downtown_radius_m: float = 380.0
    parked_car_probability: float = 0.55
    leafy_street_fraction: float = 0.65
    outskirts_m: float = 45.0


def _street_lines(length_m: float, p: CityParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n,) and widths (n,) of the parallel streets across ``length_m``."""
    n_guess = int(length_m / p.block_min_m) + 3
    offset = int(rng.integers(p.avenue_every))
    widths = np.where(
        (np.arange(n_guess) % p.avenue_every) == offset,
        p.avenue_width_m,
        np.where(rng.random(n_guess) < 0.3, p.lane_width_m, p.street_width_m),
    )
    blocks = rng.uniform(p.block_min_m, p.block_max_m, n_guess)
    pos = np.concatenate([[0.0], np.cumsum(blocks[:-1] + 0.5 * (widths[:-1] + widths[1:]))])
    keep = pos <= length_m
    if keep.sum() < 2:
        raise SimulationError(
            f"city of {length_m:.0f} m is too small for blocks of {p.block_min_m:.0f} m or more"
        )
    return pos[keep], widths[keep]


def _network(xs, wx, ys, wy, p: CityParams, rng) -> tuple[StreetNetwork, np.ndarray, np.ndarray]:
    """Grid street graph; returns it with the closed (plaza) edges and their widths."""
    nx, ny = len(xs), len(ys)
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    nodes = np.stack([xs[ii.ravel()], ys[jj.ravel()]], 1)
    idx = ii * ny + jj
    e_h = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1)  # along x, width wy[j]
    w_h = np.broadcast_to(wy[None, :], (nx - 1, ny)).ravel()
    e_v = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)  # along y, width wx[i]
    w_v = np.broadcast_to(wx[:, None], (nx, ny - 1)).ravel()
    edges, widths = np.concatenate([e_h, e_v]), np.concatenate([w_h, w_v])
    on_border = np.all((nodes[edges][..., 0] == xs[0]) | (nodes[edges][..., 0] == xs[-1]), axis=1) | np.all(
        (nodes[edges][..., 1] == ys[0]) | (nodes[edges][..., 1] == ys[-1]), axis=1
    )
    closed = (rng.random(len(edges)) < p.closed_street_fraction) & ~on_border & (widths < p.avenue_width_m)
    for e in np.flatnonzero(closed):  # re-open closures that would disconnect the network
        keep = ~closed
        g = coo_matrix((np.ones(keep.sum()), tuple(edges[keep].T)), shape=(len(nodes),) * 2)
        if connected_components(g, directed=False)[0] > 1:
            closed[e] = False
    net = StreetNetwork(nodes, edges[~closed], widths[~closed])
    return net, edges[closed], widths[closed]


class _CityBuilder(StreetDressing):
    """Lays out one city; methods add one kind of feature each (street dressing in ``city_streets``)."""

    def __init__(self, p: CityParams, seed: int) -> None:
        self.p, self.seed = p, seed
        self.rng = np.random.default_rng(seed)
        self.obj = ObjectList()
        self.markings: list[tuple[float, float, float, float, float]] = []  # x, y, length, width, yaw

    # -- helpers ----------------------------------------------------------------------------------
    def slab(self, kind: ObjectKind, x0, x1, y0, y1, top_m: float, bottom_m: float = -0.05) -> int:
        return self.obj.add(
            kind, ((x0 + x1) / 2, (y0 + y1) / 2, (top_m + bottom_m) / 2), (x1 - x0, y1 - y0, top_m - bottom_m)
        )

    def tree(
        self, x: float, y: float, z0: float = SIDEWALK_TOP_M, scale: float = 1.0, max_crown_m=6.0
    ) -> None:
        h = self.rng.uniform(6.0, 11.0) * scale
        d = self.rng.uniform(3.5, max_crown_m) * scale
        self.obj.add_on_ground(
            K.TREE, x, y, (d, d * self.rng.uniform(0.85, 1.0), h), self.rng.uniform(0, 2 * np.pi), z0
        )

    def building_height(self, x: float, y: float) -> float:
        p = self.p
        r = np.hypot(x - 0.5 * p.size_x_m, y - 0.5 * p.size_y_m)
        base = 8.0 + 20.0 * np.exp(-((r / p.downtown_radius_m) ** 2))
        return float(np.clip(base * self.rng.lognormal(0.0, 0.35), 4.0, p.max_building_height_m))

    # -- layout -----------------------------------------------------------------------------------
    def build(self) -> World:
        p, rng = self.p, self.rng
        xs, wx = _street_lines(p.size_x_m, p, rng)
        ys, wy = _street_lines(p.size_y_m, p, rng)
        net, closed_edges, _ = _network(xs, wx, ys, wy, p, rng)
        gx0, gx1, gy0, gy1 = xs[0] - wx[0] / 2, xs[-1] + wx[-1] / 2, ys[0] - wy[0] / 2, ys[-1] + wy[-1] / 2
        margin = 700.0
        self.slab(K.TERRAIN, gx0 - margin, gx1 + margin, gy0 - margin, gy1 + margin, -0.02, -0.12)
        self.road_id = self.slab(K.ROAD, gx0, gx1, gy0, gy1, 0.0, -0.1)
        self.open_edges = {tuple(sorted(e)) for e in net.edges.tolist()}
        self.ny = len(ys)
        for a, b in closed_edges:
            (xa, ya), (xb, yb) = net.nodes_xy[a], net.nodes_xy[b]
            ia, ja, ib, jb = a // len(ys), a % len(ys), b // len(ys), b % len(ys)
            if ya == yb:  # closed street along x
                x0, x1 = xa + wx[ia] / 2, xb - wx[ib] / 2
                self.slab(K.SIDEWALK, x0, x1, ya - wy[ja] / 2, ya + wy[ja] / 2, SIDEWALK_TOP_M)
                self.tree(0.5 * (x0 + x1), ya)
            else:
                y0, y1 = ya + wy[ja] / 2, yb - wy[jb] / 2
                self.slab(K.SIDEWALK, xa - wx[ia] / 2, xa + wx[ia] / 2, y0, y1, SIDEWALK_TOP_M)
                self.tree(xa, 0.5 * (y0 + y1))
        for i in range(len(xs) - 1):
            for j in range(len(ys) - 1):
                self.block(
                    i,
                    j,
                    (xs[i] + wx[i] / 2, xs[i + 1] - wx[i + 1] / 2),
                    (ys[j] + wy[j] / 2, ys[j + 1] - wy[j + 1] / 2),
                    (wx[i], wx[i + 1], wy[j], wy[j + 1]),
                )
        for i in range(len(xs)):
            for j in range(len(ys)):
                self.intersection(i, j, xs, wx, ys, wy)
        for a, b in net.edges:
            self.centre_line(net.nodes_xy[a], net.nodes_xy[b], wx, wy, a, b)
        self.outskirts(gx0, gx1, gy0, gy1)
        m = np.array(self.markings).reshape(-1, 5)
        pieces: list[MeshPiece] = []
        if len(m):
            centres = np.stack([m[:, 0], m[:, 1], np.full(len(m), 0.006)], 1)
            sizes = np.stack([m[:, 2], m[:, 3], np.full(len(m), 0.012)], 1)
            pieces.append(box_piece(centres, sizes, m[:, 4], Label.ROAD, self.road_id, Material.MARKING))
        world = assemble_world(self.obj.objects, pieces, streets=net, seed=self.seed)
        world.meta["city"] = {
            "streets_x": xs.round(3).tolist(),
            "streets_y": ys.round(3).tolist(),
            "widths_x": wx.tolist(),
            "widths_y": wy.tolist(),
        }
        return world

    def block(self, i, j, xr, yr, widths) -> None:
        p, rng = self.p, self.rng
        (x0, x1), (y0, y1) = xr, yr
        self.slab(K.SIDEWALK, x0, x1, y0, y1, SIDEWALK_TOP_M)
        sw = p.sidewalk_width_m
        ix0, ix1, iy0, iy1 = x0 + sw, x1 - sw, y0 + sw, y1 - sw
        u = rng.random()
        if u < p.park_fraction:
            self.park(ix0, ix1, iy0, iy1)
        elif u < p.park_fraction + p.parking_fraction:
            self.parking(ix0, ix1, iy0, iy1)
        else:
            self.slab(K.TERRAIN, ix0, ix1, iy0, iy1, TERRAIN_TOP_M)
            self.building_rows(ix0, ix1, iy0, iy1)
        # sides counter-clockwise: (start, direction t, inward normal n, length, street width, edge open)
        wx0, wx1, wy0, wy1 = widths
        ny = self.ny
        sides = [
            ((x0, y0), (1, 0), (0, 1), x1 - x0, wy0, (i * ny + j, (i + 1) * ny + j)),
            ((x1, y0), (0, 1), (-1, 0), y1 - y0, wx1, ((i + 1) * ny + j, (i + 1) * ny + j + 1)),
            ((x1, y1), (-1, 0), (0, -1), x1 - x0, wy1, (i * ny + j + 1, (i + 1) * ny + j + 1)),
            ((x0, y1), (0, -1), (1, 0), y1 - y0, wx0, (i * ny + j, i * ny + j + 1)),
        ]
        for start, t, n, length, width, edge in sides:
            self.curb_side(
                np.array(start, float),
                np.array(t, float),
                np.array(n, float),
                length,
                width,
                edge in self.open_edges,
            )

    def building_rows(self, ix0, ix1, iy0, iy1) -> None:
        rng = self.rng
        w, h = ix1 - ix0, iy1 - iy0
        d_ns = min(rng.uniform(14, 26), h / 2 - 1.0)
        d_ew = min(rng.uniform(14, 26), w / 2 - 1.0)
        rows = [  # (start, t, n, from s, to s, depth)
            ((ix0, iy0), (1, 0), (0, 1), 0.0, w, d_ns),
            ((ix1, iy1), (-1, 0), (0, -1), 0.0, w, d_ns),
            ((ix1, iy0), (0, 1), (-1, 0), d_ns, h - d_ns, d_ew),
            ((ix0, iy1), (0, -1), (1, 0), d_ns, h - d_ns, d_ew),
        ]
        for start, t, n, a, b, depth in rows:
            if depth < 6 or b - a < 8:
                continue
            start, t, n = np.array(start, float), np.array(t, float), np.array(n, float)
            yaw = float(np.arctan2(t[1], t[0]))
            s = a
            while b - s > 6:
                if rng.random() < 0.22 and b - s > 16:
                    g = rng.uniform(4, 12)
                    kind = K.FENCE if rng.random() < 0.55 else K.WALL
                    thick, hgt = (
                        (0.08, rng.uniform(1.2, 2.0)) if kind is K.FENCE else (0.3, rng.uniform(1.0, 2.4))
                    )
                    c = start + (s + g / 2) * t + 0.3 * n
                    self.obj.add_on_ground(kind, c[0], c[1], (g, thick, hgt), yaw, TERRAIN_TOP_M)
                    s += g
                    continue
                f = rng.uniform(12, 38)
                if b - s - f < 8:
                    f = b - s
                setback = 0.0 if rng.random() < 0.6 else rng.uniform(1, 4)
                d = rng.uniform(0.6, 1.0) * depth - setback
                c = start + (s + f / 2) * t + (setback + d / 2) * n
                self.obj.add_on_ground(K.BUILDING, c[0], c[1], (f - 0.3, d, self.building_height(*c)), yaw)
                s += f + (rng.uniform(0, 2) if rng.random() < 0.5 else 0.0)

    def park(self, ix0, ix1, iy0, iy1) -> None:
        rng = self.rng
        self.slab(K.TERRAIN, ix0, ix1, iy0, iy1, TERRAIN_TOP_M)
        n = int((ix1 - ix0) * (iy1 - iy0) / 140)
        pts = np.stack([rng.uniform(ix0 + 3, ix1 - 3, 4 * n), rng.uniform(iy0 + 3, iy1 - 3, 4 * n)], 1)
        kept: list[np.ndarray] = []
        for q in pts:
            if len(kept) >= n:
                break
            if not kept or np.min(np.linalg.norm(np.array(kept) - q, axis=1)) > 6.0:
                kept.append(q)
                self.tree(q[0], q[1], TERRAIN_TOP_M, rng.uniform(0.8, 1.3))
        for (ax, ay), (bx, by) in [
            ((ix0, iy0), (ix1, iy0)),
            ((ix1, iy0), (ix1, iy1)),
            ((ix1, iy1), (ix0, iy1)),
            ((ix0, iy1), (ix0, iy0)),
        ]:
            length = np.hypot(bx - ax, by - ay)
            yaw = np.arctan2(by - ay, bx - ax)
            seg = (length - 6.0) / 2  # two fence runs with a gate in the middle
            for f in (seg / 2, length - seg / 2):
                cx, cy = ax + (bx - ax) * f / length, ay + (by - ay) * f / length
                self.obj.add_on_ground(K.FENCE, cx, cy, (seg, 0.06, 1.3), yaw, TERRAIN_TOP_M)

    def parking(self, ix0, ix1, iy0, iy1) -> None:
        rng = self.rng
        self.slab(K.ROAD, ix0, ix1, iy0, iy1, SIDEWALK_TOP_M + 0.01)
        for y in np.arange(iy0 + 4.0, iy1 - 3.0, 6.5):
            for x in np.arange(ix0 + 2.0, ix1 - 2.0, 2.7):
                if rng.random() < 0.7:
                    self.car(x, y, np.pi / 2 + (np.pi if rng.random() < 0.5 else 0.0), SIDEWALK_TOP_M + 0.01)
        for (ax, ay), (bx, _) in [((ix0, iy0), (ix1, iy0)), ((ix1, iy1), (ix0, iy1))]:
            self.obj.add_on_ground(
                K.WALL, (ax + bx) / 2, ay, (abs(bx - ax) - 12, 0.3, 1.0), 0.0, SIDEWALK_TOP_M
            )

    def car(self, x, y, yaw, z0=0.0) -> float:
        rng = self.rng
        size = (rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.65))
        self.obj.add_on_ground(K.CAR, x, y, size, yaw, z0)
        return size[0]


def build_city(params: CityParams | None = None, seed: int = 0) -> World:
    """Lay out and mesh a procedural city (see module docstring); deterministic for a given seed."""
    p = params or CityParams()
    if p.size_x_m < 150 or p.size_y_m < 150:
        raise SimulationError(
            f"city size {p.size_x_m:.0f} x {p.size_y_m:.0f} m is too small; use at least 150 m"
        )
    return _CityBuilder(p, seed).build()
