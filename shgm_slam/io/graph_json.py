"""Semantic graph files in the ``shgm-graph/1`` JSON format (ARCHITECTURE.md, "Graph file").

```json
{"format": "shgm-graph/1", "classes": ["road", "sidewalk", ...],
 "nodes": [{"id": 0, "label": 2, "position": [x, y, z], "size": 1520.0}], "edges": [[0, 1]]}
```
In the file ``label`` indexes ``classes`` and edges name node *ids*; in ``GraphArrays`` labels are
Cityscapes train ids and edges are *row indices*. A file with its own class list is remapped to train
ids by class name. ``size`` defaults to 1; without ``edges`` the connectivity threshold builds them.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from shgm_slam.errors import GraphError, parse_failure
from shgm_slam.graph.semantic_graph import edges_within_radius
from shgm_slam.io.json_text import to_json_text
from shgm_slam.labels import CITYSCAPES_CLASSES, MAP_CLASS_NAMES
from shgm_slam.types import MAX_COORDINATE_M, GraphArrays, extent_problem

FORMAT_TAG = "shgm-graph/1"
MAX_NODES = 10_000
"""Most nodes a graph file may hold: the whole-overlap verification of a match holds arrays of (shifts x nodes)
booleans (a 20 000-node graph against a 100-node one peaked at 3.1 GB, a 50 000-node one asked 5.3 GB for one
array). KITTI 00's 3.7 km make ~2500 nodes."""
MAX_FILE_BYTES = 400 * MAX_NODES * 100
"""A graph file larger than this cannot be a graph of ``MAX_NODES`` nodes (a node is ~100-200 characters)."""
MAX_SIZE = 1e15
"""Node sizes (weights of Eq. 2) must be below this; their sums would otherwise overflow."""


def _canonical(name: str) -> str:
    return " ".join(str(name).strip().lower().replace("_", " ").replace("-", " ").split())


_TRAIN_ID_OF_NAME = {_canonical(n): i for i, n in enumerate(CITYSCAPES_CLASSES)}
_TRAIN_ID_OF_ANY_NAME = {**{_canonical(n): i for n, i in MAP_CLASS_NAMES.items()}, **_TRAIN_ID_OF_NAME}
"""Cityscapes names and the map names of ``labels.MAP_CLASS_NAMES`` (reading only: files are written with
Cityscapes names)."""


def train_id_of_class(name: str) -> int:
    """The Cityscapes train id a graph file's class name stands for (``_TRAIN_ID_OF_ANY_NAME``; a plural such as
    "traffic lights" or "street lamps" as its singular), or -1 for none."""
    key = _canonical(name)
    found = _TRAIN_ID_OF_ANY_NAME.get(key, -1)
    if found < 0 and key.endswith("s"):
        found = _TRAIN_ID_OF_ANY_NAME.get(key[:-1], -1)
    return found


def graph_to_dict(graph: GraphArrays, classes: Sequence[str] = CITYSCAPES_CLASSES) -> dict[str, Any]:
    """The ``shgm-graph/1`` document of a graph.

    Args:
        graph: nodes with Cityscapes train ids, positions (metres) and edges as row indices.
        classes: class list written to the file; each node's label becomes the index of its class name.

    Raises:
        GraphError: a node's train id has no class name in ``classes``.
    """
    index_of_train_id: dict[int, int] = {}
    for idx, name in enumerate(classes):
        tid = _TRAIN_ID_OF_NAME.get(_canonical(name))
        if tid is not None:
            index_of_train_id.setdefault(tid, idx)
    labels = [int(x) for x in np.asarray(graph.label_ids).tolist()]
    missing = sorted({t for t in labels if t not in index_of_train_id})
    if missing:
        raise GraphError(f"train ids {missing} have no class in the given class list; add their names to it")
    ids = np.asarray(graph.node_ids, dtype=np.int64)
    edges = np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2)
    nodes = [
        {"id": int(i), "label": index_of_train_id[t], "position": [float(v) for v in p], "size": float(s)}
        for i, t, p, s in zip(ids.tolist(), labels, np.asarray(graph.positions_xyz).tolist(),
                              np.asarray(graph.sizes).tolist(), strict=True)
    ]  # fmt: skip
    return {
        "format": FORMAT_TAG,
        "classes": list(classes),
        "nodes": nodes,
        "edges": ids[edges].tolist() if edges.size else [],
    }


