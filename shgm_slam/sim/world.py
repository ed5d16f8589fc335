"""The synthetic world: ground-truth objects, the street network and one labelled triangle mesh.

World frame: z up, metres. Every object is a box (centre, size along its local axes, yaw about +z)
of one ``ObjectKind``; ground surfaces (road, sidewalk, terrain) are objects too ("stuff"). The mesh
carries per-triangle label, object id and material arrays so the renderer can look up what a ray hit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from shgm_slam.labels import label_name
from shgm_slam.sim.shapes import KIND_LABEL, STUFF_KINDS, Material, MeshPiece, ObjectKind, instance_parts

WORLD_FORMAT = "shgm-world/1"


@dataclass(frozen=True)
class WorldObject:
    """One ground-truth object: a box of ``size_xyz`` (local x, y, z) centred at ``centre_xyz``.

    ``yaw_rad`` rotates the local frame about world +z; ``label`` is its Cityscapes train id.
    """

    id: int
    kind: ObjectKind
    centre_xyz: tuple[float, float, float]
    size_xyz: tuple[float, float, float]
    yaw_rad: float = 0.0

    @property
    def label(self) -> int:
        return KIND_LABEL[self.kind]

    @property
    def is_stuff(self) -> bool:
        return self.kind in STUFF_KINDS

    def to_json(self) -> dict:
        return {
            "id": self.id,
            "label": self.label,
            "label_name": label_name(self.label),
            "kind": self.kind.value,
            "stuff": self.is_stuff,
            "position": [round(float(v), 4) for v in self.centre_xyz],
            "size": [round(float(v), 4) for v in self.size_xyz],
            "yaw": round(float(self.yaw_rad), 6),
        }


@dataclass
class StreetNetwork:
    """Drivable streets as a graph: (N, 2) intersection positions (world x, y, metres), (E, 2) edges
    as node indices and (E,) curb-to-curb widths in metres."""

    nodes_xy: np.ndarray
    edges: np.ndarray
    widths_m: np.ndarray

    def neighbours(self, node: int) -> np.ndarray:
        """Indices of the nodes connected to ``node``."""
        e = self.edges
        return np.concatenate([e[e[:, 0] == node, 1], e[e[:, 1] == node, 0]])

    def width(self, a: int, b: int) -> float:
        """Curb-to-curb width of the street between nodes ``a`` and ``b`` (metres)."""
        hit = ((self.edges[:, 0] == a) & (self.edges[:, 1] == b)) | (
            (self.edges[:, 0] == b) & (self.edges[:, 1] == a)
        )
        return float(self.widths_m[np.flatnonzero(hit)[0]])


@dataclass
class World:
    """Objects + mesh of a synthetic world.

    Attributes:
        objects: ground truth, ``objects[i].id == i``.
        vertices_xyz: (V, 3) float64 mesh vertices, world frame, metres.
        faces: (F, 3) int32 triangles (outward winding).
        tri_label: (F,) uint8 train id of every triangle.
        tri_object: (F,) int32 object id of every triangle.
        tri_material: (F,) uint8 ``Material`` of every triangle.
        streets: the drivable network (None for worlds without one).
        seed: the seed the world was built from (-1 when hand-made).
    """

    objects: list[WorldObject]
    vertices_xyz: np.ndarray
    faces: np.ndarray
    tri_label: np.ndarray
    tri_object: np.ndarray
    tri_material: np.ndarray
    streets: StreetNetwork | None = None
    seed: int = -1
    meta: dict = field(default_factory=dict)

    @property
    def num_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def bounds_xyz(self) -> np.ndarray:
        """(2, 3) min/max corner of the mesh, metres."""
        return np.stack([self.vertices_xyz.min(axis=0), self.vertices_xyz.max(axis=0)])

    def face_normals(self) -> np.ndarray:
        """(F, 3) float64 unit outward triangle normals."""
        v = self.vertices_xyz[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def trimesh(self) -> trimesh.Trimesh:
        """The mesh as a ``trimesh.Trimesh`` (for proximity queries and export; not used to render)."""
        return trimesh.Trimesh(self.vertices_xyz, self.faces, process=False)

    def objects_array(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Object arrays: (n,) labels, (n, 3) centres, (n, 3) sizes, (n,) yaws."""
        o = self.objects
        return (
            np.array([x.label for x in o], dtype=np.int64).reshape(-1),
            np.array([x.centre_xyz for x in o], dtype=np.float64).reshape(-1, 3),
            np.array([x.size_xyz for x in o], dtype=np.float64).reshape(-1, 3),
            np.array([x.yaw_rad for x in o], dtype=np.float64).reshape(-1),
        )

    def to_json(self, extra: dict | None = None) -> dict:
        """``world.json`` content: format, seed, bounds, ``extra`` (e.g. robot frames) and every object."""
        b = self.bounds_xyz
        out = {
            "format": WORLD_FORMAT,
            "frame": "world: x east, y north, z up; metres; yaw about +z, size along the object's local axes",
            "seed": self.seed,
            "bounds": {"min": [round(float(x), 3) for x in b[0]], "max": [round(float(x), 3) for x in b[1]]},
            "num_triangles": self.num_triangles,
            **self.meta,
            **(extra or {}),
            "objects": [o.to_json() for o in self.objects],
        }
        return out


