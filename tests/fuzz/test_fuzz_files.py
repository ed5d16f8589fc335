"""Graph JSON files, calibrations and config YAML, valid-looking with fuzzed values or plain garbage:
a result or a ``ShgmError`` (exit 2 through the CLI), never another exception."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.config import ShgmConfig, load_config
from shgm_slam.data import open_sequence
from shgm_slam.errors import ShgmError
from shgm_slam.io.graph_json import read_graph
from tests.fuzz.conftest import fuzz_settings, scratch

HUGE = [2**63, -(2**63) - 1, 2**64, 10**30, 10**400, 2**31, -1, 0]
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -0.0, -50.0, 1e308, 1e-308, 16.0, 12.0]),
)
atoms = st.one_of(
    st.none(), st.booleans(), st.integers(), st.sampled_from(HUGE), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8), st.sampled_from(["road", "car", "building", "[/x]", "NaN"]),
)
json_values = st.recursive(atoms, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6),
                                                                                               inner, max_size=4),
                           max_leaves=12)  # fmt: skip


@st.composite
def graph_docs(draw: st.DrawFn) -> object:
    """A valid shgm-graph/1 document with some values replaced by fuzz (or, sometimes, any JSON value)."""
    if draw(st.integers(0, 9)) == 0:
        return draw(json_values)
    n = draw(st.integers(0, 6))
    rng = np.random.default_rng(draw(st.integers(0, 1000)))
    nodes = [{"id": i, "label": int(rng.integers(0, 3)), "position": rng.normal(0, 20, 3).tolist(),
              "size": float(rng.uniform(1, 100))} for i in range(n)]  # fmt: skip
    doc = {"format": "shgm-graph/1", "classes": ["road", "building", "car"], "nodes": nodes,
           "edges": [[i, i + 1] for i in range(n - 1)]}  # fmt: skip
    for _ in range(draw(st.integers(0, 3))):
        target = draw(st.sampled_from(["format", "classes", "nodes", "edges", "node", "field", "edge"]))
        value = draw(json_values)
        if target == "node" and nodes:
            nodes[draw(st.integers(0, n - 1))] = value
        elif target == "field" and nodes and isinstance(node := nodes[draw(st.integers(0, n - 1))], dict):
            key = draw(st.sampled_from(["id", "label", "position", "size"]))
            node[key] = draw(st.one_of(st.just(value), st.sampled_from(HUGE), st.lists(numbers, min_size=3,
                                                                                      max_size=3)))
        elif target == "edge" and isinstance(doc["edges"], list):
            doc["edges"].append(draw(st.lists(st.one_of(st.integers(-3, 8), st.sampled_from(HUGE)), max_size=3)))
        else:
            doc[target] = value
    return doc


@fuzz_settings(300)
@given(doc=graph_docs())
def test_fuzzed_graph_files_are_graphs_or_graph_errors(doc):
    with scratch() as d:
        path = d / "g.json"
        path.write_text(json.dumps(doc))
        try:
            graph = read_graph(path)
        except ShgmError:
            return
        assert np.isfinite(graph.positions_xyz).all() and (graph.sizes > 0).all()
        assert graph.edges.ndim == 2 and (graph.edges < len(graph.node_ids)).all()


@fuzz_settings(40)
@given(doc=graph_docs(), raw=st.one_of(st.none(), st.binary(max_size=64)))
def test_match_cli_on_fuzzed_graphs_exits_0_or_2(doc, raw):
    with scratch() as d:
        good = {"format": "shgm-graph/1", "classes": ["building", "car"],
                "nodes": [{"id": i, "label": i % 2, "position": [i * 7.0, (i * 3) % 5, i % 4]} for i in range(8)]}
        (d / "a.json").write_text(json.dumps(good))
        b = d / "b.json"
        b.write_bytes(raw) if raw is not None else b.write_text(json.dumps(doc))
        res = CliRunner().invoke(app, ["match", str(d / "a.json"), str(b), "--json"])
        assert res.exit_code in (0, 2), (res.output, repr(res.exception))
        assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)


# --- calibrations ---------------------------------------------------------------------------------------------


@st.composite
def calib_texts(draw: st.DrawFn) -> bytes:
    """A KITTI calib.txt for a 32x24 camera with fuzzed numbers, lines or bytes."""
    P = [50.0, 0.0, 15.5, 0.0, 0.0, 50.0, 11.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    for _ in range(draw(st.integers(0, 3))):
        P[draw(st.integers(0, 11))] = draw(numbers)
    count = draw(st.sampled_from([12, 12, 12, 11, 13, 0]))
    values = [*P, 1.0][:count]
    key = draw(st.sampled_from(["P2", "P2", "P0", "p2", "P2 ", ""]))
    line = f"{key}: " + " ".join(repr(v) if draw(st.booleans()) else str(v) for v in values)
    text = "".join(f"P{k}: {' '.join(map(str, P))}\n" for k in (0, 1)) + line + "\n"
    data = text.encode()
    if draw(st.integers(0, 5)) == 0:
        data = draw(st.binary(max_size=200))
    elif draw(st.integers(0, 5)) == 0:
        cut = draw(st.integers(0, len(data)))
        data = data[:cut] + draw(st.binary(max_size=8)) + data[cut:]
    return data


@fuzz_settings(200)
@given(data=calib_texts())
def test_fuzzed_calibrations_open_sane_or_fail_cleanly(data):
    with scratch() as d:
        (d / "image_2").mkdir()
        cv2.imwrite(str(d / "image_2" / "000000.png"), np.zeros((24, 32, 3), np.uint8))
        (d / "times.txt").write_text("0.0\n")
        (d / "calib.txt").write_bytes(data)
        try:
            seq = open_sequence(d)
        except ShgmError:
            return
        K = seq.intrinsics
        assert K.fx > 0 and K.fy > 0 and math.isfinite(K.fx) and math.isfinite(K.fy)
        assert 0 <= K.cx < 32 and 0 <= K.cy < 24


# --- config YAML ------------------------------------------------------------------------------------------------

_DEFAULTS = ShgmConfig().model_dump(mode="json")


@st.composite
def config_docs(draw: st.DrawFn) -> object:
    """The default config with a few fields (or whole stages) set to fuzz; sometimes any YAML value."""
    if draw(st.integers(0, 9)) == 0:
        return draw(json_values)
    doc = json.loads(json.dumps(_DEFAULTS))
    for _ in range(draw(st.integers(1, 4))):
        stage = draw(st.sampled_from(sorted(doc)))
        if isinstance(doc[stage], dict) and doc[stage] and draw(st.integers(0, 4)):
            doc[stage][draw(st.sampled_from(sorted(doc[stage])))] = draw(json_values)
        else:
            doc[stage] = draw(json_values)
    return doc


@fuzz_settings(200)
@given(doc=config_docs(), garbage=st.one_of(st.none(), st.binary(max_size=80)))
def test_fuzzed_configs_load_or_are_config_errors(doc, garbage):
    with scratch() as d:
        path = d / "c.yaml"
        if garbage is not None:
            path.write_bytes(garbage)
        else:
            try:
                path.write_text(yaml.safe_dump(doc))
            except (yaml.YAMLError, ValueError):
                return
        try:
            cfg = load_config(path)
        except ShgmError:
            return
        cfg.to_yaml()  # a loaded config can be written back (the results folder's config.yaml)


@fuzz_settings(15)
@given(doc=config_docs())
def test_dump_config_cli_on_fuzzed_configs_exits_0_or_2(doc):
    with scratch() as d:
        path = d / "c.yaml"
        path.write_text(yaml.safe_dump(doc))
        res = CliRunner().invoke(app, ["dump-config", "--config", str(path)])
        assert res.exit_code in (0, 2), (res.output, repr(res.exception))


_GRAPH_NODE = '{"format":"shgm-graph/1","classes":["road"],"nodes":[{"id":0,"label":0,"position":[1,2,3],"size":%s}]}'
EXTREME_TEXTS = {
    "nested": "[" * 100_000 + "]" * 100_000,  # deeper than Python's recursion limit
    "long-int": "9" * 5000,  # more digits than int() converts
    "graph-size-beyond-float": _GRAPH_NODE % ("1" + "0" * 400),
    "graph-long-int": _GRAPH_NODE % ("9" * 5000),
}


@pytest.mark.parametrize("name", list(EXTREME_TEXTS))
def test_extreme_documents_are_clean_errors_in_every_reader(tmp_path, name):
    """Nesting deeper than the recursion limit, integers beyond float or int(): one line and exit 2 from every
    command that reads JSON or YAML (they were RecursionError, ValueError and OverflowError tracebacks)."""
    text = EXTREME_TEXTS[name]
    good_graph = tmp_path / "good.json"
    good_graph.write_text(_GRAPH_NODE % "1.0")
    (tmp_path / "doc.json").write_text(text)
    (tmp_path / "cfg.yaml").write_text(text if not name.startswith("graph") else f"odometry: {text}")
    model = tmp_path / "m.onnx"
    model.write_bytes(b"")
    (tmp_path / "m.yaml").write_text(text)
    results = tmp_path / "results"
    results.mkdir()
    (results / "metrics.json").write_text(text)
    commands = [
        ["match", str(good_graph), str(tmp_path / "doc.json")],
        ["dump-config", "--config", str(tmp_path / "cfg.yaml")],
        ["check-model", str(model), "--runs", "1"],
        ["eval", str(results)],
    ]
    for args in commands:
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and "error:" in res.output, (args[0], res.exception, res.output[-300:])
