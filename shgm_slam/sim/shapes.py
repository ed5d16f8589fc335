"""Object shapes of the synthetic city: every kind is a few primitive parts inside its bounding box.

An object is a box in the world (centre, size, yaw about +z, see ``world.WorldObject``); its kind
lists parts (a primitive template stretched into a sub-box of the object's box, given in normalized
object coordinates ``[-0.5, 0.5]^3``), so the triangle mesh follows from the object list alone and
many objects of one kind are instanced in one vectorized step.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum
from functools import cache

import numpy as np
import trimesh

from shgm_slam.labels import Label


class ObjectKind(str, Enum):
    """What an object is; decides its shape and its Cityscapes label."""

    ROAD = "road"
    SIDEWALK = "sidewalk"
    TERRAIN = "terrain"
    BUILDING = "building"
    WALL = "wall"
    FENCE = "fence"
    TREE = "tree"
    POLE = "pole"
    STREET_LAMP = "street_lamp"
    SIGNAL_POLE = "signal_pole"
    TRAFFIC_LIGHT = "traffic_light"
    TRAFFIC_SIGN = "traffic_sign"
    CAR = "car"
    TRUCK = "truck"
    BUS = "bus"


KIND_LABEL: dict[ObjectKind, int] = {
    ObjectKind.ROAD: Label.ROAD,
    ObjectKind.SIDEWALK: Label.SIDEWALK,
    ObjectKind.TERRAIN: Label.TERRAIN,
    ObjectKind.BUILDING: Label.BUILDING,
    ObjectKind.WALL: Label.WALL,
    ObjectKind.FENCE: Label.FENCE,
    ObjectKind.TREE: Label.VEGETATION,
    ObjectKind.POLE: Label.POLE,
    ObjectKind.STREET_LAMP: Label.POLE,
    ObjectKind.SIGNAL_POLE: Label.POLE,
    ObjectKind.TRAFFIC_LIGHT: Label.TRAFFIC_LIGHT,
    ObjectKind.TRAFFIC_SIGN: Label.TRAFFIC_SIGN,
    ObjectKind.CAR: Label.CAR,
    ObjectKind.TRUCK: Label.TRUCK,
    ObjectKind.BUS: Label.BUS,
}
"""Cityscapes train id of every object kind."""

STUFF_KINDS = frozenset({ObjectKind.ROAD, ObjectKind.SIDEWALK, ObjectKind.TERRAIN})
"""Ground surfaces ("stuff" in panoptic terms): objects in world.json, but not countable things."""


class Material(IntEnum):
    """Surface material of a triangle; the renderer picks colour and texture from (label, material)."""

    BASE = 0
    GLASS = 1
    TRUNK = 2
    MARKING = 3
    LIGHT = 4
    ROOF_UNIT = 5
    METAL = 6
    TYRE = 7


class Template(str, Enum):
    BOX = "box"
    CYLINDER = "cylinder"
    BLOB = "blob"  # icosphere whose vertices are jittered per object (tree crowns)


@cache
def template_mesh(template: Template) -> tuple[np.ndarray, np.ndarray]:
    """Unit primitive filling ``[-0.5, 0.5]^3``: (V, 3) float64 vertices, (F, 3) int64 outward faces."""
    if template is Template.BOX:
        m = trimesh.creation.box()
    elif template is Template.CYLINDER:
        m = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=8)
    else:
        m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


@dataclass(frozen=True)
class Part:
    """A primitive stretched over ``lo..hi`` (normalized object coordinates); label None = the object's."""

    template: Template
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    material: Material = Material.BASE
    label: int | None = None


