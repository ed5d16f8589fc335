"""Mistyped command lines of ``simulate`` and ``bench ...``: each is refused with one line and exit code 2
before any benchmark or render starts (the benchmark functions are replaced by ones that fail the test)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from shgm_slam.bench import seeds as seeds_module
from shgm_slam.bench.seeds import parse_seeds
from shgm_slam.cli import app
from shgm_slam.errors import ConfigError
from shgm_slam.sim.kitti_paths import KittiDrive

runner = CliRunner()

BENCHMARKS = {
    "shgm_slam.bench.simulate": "run_simulate_benchmark",
    "shgm_slam.bench.localization_sparse": "run_sparse_benchmark",
    "shgm_slam.bench.heldout": "run_heldout_benchmark",
    "shgm_slam.bench.depth_quality": "run_depth_quality_benchmark",
    "shgm_slam.bench.table3": "run_table3",
    "shgm_slam.bench.robots": "run_robots_benchmark",
    "shgm_slam.demo": "prepare_world",  # bench distributed and live render the demo world first
}


@pytest.fixture
def no_benchmark(monkeypatch):
    """Every benchmark (and the demo world's render) fails the test if it is started."""
    import importlib

    def started(*_args, **_kwargs):
        raise AssertionError("the benchmark started before the command line was refused")

    for module, name in BENCHMARKS.items():
        monkeypatch.setattr(importlib.import_module(module), name, started)


def _refused(args: list[str], says: str) -> None:
    res = runner.invoke(app, args, env={"COLUMNS": "250"})
    text = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code == 2, res.output
    assert says in text, res.output
    assert "Traceback" not in res.output


def test_a_huge_seed_range_is_refused_before_its_seeds_are_listed(monkeypatch):
    # 0-2000000000 listed two billion seeds (gigabytes; the process was killed) before anything was said
    from shgm_slam.bench.seeds import MAX_SEEDS

    def bounded_range(*args):
        assert len(range(*args)) <= MAX_SEEDS, "the seeds of a huge range were listed"
        return range(*args)

    monkeypatch.setattr(seeds_module, "range", bounded_range, raising=False)
    with pytest.raises(ConfigError, match="selects 2000000001 worlds; give at most"):
        parse_seeds("0-2000000000")
    with pytest.raises(ConfigError, match=f"selects {MAX_SEEDS + 1} worlds"):
        parse_seeds(",".join(str(k) for k in range(MAX_SEEDS + 1)))
    assert len(parse_seeds(f"0-{MAX_SEEDS - 1}")) == MAX_SEEDS  # the most still run


def test_a_kitti_frame_number_of_thousands_of_digits_is_a_config_error(tmp_path):
    # Python's int() stopped at 4300 digits with a ValueError traceback
    huge = "9" * 5000
    for spec in (f"08:0-{huge}", f"08:{huge}-"):
        with pytest.raises(ConfigError, match="more than 9 digits"):
            KittiDrive.parse(spec)
    _refused(["simulate", "-s", "kitti-paths", "-o", str(tmp_path / "w"), "--kitti-drive", f"08:0-{huge}"],
             "--kitti-drive")  # fmt: skip
    assert KittiDrive.parse("08:0-123456789") == KittiDrive("08", 0, 123456789)  # nine digits: read as before


@pytest.mark.parametrize("bench", [["sparse", "--seeds", "1"], ["table3"], ["heldout"]])
def test_a_results_folder_under_a_file_is_refused_before_the_benchmark(tmp_path, no_benchmark, bench):
    # the benchmark ran to its end, then write_report's mkdir raised NotADirectoryError (a traceback)
    (tmp_path / "afile").write_text("")
    _refused(["bench", *bench, "-o", str(tmp_path / "afile" / "sub")], "afile is a file, not a folder")


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc (Linux)")
def test_a_results_folder_that_cannot_be_created_is_refused_before_the_benchmark(no_benchmark):
    _refused(["bench", "sparse", "--seeds", "1", "-o", "/proc/no-such/out"], "cannot write in /proc")
    _refused(["bench", "simulate", "-o", "/proc/no-such/sim.json"], "cannot write in /proc")


@pytest.mark.parametrize("bench, out", [(["sparse", "--seeds", "1"], "out"), (["simulate"], "sim.json"),
                                        (["simulate"], ""), (["robots"], "")])  # fmt: skip
def test_an_output_path_the_os_cannot_look_at_is_refused(tmp_path, no_benchmark, bench, out):
    # a name longer than the file system allows: the checks of --out raised OSError (File name too long), a traceback
    too_long = tmp_path / ("a" * 300)
    _refused(["bench", *bench, "-o", str(too_long / out if out else too_long)], "cannot be looked at")


def test_bench_simulate_refuses_a_folder_as_its_results_file(tmp_path, no_benchmark):
    # the whole benchmark ran, then writing the JSON over the folder raised IsADirectoryError
    _refused(["bench", "simulate", "-o", str(tmp_path)], "is a folder; give the file to write")


def test_writable_results_folders_are_accepted_and_the_probe_leaves_nothing(tmp_path):
    from shgm_slam.cli.options import out_file, out_folder

    assert out_folder(str(tmp_path / "new" / "nested")) == tmp_path / "new" / "nested"
    assert out_file(str(tmp_path / "a" / "b.json")) == tmp_path / "a" / "b.json"
    (tmp_path / "old.json").write_text("{}")
    assert out_file(str(tmp_path / "old.json")) == tmp_path / "old.json"  # written over, as before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]  # nothing created by the checks


@pytest.mark.parametrize("command", ["distributed", "live"])
def test_a_bad_config_is_refused_before_the_demo_world_is_rendered(tmp_path, no_benchmark, command):
    config = tmp_path / "c.yaml"
    config.write_text("bogus: 1\n")
    _refused(["bench", command, "-o", str(tmp_path / "o"), "--cache", str(tmp_path / "cache"), "--config",
              str(config)], "bogus: Extra inputs are not permitted")  # fmt: skip


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["heldout", "--mode", "files", "--mode", "files"], "--mode files is given more than once"),
        (["heldout", "--scenario", "disjoint", "--scenario", "disjoint"], "--scenario disjoint is given more"),
        (["depth-quality", "--level", "0.05", "--level", "0.050"], "--level 0.05 is given more than once"),
        (["depth-quality", "--scenario", "disjoint", "--scenario", "disjoint"], "--scenario disjoint is given"),
        (["depth-quality", "--odometry", "visual,visual"], "--odometry visual is given more than once"),
        (["table3", "--descriptor", "histogram", "--descriptor", "histogram"], "--descriptor histogram is given"),
        (["robots", "--fleets", "1,1"], "--fleets 1 is given more than once"),
        (["distributed", "--faults", "none,none"], "--faults none is given more than once"),
        (["distributed", "--faults", ","], "--faults ',': comma-separated none, robot, server"),
    ],
)
def test_a_value_given_twice_is_refused_before_it_is_run_twice(tmp_path, no_benchmark, args, says):
    # each was run (or judged) twice and counted twice in the results; --faults ',' ran no distributed run
    _refused(["bench", args[0], "-o", str(tmp_path / "o"), *args[1:]], says)


def test_heldout_refuses_to_replay_into_the_folder_it_replays(tmp_path, no_benchmark):
    # every run there has its verdicts.json: all were taken as done and nothing was replayed
    (tmp_path / "h" / "runs").mkdir(parents=True)
    _refused(["bench", "heldout", "-o", str(tmp_path / "h"), "--replay-from", str(tmp_path / "h")],
             "is the --out folder")  # fmt: skip


def test_heldout_names_the_mode_it_does_not_know(tmp_path, no_benchmark):
    _refused(["bench", "heldout", "-o", str(tmp_path / "o"), "--mode", "files", "--mode", "rbg"],
             "--mode 'rbg': choose files or rgb")  # fmt: skip
