"""What produced a result is recorded with it: metrics.json and every benchmark JSON carry the environment."""

from __future__ import annotations

import importlib.metadata
import json
from pathlib import Path

from shgm_slam import __version__
from shgm_slam.bench.report import write_report
from shgm_slam.environment import LIBRARIES, environment, processor_name
from shgm_slam.run_report import RunSummary


def test_the_environment_names_this_package_python_and_the_installed_library_versions():
    env = environment()
    assert env["shgm_slam"] == __version__ and env["python"].count(".") == 2
    assert set(env["libraries"]) == set(LIBRARIES)
    assert env["libraries"]["numpy"] == importlib.metadata.version("numpy")
    assert json.loads(json.dumps(env)) == env  # plain JSON


def test_the_processor_is_read_from_cpuinfo_and_a_missing_file_is_not_an_error(tmp_path: Path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Some CPU @ 2.0GHz\nmodel name\t: other\n")
    assert processor_name(cpuinfo) == "Some CPU @ 2.0GHz"
    assert isinstance(processor_name(tmp_path / "missing"), str)


def test_metrics_and_benchmark_reports_carry_it(tmp_path: Path):
    summary = RunSummary(tmp_path, [], 0, 0, 0, {}, 0.0, 0.0)
    assert summary.to_json_dict()["environment"] == environment()
    write_report(tmp_path, "bench", {"rows": []}, lambda results: "table\n")
    assert json.loads((tmp_path / "bench.json").read_text())["environment"] == environment()


def test_a_report_ends_with_a_line_naming_what_computed_it(tmp_path: Path):
    write_report(tmp_path, "bench", {"rows": []}, lambda results: "table\n")
    md = (tmp_path / "bench.md").read_text()
    assert md.startswith("table\n") and md.rstrip().endswith("._")
    assert f"shgm_slam {__version__}" in md and f"numpy {importlib.metadata.version('numpy')}" in md