_FULL = ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
KIND_PARTS: dict[ObjectKind, tuple[Part, ...]] = {
    ObjectKind.ROAD: (Part(Template.BOX, *_FULL),),
    ObjectKind.SIDEWALK: (Part(Template.BOX, *_FULL),),
    ObjectKind.TERRAIN: (Part(Template.BOX, *_FULL),),
    ObjectKind.BUILDING: (
        Part(Template.BOX, (-0.5, -0.5, -0.5), (0.5, 0.5, 0.45)),
        Part(Template.BOX, (-0.15, -0.2, 0.45), (0.2, 0.15, 0.5), Material.ROOF_UNIT),
    ),
    ObjectKind.WALL: (Part(Template.BOX, *_FULL),),
    ObjectKind.FENCE: (Part(Template.BOX, *_FULL),),
    ObjectKind.TREE: (
        Part(Template.CYLINDER, (-0.05, -0.05, -0.5), (0.05, 0.05, 0.0), Material.TRUNK),
        Part(Template.BLOB, (-0.5, -0.5, -0.12), (0.5, 0.5, 0.5)),  # crown from 0.38 h: cars pass below
    ),
    ObjectKind.POLE: (Part(Template.CYLINDER, *_FULL, Material.METAL),),
    ObjectKind.STREET_LAMP: (  # pole at local -x, arm reaching +x over the road, lamp head at the end
        Part(Template.CYLINDER, (-0.5, -0.35, -0.5), (-0.38, 0.35, 0.5), Material.METAL),
        Part(Template.BOX, (-0.45, -0.12, 0.45), (0.5, 0.12, 0.49), Material.METAL),
        Part(Template.BOX, (0.15, -0.5, 0.41), (0.5, 0.5, 0.46), Material.LIGHT),
    ),
    ObjectKind.SIGNAL_POLE: (
        Part(Template.CYLINDER, (-0.5, -0.5, -0.5), (-0.44, 0.5, 0.5), Material.METAL),
        Part(Template.BOX, (-0.47, -0.3, 0.42), (0.5, 0.3, 0.48), Material.METAL),
    ),
    ObjectKind.TRAFFIC_LIGHT: (
        Part(Template.BOX, *_FULL),
        Part(Template.BOX, (-0.52, -0.3, 0.15), (-0.45, 0.3, 0.4), Material.LIGHT),
    ),
    ObjectKind.TRAFFIC_SIGN: (Part(Template.BOX, *_FULL),),
    ObjectKind.CAR: (
        Part(Template.BOX, (-0.5, -0.5, -0.36), (0.5, 0.5, 0.08)),
        Part(Template.BOX, (-0.32, -0.46, 0.08), (0.22, 0.46, 0.42), Material.GLASS),
        Part(Template.BOX, (-0.3, -0.44, 0.42), (0.18, 0.44, 0.5)),
        Part(Template.BOX, (-0.42, -0.52, -0.5), (0.42, 0.52, -0.36), Material.TYRE),  # wheels band
    ),
    ObjectKind.TRUCK: (
        Part(Template.BOX, (0.24, -0.5, -0.42), (0.49, 0.5, 0.2)),
        Part(Template.BOX, (0.45, -0.46, -0.05), (0.5, 0.46, 0.17), Material.GLASS),
        Part(Template.BOX, (-0.5, -0.5, -0.42), (0.22, 0.5, 0.5)),
        Part(Template.BOX, (-0.45, -0.5, -0.5), (0.45, 0.5, -0.42), Material.TYRE),
    ),
    ObjectKind.BUS: (
        Part(Template.BOX, (-0.5, -0.5, -0.42), (0.5, 0.5, -0.02)),
        Part(Template.BOX, (-0.49, -0.49, -0.02), (0.49, 0.49, 0.34), Material.GLASS),
        Part(Template.BOX, (-0.5, -0.5, 0.34), (0.5, 0.5, 0.5)),
        Part(Template.BOX, (-0.4, -0.48, -0.5), (0.4, 0.48, -0.42), Material.TYRE),
    ),
}
"""Parts of every object kind (each kind's parts fill its bounding box)."""


def hash01(*keys: np.ndarray | int) -> np.ndarray:
    """Deterministic pseudo-random floats in [0, 1) from integer keys (broadcast), splitmix64-style."""
    h = np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        for k in keys:
            h = (h ^ np.asarray(k).astype(np.int64).astype(np.uint64)) * np.uint64(0xBF58476D1CE4E5B9)
            h = h ^ (h >> np.uint64(31))
            h = h * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(29))
    return (np.asarray(h) >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def instance_parts(
    kind: ObjectKind,
    centres_xyz: np.ndarray,
    sizes_xyz: np.ndarray,
    yaws_rad: np.ndarray,
    object_ids: np.ndarray,
) -> list[MeshPiece]:
    """Triangles of ``n`` objects of one kind, one ``MeshPiece`` per part.

    Args:
        centres_xyz: (n, 3) bounding-box centres, world frame, metres.
        sizes_xyz: (n, 3) bounding-box extents along the object's local x, y, z, metres.
        yaws_rad: (n,) rotation of the local frame about world +z.
        object_ids: (n,) ids, stored per triangle (and seeding the crown jitter).
    """
    c, s, yaw = np.asarray(centres_xyz, float), np.asarray(sizes_xyz, float), np.asarray(yaws_rad, float)
    ids = np.asarray(object_ids, dtype=np.int64)
    cy, sy = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    pieces = []
    for pi, part in enumerate(KIND_PARTS[kind]):
        v, f = template_mesh(part.template)
        lo, hi = np.array(part.lo), np.array(part.hi)
        local = lo + (v + 0.5) * (hi - lo)  # (V, 3) normalized object coordinates
        if part.template is Template.BLOB:  # organic crowns: radial jitter per object and vertex
            centre = lo + 0.5 * (hi - lo)
            r = 0.78 + 0.3 * hash01(ids[:, None], np.arange(len(v))[None], pi)
            local = centre + (local - centre)[None] * r[..., None]
        local = np.broadcast_to(local, (len(ids), *v.shape)) * s[:, None, :]  # (n, V, 3) metres
        world = np.empty_like(local)
        world[..., 0] = cy * local[..., 0] - sy * local[..., 1] + c[:, None, 0]
        world[..., 1] = sy * local[..., 0] + cy * local[..., 1] + c[:, None, 1]
        world[..., 2] = local[..., 2] + c[:, None, 2]
        faces = f[None] + (len(v) * np.arange(len(ids)))[:, None, None]
        label = KIND_LABEL[kind] if part.label is None else part.label
        pieces.append(
            MeshPiece(
                world.reshape(-1, 3), faces.reshape(-1, 3), label, np.repeat(ids, len(f)), part.material
            )
        )
    return pieces


@dataclass
class MeshPiece:
    """Triangles with their semantic attributes: (V, 3) vertices, (F, 3) faces, (F,) object ids."""

    vertices: np.ndarray
    faces: np.ndarray
    label: int
    object_ids: np.ndarray
    material: Material = Material.BASE


def box_piece(
    centres_xyz: np.ndarray,
    sizes_xyz: np.ndarray,
    yaws_rad: np.ndarray,
    label: int,
    object_id: int,
    material: Material,
) -> MeshPiece:
    """Plain boxes that belong to one existing object (e.g. road markings on the road object)."""
    n = len(centres_xyz)
    piece = instance_parts(ObjectKind.WALL, centres_xyz, sizes_xyz, yaws_rad, np.full(n, object_id))[0]
    piece.label, piece.material = label, material
    return piece
