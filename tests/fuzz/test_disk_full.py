"""A full disk (ENOSPC) while writing results: a clear error naming the file, the previous version kept,
no temporary file left behind; through the CLI one line and exit 2."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.errors import DataError
from shgm_slam.io import export
from shgm_slam.io.export import ResultsWriter


def _full(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def _half_then_full(path, *_args, **_kwargs):
    Path(path).write_text("1.0 0 0")  # a truncated line, as a real full disk leaves it
    _full()


def test_json_write_on_a_full_disk_keeps_the_previous_file(tmp_path, monkeypatch):
    writer = ResultsWriter(tmp_path)
    writer.write_json("metrics.json", {"run": 1})
    real_write_text = Path.write_text

    def write_text(self, text, *args, **kwargs):
        if self.name.startswith(".metrics.json."):
            real_write_text(self, text[: len(text) // 2])
            _full()
        return real_write_text(self, text, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", write_text)
    with pytest.raises(DataError, match=r"cannot write .*metrics\.json: No space left on device; free space"):
        writer.write_json("metrics.json", {"run": 2})
    assert json.loads((tmp_path / "metrics.json").read_text()) == {"run": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]


def test_trajectory_write_on_a_full_disk_keeps_the_previous_file(tmp_path, monkeypatch):
    writer = ResultsWriter(tmp_path)
    T = np.tile(np.eye(4), (3, 1, 1))
    writer.write_trajectories("car", np.arange(3.0), T, T)
    before = (tmp_path / "car_fused_tum.txt").read_text()
    monkeypatch.setattr(export, "write_tum", _half_then_full)
    with pytest.raises(DataError, match="No space left on device"):
        writer.write_trajectories("car", np.arange(3.0), T * 2, T * 2)
    assert (tmp_path / "car_fused_tum.txt").read_text() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_run_on_a_full_disk_exits_2_with_one_line(tmp_path, monkeypatch, tiny_scenario):
    monkeypatch.setattr(export, "write_tum", _half_then_full)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["run", "--robot", f"car1={tiny_scenario / 'car1'}:0-12", "--rerun", "off",
                                   "--out", str(out)])  # fmt: skip
    assert res.exit_code == 2, (res.output, repr(res.exception))
    assert "No space left on device" in res.output and "Traceback" not in res.output
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no half-written temporaries
