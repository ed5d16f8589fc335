"""shgm-graph/1 files: round trips, class remapping, optional fields, and a clear error per bad file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shgm_slam.errors import GraphError
from shgm_slam.graph.semantic_graph import edges_within_radius
from shgm_slam.io.graph_json import graph_from_dict, graph_to_dict, read_graph, write_graph
from shgm_slam.labels import CITYSCAPES_CLASSES, MAP_CLASS_NAMES, Label
from shgm_slam.types import GraphArrays


def random_graph(n: int = 30, seed: int = 0) -> GraphArrays:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-30, 30, (n, 3))
    ids = rng.permutation(1000)[:n].astype(np.int64)  # ids are not row indices
    labels = rng.choice([Label.BUILDING, Label.POLE, Label.CAR, Label.VEGETATION], n).astype(np.int64)
    return GraphArrays(ids, labels, pos, rng.uniform(1, 5000, n), edges_within_radius(pos, 12.0))


def test_round_trip_is_exact(tmp_path):
    g = random_graph()
    path = write_graph(tmp_path / "sub" / "g.json", g)
    doc = json.loads(path.read_text())
    assert doc["format"] == "shgm-graph/1" and doc["classes"] == list(CITYSCAPES_CLASSES)
    # edges in the file are node ids
    assert set(map(tuple, doc["edges"])) == {tuple(e) for e in g.node_ids[g.edges].tolist()}
    back = read_graph(path)
    for field in ("node_ids", "label_ids", "positions_xyz", "sizes", "edges"):
        np.testing.assert_array_equal(getattr(back, field), getattr(g, field))


def test_custom_class_list_is_remapped_by_name():
    g = random_graph(10)
    doc = graph_to_dict(g, classes=["car", "vegetation", "pole", "building"])
    assert {n["label"] for n in doc["nodes"]} <= {0, 1, 2, 3}
    back = graph_from_dict(doc)
    np.testing.assert_array_equal(back.label_ids, g.label_ids)
    doc["classes"] = ["Car", "vegetation", "POLE", "building"]  # case and spacing tolerant
    np.testing.assert_array_equal(graph_from_dict(doc).label_ids, g.label_ids)
    with pytest.raises(GraphError, match="no class"):
        graph_to_dict(g, classes=["car"])


def test_map_class_names_are_read_as_their_cityscapes_class():
    g = random_graph(12)
    doc = graph_to_dict(g, classes=["car", "vegetation", "pole", "building"])
    doc["classes"] = ["Parked_Car", "tree", "street-light", "house"]  # what map layers call them
    np.testing.assert_array_equal(graph_from_dict(doc).label_ids, g.label_ids)
    for name, train_id in MAP_CLASS_NAMES.items():  # every map name is one Cityscapes class, none shadows one
        assert 0 <= train_id < len(CITYSCAPES_CLASSES) and name not in CITYSCAPES_CLASSES
    with pytest.raises(GraphError, match="'tree', 'street light'"):  # the error says map names are read
        graph_from_dict(_doc(classes=["building", "spaceship"]))


def test_optional_size_and_edges():
    doc = {
        "format": "shgm-graph/1",
        "classes": list(CITYSCAPES_CLASSES),
        "nodes": [{"id": 7, "label": 2, "position": [0, 0, 0]}, {"id": 3, "label": 5, "position": [4, 0, 0]},
                  {"id": 9, "label": 5, "position": [40, 0, 0]}],
    }  # fmt: skip
    g = graph_from_dict(doc, connectivity_m=10.0)
    np.testing.assert_array_equal(g.sizes, [1, 1, 1])
    np.testing.assert_array_equal(g.edges, [[0, 1]])
    assert graph_from_dict(doc, connectivity_m=50.0).num_edges == 3
    doc["edges"] = [[9, 7], [7, 9]]  # explicit edges win; duplicates and order are normalized
    np.testing.assert_array_equal(graph_from_dict(doc).edges, [[0, 2]])


def test_empty_graph_is_valid(tmp_path):
    path = tmp_path / "empty.json"
    path.write_text(json.dumps({"format": "shgm-graph/1", "classes": [], "nodes": []}))
    g = read_graph(path)
    assert len(g) == 0 and g.edges.shape == (0, 2) and g.positions_xyz.shape == (0, 3)
    write_graph(tmp_path / "again.json", g)
    assert len(read_graph(tmp_path / "again.json")) == 0


def _doc(**changes):
    doc = {
        "format": "shgm-graph/1",
        "classes": ["building", "pole"],
        "nodes": [{"id": 1, "label": 0, "position": [0, 0, 0], "size": 2.0},
                  {"id": 2, "label": 1, "position": [1, 0, 0]}],
        "edges": [[1, 2]],
    }  # fmt: skip
    doc.update(changes)
    return doc


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ([1, 2], "JSON object"),
        (_doc(format="shgm-graph/2"), "format tag"),
        ({k: v for k, v in _doc().items() if k != "format"}, "format tag"),
        ({k: v for k, v in _doc().items() if k != "nodes"}, '"nodes"'),
        ({k: v for k, v in _doc().items() if k != "classes"}, '"classes"'),
        (_doc(nodes=[{"id": 1, "position": [0, 0, 0]}]), "needs"),
        (_doc(nodes=[{"id": 1, "label": 0, "position": [0, 0, 0]},
                     {"id": 1, "label": 1, "position": [1, 0, 0]}]), "duplicate node ids"),
        (_doc(nodes=[{"id": 1, "label": 0, "position": [0, float("nan"), 0]}], edges=[]), "finite"),
        (_doc(nodes=[{"id": 1, "label": 0, "position": [0]}], edges=[]), r"\[x, y, z\] or \[x, y\]"),
        (_doc(nodes=[{"id": 1, "label": 0, "position": [0, 0, 0]}, {"id": 2, "label": 1, "position": [9, 0]}],
              edges=[]), "2 coordinates where earlier nodes have 3"),
        (_doc(nodes=[{"id": i, "label": 0, "position": [48.1 + i * 1e-4, 11.5, 0]} for i in range(3)], edges=[]),
         "span only 0.0002 .*latitude and longitude"),
        (_doc(nodes=[{"id": 1, "label": 2, "position": [0, 0, 0]}], edges=[]), "not an index"),
        (_doc(nodes=[{"id": 1, "label": -1, "position": [0, 0, 0]}], edges=[]), "not an index"),
        (_doc(nodes=[{"id": 1, "label": 0, "position": [0, 0, 0], "size": -3}], edges=[]), "size"),
        (_doc(edges=[[1, 5]]), "unknown node ids \\[5\\]"),
        (_doc(edges=[[2, 2]]), "self-loop"),
        (_doc(edges=[[1, 2, 3]]), "pairs"),
        (_doc(classes=["building", "spaceship"]), "spaceship"),
        (_doc(nodes=[{"id": "a", "label": 0, "position": [0, 0, 0]}], edges=[]), "id must be an integer"),
    ],
)  # fmt: skip
def test_bad_documents_raise_graph_errors_naming_the_file(tmp_path, doc, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(GraphError, match=message) as info:
        read_graph(path)
    assert str(path) in str(info.value)


def test_unused_unknown_class_names_are_tolerated():
    g = graph_from_dict(_doc(classes=["building", "pole", "spaceship"]))
    np.testing.assert_array_equal(g.label_ids, [Label.BUILDING, Label.POLE])


def test_unreadable_files(tmp_path):
    with pytest.raises(GraphError, match="does not exist"):
        read_graph(tmp_path / "missing.json")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(GraphError, match="not JSON"):
        read_graph(tmp_path / "junk.json")
    with pytest.raises(GraphError, match=r"graph file \{'format': 'shgm-graph/1'\} is no path; .*graph_from_dict"):
        read_graph({"format": "shgm-graph/1"})  # a decoded document: pathlib's TypeError before


def test_graph_files_too_large_to_match_or_not_files_are_refused(tmp_path, monkeypatch):
    import shgm_slam.io.graph_json as gj

    monkeypatch.setattr(gj, "MAX_NODES", 5)
    nodes = [{"id": i, "label": 0, "position": [float(i), 0.0, 0.0]} for i in range(6)]
    path = tmp_path / "big.json"
    path.write_text(json.dumps({"format": "shgm-graph/1", "classes": ["road"], "nodes": nodes}))
    with pytest.raises(GraphError, match="6 nodes, more than the 5"):
        read_graph(path)
    with pytest.raises(GraphError, match="not a regular file"):
        read_graph(tmp_path)
    monkeypatch.setattr(gj, "MAX_FILE_BYTES", 10)
    with pytest.raises(GraphError, match="MB, more than"):
        read_graph(path)


def test_an_integer_of_thousands_of_digits_is_said_in_our_words(tmp_path):
    path = tmp_path / "g.json"
    path.write_text('{"format": "shgm-graph/1", "classes": ["road"], "nodes": [{"id": ' + "1" * 50000 + "}]}")
    with pytest.raises(GraphError, match="holds an integer of 50000 digits") as info:
        read_graph(path)
    assert "set_int_max_str_digits" not in str(info.value)


def test_a_map_without_heights_is_read_at_height_zero():
    """Map layers often hold no heights; [x, y] positions used to be refused ("three finite numbers")."""
    g = graph_from_dict(_doc(nodes=[{"id": 1, "label": 0, "position": [3.5, -2]},
                                    {"id": 2, "label": 1, "position": [7, 1.25]}]))  # fmt: skip
    np.testing.assert_array_equal(g.positions_xyz, [[3.5, -2, 0], [7, 1.25, 0]])


def test_plural_class_names_are_read_as_their_singular():
    """A map layer named "traffic lights" or "street lamps" was an unknown class (the whole file refused)."""
    g = graph_from_dict(_doc(classes=["Traffic_Lights", "street lamps"]))
    np.testing.assert_array_equal(g.label_ids, [Label.TRAFFIC_LIGHT, Label.POLE])
    with pytest.raises(GraphError, match="spaceships"):
        graph_from_dict(_doc(classes=["building", "spaceships"]))
