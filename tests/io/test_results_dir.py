"""A reused results folder never mixes two runs: refused unless --overwrite, which clears only our files."""

from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.errors import DataError
from shgm_slam.io.export import LOCK_FILE, claimed_results_dir, make_results_dir, run_output_files


def _earlier_run(folder):
    folder.mkdir()
    for name in ("b_fused_tum.txt", "b_fused_kitti.txt", "metrics.json", "pose_graph.g2o", ".metrics.json.x1"):
        (folder / name).write_text("old\n")
    (folder / "notes.md").write_text("mine\n")


def test_a_fresh_or_empty_folder_is_used(tmp_path):
    assert make_results_dir(tmp_path / "new").is_dir()
    (tmp_path / "empty").mkdir()
    assert make_results_dir(tmp_path / "empty") == tmp_path / "empty"


def test_a_folder_with_an_earlier_run_is_refused(tmp_path):
    _earlier_run(tmp_path / "out")
    with pytest.raises(DataError, match=r"holds an earlier run's results.*--overwrite"):
        make_results_dir(tmp_path / "out")
    assert (tmp_path / "out" / "b_fused_tum.txt").is_file()


def test_overwrite_removes_only_the_earlier_runs_files(tmp_path):
    _earlier_run(tmp_path / "out")
    with claimed_results_dir(tmp_path / "out", overwrite=True):
        pass
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["notes.md"]
    assert run_output_files(tmp_path / "out") == []


def test_a_folder_with_only_other_files_is_used_and_they_are_kept(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "server.0.log").write_text("x")  # e.g. logs a launcher writes before the server starts
    make_results_dir(tmp_path / "out")
    assert (tmp_path / "out" / "server.0.log").read_text() == "x"


