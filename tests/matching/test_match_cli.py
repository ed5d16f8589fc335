"""``shgm-slam match`` smoke tests: JSON output, rich summary, clean errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.geometry.se3 import pose_error
from shgm_slam.io.graph_json import write_graph

from .synthetic import city_pair

runner = CliRunner()


@pytest.fixture(scope="module")
def graph_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("graphs")
    a, b, T_a_b = city_pair(seed=1)
    return write_graph(folder / "a.json", a), write_graph(folder / "b.json", b), T_a_b


@pytest.mark.parametrize(
    "options", [[], ["--mode", "ransac"], ["--descriptor", "histogram", "--mode", "clique"]]
)
def test_match_json(graph_files, options):
    path_a, path_b, T_a_b = graph_files
    result = runner.invoke(app, ["match", str(path_a), str(path_b), "--json", *options])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert list(doc)[:5] == ["success", "T_a_b", "inliers", "candidates", "timings_ms"]
    assert doc["success"] is True
    v = doc["verification"]
    assert doc["decisive"] is (v["llr"] >= 2 * v["llr_threshold"])  # backend.min_closures_to_anchor: 2
    _, dr = pose_error(np.asarray(doc["T_a_b"]), T_a_b)
    assert dr < 1.0


def test_match_summary_and_no_match(graph_files, tmp_path):
    path_a, path_b, _ = graph_files
    result = runner.invoke(app, ["match", str(path_a), str(path_b)])
    assert result.exit_code == 0 and "match" in result.output and "T_a_b" in result.output
    _, other, _ = city_pair(seed=20, overlap=False)
    path_c = write_graph(tmp_path / "c.json", other)
    result = runner.invoke(
        app, ["match", str(path_a), str(path_c), "--json", "--descriptor", "neighbor-vector"]
    )
    assert result.exit_code == 0
    doc = json.loads(result.output)
    assert doc["success"] is False and doc["T_a_b"] is None and doc["inliers"] == []


def test_the_summary_of_a_rejected_match_names_no_inliers(graph_files, tmp_path):
    path_a, path_b, _ = graph_files
    accepted = runner.invoke(app, ["match", str(path_a), str(path_b)], terminal_width=200)
    rows = [line.split()[0] for line in accepted.output.splitlines() if line.strip()]
    assert "inliers" in rows and "rejected" not in rows
    _, other, _ = city_pair(seed=20, overlap=False)
    path_c = write_graph(tmp_path / "c.json", other)
    result = runner.invoke(app, ["match", str(path_a), str(path_c)], terminal_width=200)
    assert result.exit_code == 0 and "no match" in result.output
    rows = [line.split()[0] for line in result.output.splitlines() if line.strip()]
    assert "inliers" not in rows and "rejected" in rows
    assert "best hypothesis" in result.output or "no hypothesis" in result.output


def test_match_bad_files_exit_cleanly(graph_files, tmp_path):
    path_a, _, _ = graph_files
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"format": "shgm-graph/1", "classes": [], "nodes": [], "edges": []}))
    for path in (broken, tmp_path / "missing.json"):
        result = runner.invoke(app, ["match", str(path_a), str(path)])
        assert result.exit_code == 2 and "error" in result.output, result.output
    result = runner.invoke(app, ["match", str(path_a), str(empty), "--json"])
    if result.exit_code == 0:  # an empty graph is a valid file: an unsuccessful match with a reason
        doc = json.loads(result.output)
        assert doc["success"] is False and "node" in doc["reason"]
    else:
        assert result.exit_code == 2 and "error" in result.output
    result = runner.invoke(app, ["match", str(path_a), str(path_a), "--mode", "magic"])
    assert result.exit_code != 0


def test_an_accepted_match_says_what_its_evidence_is_worth(graph_files):
    # a match barely past chance is one piece of evidence (a far-apart pair passes ~alpha of the time): the
    # summary says so instead of a bare "match"; a strong one is as unlikely under chance as two together
    from shgm_slam.cli.render import match_evidence
    from shgm_slam.matching import MatchResult

    path_a, path_b, _ = graph_files
    out = runner.invoke(app, ["match", str(path_a), str(path_b)], terminal_width=300).output
    assert "evidence" in out and "chance threshold" in out

    def accepted(llr: float, threshold: float) -> MatchResult:
        r = MatchResult(True, np.eye(4), np.zeros((0, 2), np.int64), 10)
        r.llr, r.llr_threshold = llr, threshold
        return r

    weak, strong = accepted(9.5, 9.1), accepted(18.3, 9.1)
    assert not weak.is_decisive(2) and strong.is_decisive(2)
    assert not strong.is_decisive(2, tried=2)  # the bar grows with the matches a pair tried: 2 (9.1 + ln 2) > 18.3
    assert not strong.is_decisive(1)  # one piece needed: nothing to be decisive about
    assert "one piece of evidence" in match_evidence(weak, 0.003, 2)
    assert "about 1 in 333" in match_evidence(weak, 0.003, 2)
    assert "as far beyond chance as 2 independent matches" in match_evidence(strong, 0.003, 2)
    assert "places a robot on one" in match_evidence(weak, 0.003, 1)
    failed = accepted(30.0, 9.1)
    failed.success = False
    assert not failed.is_decisive(2)