def graph_from_dict(
    data: Any, *, connectivity_m: float = 10.0, source: str = "graph document"
) -> GraphArrays:
    """Parse and validate a ``shgm-graph/1`` document.

    Args:
        data: the decoded JSON value.
        connectivity_m: builds the edges (nodes closer than this) when the document has no ``edges``.
        source: name of the file or document used in error messages.

    Returns:
        The graph with Cityscapes train ids and edges as row indices (i < j, unique, sorted).

    Raises:
        GraphError: wrong or missing format tag, missing fields, duplicate node ids, non-finite positions,
            label indices outside ``classes``, unknown class names used by nodes, edges to unknown ids
            or self loops.
    """

    def fail(msg: str) -> GraphError:
        return GraphError(f"{source}: {msg}")

    if not isinstance(data, dict):
        raise fail(f'must hold a JSON object with "format": "{FORMAT_TAG}", got {type(data).__name__}')
    tag = data.get("format")
    if tag != FORMAT_TAG:
        raise fail(f'format tag is {tag!r}, expected "{FORMAT_TAG}" (write it with `shgm-slam graph`)')
    classes = data.get("classes")
    if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
        raise fail('needs "classes": a list of class names that node labels index')
    nodes = data.get("nodes")
    if not isinstance(nodes, list):
        raise fail('needs "nodes": a list of {"id", "label", "position", "size"} objects')

    n = len(nodes)
    if n > MAX_NODES:
        raise fail(f"{n} nodes, more than the {MAX_NODES} a match can hold in memory; split the map into "
                   "areas (KITTI 00's 3.7 km make ~2500)")
    node_ids = np.zeros(n, np.int64)
    label_idx = np.zeros(n, np.int64)
    positions = np.zeros((n, 3))
    sizes = np.ones(n)
    dims: set[int] = set()
    for k, node in enumerate(nodes):
        if not isinstance(node, dict) or not {"id", "label", "position"} <= node.keys():
            raise fail(f'node #{k} needs "id", "label" and "position" fields, got {_short(node)}')
        nid, lab, pos, size = node["id"], node["label"], node["position"], node.get("size", 1.0)
        if isinstance(nid, bool) or not isinstance(nid, int) or not _fits_int64(nid):
            raise fail(f"node #{k}: id must be an integer within +-2^63, got {_short(nid)}")
        if isinstance(lab, bool) or not isinstance(lab, int) or not 0 <= lab < len(classes):
            raise fail(f"node {nid}: label {_short(lab)} is not an index into the {len(classes)} classes")
        if not (isinstance(pos, list) and len(pos) in (2, 3) and all(_is_finite_number(v) for v in pos)):
            raise fail(f"node {nid}: position must be [x, y, z] or [x, y] (a map without heights), finite numbers, "
                       f"got {_short(pos)}")
        dims.add(len(pos))
        if len(dims) > 1:
            raise fail(f"node {nid}: position {_short(pos)} has {len(pos)} coordinates where earlier nodes have "
                       f"{5 - len(pos)}; give every node [x, y, z], or every node [x, y]")
        pos = pos if len(pos) == 3 else [*pos, 0.0]
        if any(abs(v) > MAX_COORDINATE_M for v in pos):
            raise fail(f"node {nid}: position {_short(pos)} is farther than {MAX_COORDINATE_M:g} m from the origin")
        if not _is_finite_number(size) or not 0 < size < MAX_SIZE:
            raise fail(f"node {nid}: size must be a positive finite number, got {_short(size)}")
        node_ids[k], label_idx[k], positions[k], sizes[k] = nid, lab, pos, size

    if (problem := extent_problem(positions)) is not None:
        raise fail(problem)
    uniq, counts = np.unique(node_ids, return_counts=True)
    if (counts > 1).any():
        raise fail(f"duplicate node ids {uniq[counts > 1].tolist()[:10]}; node ids must be unique")

    class_train_ids = np.array([train_id_of_class(c) for c in classes], dtype=np.int64)
    label_ids = class_train_ids[label_idx] if n else np.zeros(0, np.int64)
    if (label_ids < 0).any():
        unknown = sorted({classes[i] for i in label_idx[label_ids < 0].tolist()})
        raise fail(
            f"class names {unknown} are not Cityscapes classes; rename them to Cityscapes names "
            f"({', '.join(CITYSCAPES_CLASSES)}; map names such as 'tree', 'street light' or 'sign' are read too)"
        )

    if "edges" in data and data["edges"] is not None:
        edges = _edges_to_rows(data["edges"], node_ids, fail)
    else:
        edges = edges_within_radius(positions, connectivity_m)
    return GraphArrays(node_ids, label_ids, positions, sizes, edges)