def test_a_file_is_not_a_results_folder(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(DataError, match="is a file"):
        make_results_dir(tmp_path / "f", overwrite=True)


def test_a_server_journal_resumes_the_folder_and_overwrite_starts_fresh(tmp_path):
    _earlier_run(tmp_path / "out")
    (tmp_path / "out" / "journal.bin").write_bytes(b"j")
    (tmp_path / "out" / "snapshot-000000120.bin").write_bytes(b"s")
    with claimed_results_dir(tmp_path / "out", resume_file="journal.bin"):  # a restart keeps everything
        assert (tmp_path / "out" / "journal.bin").is_file() and (tmp_path / "out" / "metrics.json").is_file()
        assert (tmp_path / "out" / "snapshot-000000120.bin").is_file()
    make_results_dir(tmp_path / "out", overwrite=True, resume_file="journal.bin")
    assert not (tmp_path / "out" / "journal.bin").exists()
    assert not (tmp_path / "out" / "snapshot-000000120.bin").exists()


def test_a_server_that_stopped_before_any_robot_is_resumed(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "config.yaml").write_text("x")
    (tmp_path / "out" / "server.rrd").write_bytes(b"x")
    with claimed_results_dir(tmp_path / "out", resume_file="journal.bin"):
        pass
    with pytest.raises(DataError, match="earlier run"):
        make_results_dir(tmp_path / "out")  # but run does not mix into it


def test_run_cli_refuses_a_reused_out_with_exit_2(tmp_path, tiny_scenario):
    _earlier_run(tmp_path / "out")
    args = ["run", "--robot", f"car1={tiny_scenario / 'car1'}", "--rerun", "off", "--out", str(tmp_path / "out")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--overwrite" in res.output, res.output
    assert (tmp_path / "out" / "b_fused_tum.txt").read_text() == "old\n"


_HOLD = """
import sys
from pathlib import Path
from shgm_slam.io.export import make_results_dir
make_results_dir(Path(sys.argv[1]))
print("held", flush=True)
sys.stdin.read()
"""


def test_a_folder_another_process_writes_is_refused_then_free_again(tmp_path):
    """Two servers (or runs) on one --out mixed their files and journals; the second is now refused."""
    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(DataError, match=rf"in use by another shgm-slam process \(pid {holder.pid}\)"):
            make_results_dir(out, overwrite=True)
        res = CliRunner().invoke(app, ["server", "--out", str(out), "--rerun", "off"])
        assert res.exit_code == 2 and "in use by" in " ".join(res.output.split()), res.output
    finally:
        holder.communicate("")
    with claimed_results_dir(out) as path:  # the holder ended: its lock went with it
        assert (path / LOCK_FILE).is_file()
    assert not (out / LOCK_FILE).exists()


def test_a_folder_a_run_of_this_process_writes_is_refused_too(tmp_path):
    """Two runs of one process on one folder (two ``LiveRun``s, a script's threads) were both let in, the second
    with ``overwrite`` removing the first's files while it wrote: their files mixed."""
    with claimed_results_dir(tmp_path / "out"):
        for overwrite in (False, True):
            with pytest.raises(DataError, match="in use by a run of this process that has not finished"):
                make_results_dir(tmp_path / "out", overwrite=overwrite)
        assert (tmp_path / "out" / LOCK_FILE).is_file()  # the refusal left the first run's lock alone
    with claimed_results_dir(tmp_path / "out") as again:  # free again once it finished
        assert again == tmp_path / "out"


def test_a_robots_out_is_checked_before_its_first_frame(tmp_path, tiny_scenario):
    """`robot --out` on an unwritable folder ran every frame and only then failed."""
    from shgm_slam.config import ShgmConfig
    from shgm_slam.data import open_sequence
    from shgm_slam.io.export import check_writable_dir
    from shgm_slam.robot.drive import drive_robot

    assert check_writable_dir(tmp_path / "a" / "b").is_dir() and not list((tmp_path / "a" / "b").iterdir())
    (tmp_path / "f").write_text("x")
    with pytest.raises(DataError, match="is a file"):
        drive_robot("car1", open_sequence(tiny_scenario / "car1"), ShgmConfig(), out_dir=tmp_path / "f")
    with pytest.raises(DataError, match="cannot write into"):
        check_writable_dir(tmp_path / "f" / "sub")


def test_a_sequence_folder_is_never_a_results_folder(tmp_path) -> None:
    """`run --out` into another sequence's folder (not one of the run's robots) wrote results among its files."""
    seq = tmp_path / "car2"
    seq.mkdir()
    (seq / "calib.txt").write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (seq / "times.txt").write_text("0.0\n")
    for overwrite in (False, True):
        with pytest.raises(DataError, match="holds a sequence"):
            make_results_dir(seq, overwrite=overwrite)
    assert sorted(p.name for p in seq.iterdir()) == ["calib.txt", "times.txt"]  # no lock left behind


@pytest.mark.parametrize("name", ["metrics.json", "car2_fused_tum.txt"])
def test_a_folder_where_a_results_file_goes_is_refused_before_the_run(tmp_path, name):
    """A folder named like a results file (``metrics.json/``) let the run go on to its end (or first checkpoint)
    and then fail with "cannot write ... Is a directory", every result lost, ``--overwrite`` no help."""
    (tmp_path / "out" / name).mkdir(parents=True)
    for overwrite in (False, True):
        with pytest.raises(DataError, match=rf"holds a folder named {name}, where a run writes that file"):
            make_results_dir(tmp_path / "out", overwrite=overwrite)
    assert [p.name for p in (tmp_path / "out").iterdir()] == [name]  # the user's folder kept, no lock left


def test_runs_without_out_in_the_same_second_get_folders_of_their_own(tmp_path, monkeypatch):
    """Two runs without --out in one second (two ``LiveRun``s of a script, a run after a short one) wrote into
    one ``results/<time>`` folder, the second's files mixed into the first's, unchecked."""
    from datetime import datetime

    from shgm_slam.io import export

    class Frozen(datetime):
        @classmethod
        def now(cls, tz=None):
            return datetime(2026, 1, 2, 3, 4, 5)

    monkeypatch.setattr(export, "datetime", Frozen)
    first, second = make_results_dir(None, tmp_path), make_results_dir(None, tmp_path)
    assert (first.name, second.name) == ("20260102_030405", "20260102_030405_2")
    assert (tmp_path / "latest").resolve() == second.resolve()


def test_a_latest_that_is_a_folder_is_a_warning(tmp_path, caplog):
    (tmp_path / "latest").mkdir()
    with caplog.at_level("WARNING"):
        path = make_results_dir(None, tmp_path)
    assert path.is_dir() and "cannot point" in caplog.text and (tmp_path / "latest").is_dir()
    assert not list(tmp_path.glob(".latest.*"))