def assemble_world(
    objects: list[WorldObject],
    extra_pieces: list[MeshPiece] | None = None,
    *,
    streets: StreetNetwork | None = None,
    seed: int = -1,
) -> World:
    """Build the mesh of ``objects`` (vectorized per kind) plus ``extra_pieces`` into one ``World``.

    Object ids must equal their index in ``objects``.
    """
    if any(o.id != i for i, o in enumerate(objects)):
        raise ValueError("world objects must be numbered 0..n-1 in order")
    pieces: list[MeshPiece] = []
    kinds = np.array([o.kind.value for o in objects])
    for kind in ObjectKind:
        rows = np.flatnonzero(kinds == kind.value)
        if rows.size == 0:
            continue
        sel = [objects[i] for i in rows]
        pieces += instance_parts(
            kind,
            np.array([o.centre_xyz for o in sel]),
            np.array([o.size_xyz for o in sel]),
            np.array([o.yaw_rad for o in sel]),
            rows,
        )
    pieces += extra_pieces or []
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces])
    vertices = np.concatenate([p.vertices for p in pieces]) if pieces else np.zeros((0, 3))
    faces = (
        np.concatenate([p.faces + o for p, o in zip(pieces, offsets[:-1], strict=True)]).astype(np.int32)
        if pieces
        else np.zeros((0, 3), np.int32)
    )
    tri_label = np.concatenate([np.full(len(p.faces), p.label, np.uint8) for p in pieces]) if pieces else []
    tri_object = np.concatenate([p.object_ids for p in pieces]).astype(np.int32) if pieces else []
    tri_material = (
        np.concatenate([np.full(len(p.faces), int(p.material), np.uint8) for p in pieces]) if pieces else []
    )
    return World(
        objects,
        vertices.astype(np.float64),
        faces,
        np.asarray(tri_label, np.uint8),
        np.asarray(tri_object, np.int32),
        np.asarray(tri_material, np.uint8),
        streets=streets,
        seed=seed,
    )


class ObjectList:
    """Accumulates ``WorldObject``s with consecutive ids while a world is being laid out."""

    def __init__(self) -> None:
        self.objects: list[WorldObject] = []

    def add(self, kind: ObjectKind, centre_xyz, size_xyz, yaw_rad: float = 0.0) -> int:
        """Add one object; ``centre_xyz``/``size_xyz`` are 3-sequences in metres. Returns its id."""
        oid = len(self.objects)
        self.objects.append(
            WorldObject(
                oid,
                kind,
                tuple(float(v) for v in centre_xyz),
                tuple(float(v) for v in size_xyz),
                float(yaw_rad),
            )
        )
        return oid

    def add_on_ground(
        self, kind: ObjectKind, x: float, y: float, size_xyz, yaw_rad: float = 0.0, z0: float = 0.0
    ) -> int:
        """Add an object standing on height ``z0`` at (x, y)."""
        return self.add(kind, (x, y, z0 + 0.5 * float(size_xyz[2])), size_xyz, yaw_rad)


__all__ = ["Material", "ObjectKind", "ObjectList", "StreetNetwork", "World", "WorldObject", "assemble_world"]