def _short(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (a message stays one readable line)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


def _fits_int64(v: int) -> bool:
    return -(2**63) <= v < 2**63


def _is_finite_number(v: Any) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer too large for a float
        return False


def _edges_to_rows(edges_in: Any, node_ids: np.ndarray, fail: Any) -> np.ndarray:
    if not isinstance(edges_in, list) or not all(
        isinstance(e, list) and len(e) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and _fits_int64(v) for v in e)
        for e in edges_in
    ):
        raise fail('"edges" must be a list of [id_a, id_b] integer pairs')
    if not edges_in:
        return np.zeros((0, 2), np.int64)
    pairs = np.asarray(edges_in, dtype=np.int64)
    order = np.argsort(node_ids)
    pos = np.searchsorted(node_ids[order], pairs).clip(0, max(node_ids.size - 1, 0))
    known = node_ids.size > 0
    found = (node_ids[order][pos] == pairs) if known else np.zeros(pairs.shape, bool)
    if not found.all():
        bad = sorted(set(pairs[~found].tolist()))
        raise fail(f"edges refer to unknown node ids {bad[:10]}; every edge must join two listed nodes")
    loops = pairs[:, 0] == pairs[:, 1]
    if loops.any():
        raise fail(f"self-loop edges on node ids {pairs[loops, 0].tolist()[:10]}; remove them")
    rows = np.sort(order[pos], axis=1)
    rows = np.unique(rows, axis=0)
    return rows.astype(np.int64)


def write_graph(path: Path | str, graph: GraphArrays, classes: Sequence[str] = CITYSCAPES_CLASSES) -> Path:
    """Write a graph as a ``shgm-graph/1`` JSON file (parent folders are created); returns the path."""
    path = Path(path)
    doc = graph_to_dict(graph, classes)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(to_json_text(doc, compact=True) + "\n")
    except OSError as exc:
        raise GraphError(f"cannot write graph file {path}: {exc.strerror}; check the folder") from None
    return path


def read_graph(path: Path | str, *, connectivity_m: float = 10.0) -> GraphArrays:
    """Read and validate a ``shgm-graph/1`` JSON file.

    Args:
        path: the file.
        connectivity_m: builds edges (nodes closer than this, metres) when the file has none.

    Raises:
        GraphError: the file is missing, not JSON, or not a valid ``shgm-graph/1`` graph (message says why); a
            ``path`` that is no path (a decoded document: ``graph_from_dict``; pathlib's TypeError before).
    """
    if not isinstance(path, str | os.PathLike):
        raise GraphError(f"graph file {_short(path)} is no path; give the file's path (a decoded {FORMAT_TAG} "
                         "document: graph_from_dict(doc))")  # fmt: skip
    path = Path(path)
    try:
        if path.exists():
            if not path.is_file():
                raise GraphError(f"graph file {path} is not a regular file")
            if (size := path.stat().st_size) > MAX_FILE_BYTES:
                raise GraphError(f"graph file {path} holds {size / 1e6:.0f} MB, more than the "
                                 f"{MAX_FILE_BYTES / 1e6:.0f} MB a graph of {MAX_NODES} nodes needs")
        text = path.read_text()
    except FileNotFoundError:
        raise GraphError(f"graph file {path} does not exist (write one with `shgm-slam graph`)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GraphError(f"cannot read graph file {path}: {exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise GraphError(
            f"graph file {path} is not JSON ({exc.msg}, line {exc.lineno}); expected a {FORMAT_TAG} document"
        ) from None
    except (ValueError, RecursionError) as exc:  # an integer of thousands of digits, nesting too deep
        raise GraphError(f"graph file {path} cannot be read as a {FORMAT_TAG} document: {parse_failure(exc)}") from None
    return graph_from_dict(data, connectivity_m=connectivity_m, source=f"graph file {path}")
