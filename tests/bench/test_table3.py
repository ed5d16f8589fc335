"""The Table III protocol (``bench.table3``): splits and paper numbers, options, the placement error of one
localization, and a tiny end-to-end run that produces a well-formed table."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shgm_slam.bench.localization import BenchMode
from shgm_slam.bench.table3 import (
    PAPER_TABLE3,
    REPORT_SEEDS,
    SPLITS,
    TABLE3_WORLDS,
    Table3Options,
    localize,
    parse_seeds,
    run_table3,
    table3_markdown,
    write_table3,
)
from shgm_slam.config import DescriptorKind, ShgmConfig
from shgm_slam.errors import ConfigError
from shgm_slam.sim.kitti_paths import KittiDrive, drive_names
from shgm_slam.types import GraphArrays


def test_splits_name_robots_of_their_worlds_and_have_the_papers_numbers():
    for split in SPLITS:
        names = drive_names([KittiDrive.parse(s) for s in TABLE3_WORLDS[split.world]])
        assert split.robot_a in names and split.robot_b in names and split.robot_a != split.robot_b
        assert set(PAPER_TABLE3[split.paper_column]) == {k.value for k in DescriptorKind}
    # the paper's table as printed (ours: the histogram)
    assert PAPER_TABLE3["08B"]["histogram"] == (7.48, 3.67)
    assert PAPER_TABLE3["02"]["random-walk"] == (76.61, 36.42)


def test_parse_seeds():
    assert parse_seeds("report") == REPORT_SEEDS
    assert parse_seeds("3-5") == (3, 4, 5)
    assert parse_seeds("7,9") == (7, 9)
    for bad in ("5-3", "x", "1-2-3"):
        with pytest.raises(ConfigError):
            parse_seeds(bad)


@pytest.mark.parametrize(
    ("kw", "match"),
    [({"splits": ("09",)}, "unknown Table III split"), ({"seeds": ()}, "at least one"), ({"runs": 0}, "runs"),
     ({"max_frames": 1}, "max_frames"), ({"depth_noise": 2.0}, "noise")],
)  # fmt: skip
def test_options_are_validated(kw, match):
    with pytest.raises(ConfigError, match=match):
        Table3Options(**kw).validated()


def _grid_graph(rng: np.random.Generator) -> GraphArrays:
    """A random semantic graph of 120 objects along a 200 m street (world frame, z up)."""
    n = 120
    xyz = np.column_stack([rng.uniform(0, 200, n), rng.choice([-9.0, 9.0], n) + rng.normal(0, 2, n),
                           rng.uniform(0, 6, n)])  # fmt: skip
    labels = rng.choice([2, 5, 7, 8, 13], n)
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    i, j = np.nonzero(np.triu(d < 15.0, 1))
    return GraphArrays(np.arange(n), labels, xyz, np.full(n, 100.0), np.column_stack([i, j]))


@pytest.mark.parametrize("mode", list(BenchMode))
def test_localize_scores_the_placement_of_robot_b(mode):
    """B = A's graph (same world frame): the localization is accepted and puts B's cameras where they are."""
    rng = np.random.default_rng(4)
    graph = _grid_graph(rng)
    cams = np.column_stack([np.linspace(0, 200, 50), np.zeros(50), np.full(50, 1.65)])
    loc = localize(SPLITS[0], graph, graph, cams, DescriptorKind.HISTOGRAM, ShgmConfig(), seed=1, run=0, mode=mode)
    assert loc.success and loc.correct
    assert loc.placement_error_m < 0.1 and loc.centroid_error_m < 0.1


def test_tiny_table3_run_is_well_formed(shared_data, tmp_path):
    options = Table3Options(seeds=(10,), runs=1, max_frames=12, resolution=(48, 16), cache=tmp_path / "cache",
                            kinds=(DescriptorKind.HISTOGRAM, DescriptorKind.NEIGHBOR_VECTOR))  # fmt: skip
    results = run_table3(options, kitti_root=shared_data / "kitti")
    assert [(r.split, r.descriptor) for r in results.rows] == [
        (s.name, k.value) for s in SPLITS for k in options.kinds
    ]
    assert all(r.queries == 1 and r.paper_m is not None for r in results.rows)
    assert len(results.worlds) == 3 and all(w["frames"] and max(w["frames"].values()) == 12
                                            for w in results.worlds.values())  # fmt: skip
    md = table3_markdown(results)
    table = [line for line in md.splitlines() if line.startswith("|")]
    assert len(table) == 2 + len(results.rows)
    assert all(line.count("|") == table[0].count("|") for line in table)
    assert "paper" in table[0] and "7.48 ± 3.67 (08B)" in md and "(19)" in md
    json_path, md_path = write_table3(results, tmp_path / "out")

    def no_nan(token: str) -> float:
        raise AssertionError(f"{token} in table3.json")

    data = json.loads(json_path.read_text(), parse_constant=no_nan)
    assert data["format"] == "shgm-table3/1" and len(data["rows"]) == len(results.rows)
    assert md_path.read_text() == md
    # rendered worlds are cached: a second run renders nothing new
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "cache").glob("*/scenario.json")}
    assert len(stamps) == 3
    run_table3(options, kitti_root=shared_data / "kitti")
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "cache").glob("*/scenario.json")} == stamps


def test_cli_bench_table3(shared_data, tmp_path):
    from typer.testing import CliRunner

    from shgm_slam.cli import app

    args = ["bench", "table3", "-o", str(tmp_path / "out"), "--seeds", "10", "--runs", "1", "--split", "02",
            "--descriptor", "histogram", "--max-frames", "10", "--resolution", "48x16",
            "--cache", str(tmp_path / "cache"), "--kitti-root", str(shared_data / "kitti")]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "| 02 | histogram |" in result.output and (tmp_path / "out" / "table3.md").is_file()
    bad = CliRunner().invoke(app, [*args[:-2], "--split", "19"])
    assert bad.exit_code == 2 and "unknown Table III split" in bad.output
    paper = CliRunner().invoke(app, [*args, "--mode", "paper"])
    assert paper.exit_code == 0 and "paper mode" in paper.output, paper.output
    bad_mode = CliRunner().invoke(app, [*args, "--mode", "fast"])
    assert bad_mode.exit_code == 2 and "choose robust or paper" in bad_mode.output
