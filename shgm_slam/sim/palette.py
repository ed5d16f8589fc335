"""Surface colours of the synthetic city: realistic albedos per class and material, jittered per object.

Also the world-anchored texture strength per class and the procedural facade windows. Deliberately *not*
the Cityscapes label palette: the RGB images should look like a city (grey asphalt,
beige and brick facades, painted cars), so that image-based perception has something real to chew on.
Colours are sRGB in [0, 1]; the jitter is a hash of the object id, so it is deterministic.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.labels import Label
from shgm_slam.sim.shapes import Material, hash01
from shgm_slam.sim.world import World

CLASS_ALBEDO = {
    Label.ROAD: (0.34, 0.34, 0.35),
    Label.SIDEWALK: (0.64, 0.62, 0.58),
    Label.BUILDING: (0.72, 0.68, 0.60),
    Label.WALL: (0.68, 0.63, 0.55),
    Label.FENCE: (0.42, 0.38, 0.32),
    Label.POLE: (0.46, 0.47, 0.48),
    Label.TRAFFIC_LIGHT: (0.14, 0.14, 0.13),
    Label.TRAFFIC_SIGN: (0.85, 0.85, 0.85),
    Label.VEGETATION: (0.23, 0.38, 0.15),
    Label.TERRAIN: (0.40, 0.50, 0.25),
    Label.CAR: (0.6, 0.6, 0.6),
    Label.TRUCK: (0.85, 0.85, 0.83),
    Label.BUS: (0.80, 0.70, 0.20),
}
"""Base albedo per train id (sRGB, 0..1)."""

FACADES = np.array(
    [(0.80, 0.74, 0.62), (0.62, 0.36, 0.28), (0.86, 0.85, 0.81), (0.56, 0.57, 0.58), (0.72, 0.62, 0.46),
     (0.47, 0.52, 0.57), (0.74, 0.55, 0.42), (0.66, 0.66, 0.62)], np.float32,
)  # fmt: skip
CAR_PAINTS = np.array(
    [(0.88, 0.88, 0.88), (0.10, 0.10, 0.11), (0.66, 0.67, 0.69), (0.40, 0.41, 0.43), (0.62, 0.10, 0.09),
     (0.14, 0.24, 0.52), (0.17, 0.30, 0.22), (0.80, 0.80, 0.78), (0.25, 0.25, 0.27)], np.float32,
)  # fmt: skip
BUS_PAINTS = np.array(
    [(0.82, 0.70, 0.18), (0.20, 0.40, 0.70), (0.75, 0.16, 0.14), (0.90, 0.90, 0.88)], np.float32
)
SIGN_PAINTS = np.array(
    [(0.88, 0.88, 0.88), (0.15, 0.30, 0.70), (0.80, 0.12, 0.10), (0.90, 0.75, 0.10)], np.float32
)
MATERIAL_ALBEDO = {
    Material.GLASS: (0.11, 0.13, 0.16),
    Material.TRUNK: (0.33, 0.24, 0.16),
    Material.MARKING: (0.86, 0.86, 0.82),
    Material.ROOF_UNIT: (0.60, 0.60, 0.60),
    Material.METAL: (0.46, 0.47, 0.48),
    Material.TYRE: (0.07, 0.07, 0.07),
}


def _pick(palette: np.ndarray, u: np.ndarray) -> np.ndarray:
    return palette[(u * len(palette)).astype(np.int64)]


def triangle_albedo(world: World, tri_normal: np.ndarray) -> np.ndarray:
    """(F, 3) float32 albedo of every triangle of ``world`` given its (F, 3) unit normals."""
    lab, mat, obj = world.tri_label, world.tri_material, world.tri_object.astype(np.int64)
    ids = np.arange(max(len(world.objects), int(obj.max(initial=-1)) + 1))
    u = hash01(ids[:, None], np.arange(12)[None])[obj]  # (F, 12) per-object random numbers
    lut = np.full((256, 3), 0.5, np.float32)
    for k, c in CLASS_ALBEDO.items():
        lut[k] = c
    jitter = 0.88 + 0.24 * u[:, [0]] + 0.05 * (u[:, 1:4] - 0.5)
    albedo = (lut[lab] * jitter).astype(np.float32)
    base = mat == Material.BASE
    sel = base & (lab == Label.BUILDING)
    albedo[sel] = _pick(FACADES, u[sel, 4]) * (0.92 + 0.16 * u[sel, 5])[:, None]
    roof = sel & (tri_normal[:, 2] > 0.7)
    albedo[roof] = np.array([0.42, 0.41, 0.40], np.float32) * (0.85 + 0.3 * u[roof, 6])[:, None]
    for label, palette in (
        (Label.CAR, CAR_PAINTS),
        (Label.BUS, BUS_PAINTS),
        (Label.TRAFFIC_SIGN, SIGN_PAINTS),
    ):
        sel = base & (lab == label)
        albedo[sel] = _pick(palette, u[sel, 7])
    sel = base & (lab == Label.TERRAIN)  # some lawns dry and brownish
    dry = 0.4 * u[sel, 8][:, None]
    albedo[sel] = albedo[sel] * (1 - dry) + np.array([0.52, 0.46, 0.30], np.float32) * dry
    for m, c in MATERIAL_ALBEDO.items():
        albedo[mat == m] = c
    light = mat == Material.LIGHT
    red = u[light, 9] < 0.5
    albedo[light] = np.where(red[:, None], [[0.95, 0.25, 0.15]], [[0.25, 0.90, 0.45]]).astype(np.float32)
    albedo[light & (lab == Label.POLE)] = (0.95, 0.93, 0.82)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)


def noise_texture(size: int = 256, seed: int = 5) -> np.ndarray:
    """(size, size) float32 tileable zero-mean noise (three octaves of bilinear value noise), std ~0.3."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size), np.float32)
    for cells, amp in ((size, 0.5), (size // 4, 0.35), (size // 16, 0.3)):
        g = rng.random((cells, cells)).astype(np.float32) - 0.5
        x = np.arange(size) * cells / size
        i0 = np.floor(x).astype(int)
        f = (x - i0).astype(np.float32)
        i1 = (i0 + 1) % cells
        rows = g[i0] * (1 - f)[:, None] + g[i1] * f[:, None]
        out += amp * (rows[:, i0] * (1 - f)[None] + rows[:, i1] * f[None])
    return out / out.std() * 0.3


def noise_strength(world: World) -> np.ndarray:
    """(F,) float32 texture-noise amplitude of every triangle (rough ground and foliage, smooth paint)."""
    amp = np.full(256, 0.12, np.float32)
    amp[[Label.ROAD, Label.SIDEWALK]] = 0.22
    amp[[Label.TERRAIN, Label.VEGETATION]] = 0.45
    amp[[Label.CAR, Label.TRUCK, Label.BUS, Label.TRAFFIC_SIGN]] = 0.04
    s = amp[world.tri_label]
    s[world.tri_material == Material.MARKING] = 0.1
    s[world.tri_material == Material.GLASS] = 0.05
    return s


def facade_windows(
    p: np.ndarray, n: np.ndarray, obj: np.ndarray, obj_windows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Window grid on facades: (M,) bool window mask of M facade hit points (world p, normals n, building
    ids) and the (K, 3) glass albedo of the K window pixels (tint varies per window)."""
    a = p[:, 1] * n[:, 0] - p[:, 0] * n[:, 1]  # horizontal coordinate along the facade
    col_w, floor_h, frac_w = obj_windows[obj].T
    fa = a / col_w
    fz = (p[:, 2] - 0.4) / floor_h
    rel_a, rel_z = fa - np.floor(fa), fz - np.floor(fz)
    win = (np.abs(rel_a - 0.5) < frac_w / 2) & (rel_z > 0.28) & (rel_z < 0.85) & (p[:, 2] > 1.2)
    v = hash01(obj[win], np.floor(fa[win]).astype(np.int64), np.floor(fz[win]).astype(np.int64)).astype(
        np.float32
    )
    glass = np.stack([0.16 + 0.18 * v, 0.20 + 0.18 * v, 0.26 + 0.2 * v], 1)
    return win, glass
