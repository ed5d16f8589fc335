"""Results folder: valid JSON (no NaN), normal file modes, atomic writes that keep the last good file."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from shgm_slam.errors import DataError
from shgm_slam.io import export
from shgm_slam.io.export import ResultsWriter, finite_or_none


def test_metrics_with_nan_are_valid_json(tmp_path):
    w = ResultsWriter(tmp_path)
    w.write_json("metrics.json", {"ate": float("nan"), "x": [1.0, float("inf"), np.float32("nan")], "n": np.int64(3)})
    text = (tmp_path / "metrics.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert data == {"ate": None, "x": [1.0, None, None], "n": 3}
    assert finite_or_none({"a": (1.5, float("-inf"))}) == {"a": [1.5, None]}


def test_results_files_get_normal_modes(tmp_path):
    w = ResultsWriter(tmp_path)
    w.write_text("config.yaml", "a: 1\n")
    t = np.arange(3.0)
    w.write_trajectories("car", t, np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)))
    umask = os.umask(0)
    os.umask(umask)
    for name in ("config.yaml", "car_odometry_tum.txt", "car_fused_tum.txt", "car_fused_kitti.txt"):
        mode = stat.S_IMODE((tmp_path / name).stat().st_mode)
        assert mode == 0o666 & ~umask, (name, oct(mode))


def test_a_failed_write_keeps_the_previous_file_and_says_why(tmp_path, monkeypatch):
    w = ResultsWriter(tmp_path)
    t = np.arange(3.0)
    poses = np.tile(np.eye(4), (3, 1, 1))
    w.write_trajectories("car", t, poses, None)
    before = (tmp_path / "car_odometry_tum.txt").read_text()

    def disk_full(path, *_args):
        path.write_text("half a li")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "write_tum", disk_full)
    with pytest.raises(DataError, match="No space left"):
        w.write_trajectories("car", t, poses + 1.0, None)
    assert (tmp_path / "car_odometry_tum.txt").read_text() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left behind
