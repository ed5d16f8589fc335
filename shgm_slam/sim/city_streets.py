"""Street dressing of the procedural city: what lines a block side (trees with grass strips, lamps,
utility poles, signs, parked cars, trucks and buses), what marks a signalized intersection (traffic
lights on signal poles, crosswalks, signs), centre-line dashes and the tree belt around the city.

``StreetDressing`` is a mixin of ``city._CityBuilder``: it uses the builder's ``p`` (``CityParams``),
``rng``, ``obj`` (``ObjectList``), ``markings``, ``open_edges``, ``ny``, ``slab``, ``tree`` and ``car``.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.sim.shapes import ObjectKind

K = ObjectKind
SIDEWALK_TOP_M = 0.15
TERRAIN_TOP_M = 0.18


class StreetDressing:
    """Street furniture, parked vehicles and markings (metres, world frame, z up)."""

    def curb_side(self, start, t, n, length, street_w, is_open) -> None:
        """Street furniture on one block side and parked vehicles on the street next to it."""
        rng, obj, p = self.rng, self.obj, self.p
        yaw_t = float(np.arctan2(t[1], t[0]))
        out = -n
        yaw_out = float(np.arctan2(out[1], out[0]))
        m = 7.0
        leafy = rng.random() < p.leafy_street_fraction
        if leafy and length > 2 * m + 8:
            c = start + 0.5 * length * t + 1.3 * n
            obj.add_on_ground(
                K.TERRAIN, c[0], c[1], (length - 2 * m, 1.4, 0.05), yaw_t, SIDEWALK_TOP_M - 0.02
            )
            spacing = rng.uniform(8, 12)
            for s in np.arange(m + 2, length - m - 1, spacing):
                if rng.random() > 0.15:
                    q = start + (s + rng.uniform(-1, 1)) * t + 1.5 * n
                    self.tree(q[0], q[1], SIDEWALK_TOP_M, max_crown_m=5.0)  # crowns stay off the lanes
        for s in np.arange(m + rng.uniform(0, 10), length - m, rng.uniform(26, 34)):
            pole = start + s * t + 0.45 * n
            c = pole + 0.9 * out
            obj.add(K.STREET_LAMP, (c[0], c[1], SIDEWALK_TOP_M + 4.0), (1.8, 0.3, 8.0), yaw_out)
        for _ in range(rng.integers(0, 3)):
            q = start + rng.uniform(m, max(m + 1, length - m)) * t + 0.5 * n
            obj.add_on_ground(K.POLE, q[0], q[1], (0.25, 0.25, rng.uniform(5, 9)), 0.0, SIDEWALK_TOP_M)
        if rng.random() < 0.3 and length > 30:
            q = start + rng.uniform(m + 5, length - m - 5) * t + 0.5 * n
            self.sign(q, yaw_t + np.pi)
        if not is_open or street_w < p.street_width_m - 0.1:
            return
        s = m + 3.0
        while s < length - m - 3.0:
            if rng.random() > p.parked_car_probability:
                s += rng.uniform(3, 7)
                continue
            u = rng.random()
            kind, size = (
                (K.CAR, None) if u < 0.87 else
                (K.TRUCK, (rng.uniform(6.5, 9.0), 2.4, rng.uniform(3.0, 3.6))) if u < 0.96 else
                (K.BUS, (12.0, 2.55, 3.2))
            )  # fmt: skip
            length_v = 4.8 if size is None else size[0]
            if s + length_v > length - m:
                break
            c = start + (s + length_v / 2) * t - (1.3 if size is None else 1.35) * n  # kerbside
            if size is None:
                length_v = self.car(c[0], c[1], yaw_t + np.pi)
            else:
                obj.add_on_ground(kind, c[0], c[1], size, yaw_t + np.pi)
            s += length_v + rng.uniform(0.8, 2.5)

    def sign(self, q, yaw_face: float) -> None:
        rng = self.rng
        h = rng.uniform(2.4, 3.0)
        self.obj.add_on_ground(K.POLE, q[0], q[1], (0.08, 0.08, h), 0.0, SIDEWALK_TOP_M)
        w = rng.choice([0.6, 0.75, 0.9])
        self.obj.add(K.TRAFFIC_SIGN, (q[0], q[1], SIDEWALK_TOP_M + h - w / 2), (0.05, w, w), yaw_face)

    def intersection(self, i, j, xs, wx, ys, wy) -> None:
        """Traffic lights, signs and crosswalks at a crossing of at least three open streets."""
        rng, ny = self.rng, self.ny
        node = i * ny + j
        arms = [
            e
            for e in ((node, node + ny), (node - ny, node), (node, node + 1), (node - 1, node))
            if e in self.open_edges
        ]
        if len(arms) < 3:
            return
        x, y = xs[i], ys[j]
        signalized = max(wx[i], wy[j]) >= self.p.avenue_width_m or rng.random() < 0.5
        for qx, qy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            bi, bj = (i if qx > 0 else i - 1), (j if qy > 0 else j - 1)
            if not (0 <= bi < len(xs) - 1 and 0 <= bj < len(ys) - 1):
                continue  # no block in this quadrant
            corner = np.array([x + qx * wx[i] / 2, y + qy * wy[j] / 2])
            if signalized and qx * qy > 0:
                pole = corner + np.array([qx, qy]) * 0.8
                reach = wx[i] / 2 + 0.8
                d = np.array([-qx, 0.0])
                c = pole + d * reach / 2
                self.obj.add(
                    K.SIGNAL_POLE, (c[0], c[1], SIDEWALK_TOP_M + 2.75), (reach, 0.3, 5.5), np.arctan2(0, -qx)
                )
                h = pole + d * (reach - 0.4)
                self.obj.add(
                    K.TRAFFIC_LIGHT, (h[0], h[1], SIDEWALK_TOP_M + 4.7), (0.35, 0.4, 1.0), np.arctan2(-qy, 0)
                )
                self.obj.add(
                    K.TRAFFIC_LIGHT,
                    (pole[0] + 0.3 * qx, pole[1], SIDEWALK_TOP_M + 3.2),
                    (0.35, 0.4, 1.0),
                    np.arctan2(0, -qx),
                )
            elif rng.random() < 0.6:
                self.sign(corner + np.array([qx * 0.9, qy * 1.6]), np.arctan2(qy, 0))
        if not signalized:
            return
        for a, b in arms:  # crosswalk stripes across each arm, just outside the crossing
            along_x = abs(b - a) == ny
            sgn = 1.0 if (b if a == node else a) > node else -1.0
            if along_x:
                cx, half = x + sgn * (wx[i] / 2 + 2.5), wy[j] / 2
                for yy in np.arange(y - half + 1.0, y + half - 0.5, 1.2):
                    self.markings.append((cx, yy, 3.0, 0.55, 0.0))
            else:
                cy, half = y + sgn * (wy[j] / 2 + 2.5), wx[i] / 2
                for xx in np.arange(x - half + 1.0, x + half - 0.5, 1.2):
                    self.markings.append((xx, cy, 3.0, 0.55, np.pi / 2))

    def centre_line(self, pa, pb, wx, wy, a, b) -> None:
        ny = self.ny
        ia, ja, ib, jb = a // ny, a % ny, b // ny, b % ny
        if pa[1] == pb[1]:
            s0, s1, fixed, yaw = pa[0] + wx[ia] / 2 + 6, pb[0] - wx[ib] / 2 - 6, pa[1], 0.0
        else:
            s0, s1, fixed, yaw = pa[1] + wy[ja] / 2 + 6, pb[1] - wy[jb] / 2 - 6, pa[0], np.pi / 2
        for s in np.arange(s0, s1 - 3, 9.0):
            x, y = (s + 1.5, fixed) if yaw == 0.0 else (fixed, s + 1.5)
            self.markings.append((x, y, 3.0, 0.15, yaw))

    def outskirts(self, gx0, gx1, gy0, gy1) -> None:
        """Sidewalk strips and a band of trees around the grid."""
        rng, sw, d = self.rng, self.p.sidewalk_width_m, self.p.outskirts_m
        self.slab(K.SIDEWALK, gx0 - sw, gx1 + sw, gy0 - sw, gy0, SIDEWALK_TOP_M)
        self.slab(K.SIDEWALK, gx0 - sw, gx1 + sw, gy1, gy1 + sw, SIDEWALK_TOP_M)
        self.slab(K.SIDEWALK, gx0 - sw, gx0, gy0, gy1, SIDEWALK_TOP_M)
        self.slab(K.SIDEWALK, gx1, gx1 + sw, gy0, gy1, SIDEWALK_TOP_M)
        perim = 2 * ((gx1 - gx0) + (gy1 - gy0))
        n = int(perim * d / 90)
        side = rng.integers(0, 4, n)
        along = rng.random(n)
        depth = rng.uniform(sw + 2, sw + d, n)
        for s, a, dd in zip(side, along, depth, strict=True):
            if s == 0:
                q = (gx0 - d + a * (gx1 - gx0 + 2 * d), gy0 - dd)
            elif s == 1:
                q = (gx0 - d + a * (gx1 - gx0 + 2 * d), gy1 + dd)
            elif s == 2:
                q = (gx0 - dd, gy0 + a * (gy1 - gy0))
            else:
                q = (gx1 + dd, gy0 + a * (gy1 - gy0))
            self.tree(q[0], q[1], -0.02, rng.uniform(0.9, 1.4))
