"""Results folder: valid JSON (no NaN), normal file modes, atomic writes that keep the last good file."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.errors import DataError
from shgm_slam.io import export
from shgm_slam.io.export import ResultsWriter
from shgm_slam.io.json_text import finite_or_none


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


def test_ground_truth_is_written_in_the_shared_frame(tmp_path):
    from types import SimpleNamespace

    from shgm_slam.geometry import se3
    from shgm_slam.io.trajectories import read_kitti_poses, read_tum

    def poses(x0):
        T = np.tile(np.eye(4), (4, 1, 1))
        T[:, 0, 3] = x0 + np.arange(4.0)
        return T

    robots = {
        "a": SimpleNamespace(gt_poses=poses(100.0), timestamps_s=np.arange(4.0)),
        "b": SimpleNamespace(gt_poses=poses(200.0), timestamps_s=10 + np.arange(4.0)),
        "c": SimpleNamespace(gt_poses=None, timestamps_s=np.arange(4.0)),
    }
    written = ResultsWriter(tmp_path).write_ground_truth(robots)
    assert sorted(p.name for p in written) == ["a_gt_kitti.txt", "a_gt_tum.txt", "b_gt_kitti.txt", "b_gt_tum.txt"]
    t, T_b = read_tum(tmp_path / "b_gt_tum.txt")
    np.testing.assert_allclose(t, 10 + np.arange(4.0))
    np.testing.assert_allclose(T_b, se3.inverse(poses(100.0)[0]) @ poses(200.0), atol=1e-9)  # a's first camera
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "a_gt_kitti.txt")[0], np.eye(4), atol=1e-9)
    assert stat.S_IMODE(os.stat(tmp_path / "a_gt_tum.txt").st_mode) == export._FILE_MODE
    other = tmp_path / "own_frames"
    assert [p.name for p in ResultsWriter(other).write_ground_truth(robots, gt_shared_frame=False)] == [
        "a_gt_tum.txt", "a_gt_kitti.txt"]
    assert ResultsWriter(tmp_path / "none").write_ground_truth({"c": robots["c"]}) == []


def _fused_lines(path):
    return path.read_text().splitlines()


def test_provisional_fused_files_say_so_and_evo_still_reads_them(tmp_path):
    from evo.tools import file_interface

    w = ResultsWriter(tmp_path)
    t, poses = np.arange(3.0), np.tile(np.eye(4), (3, 1, 1))
    w.write_trajectories("car", t, poses, poses, provisional="car rests on a single graph match")
    assert _fused_lines(tmp_path / "car_fused_tum.txt")[0] == "# provisional: car rests on a single graph match"
    assert not any(line.startswith("#") for line in _fused_lines(tmp_path / "car_fused_kitti.txt"))  # devkit rows
    assert len(file_interface.read_tum_trajectory_file(str(tmp_path / "car_fused_tum.txt")).poses_se3) == 3
    assert not any(line.startswith("#") for line in _fused_lines(tmp_path / "car_odometry_tum.txt"))
    w.write_trajectories("car", t, poses, poses)  # confirmed later: the mark goes
    assert not any(line.startswith("#") for line in _fused_lines(tmp_path / "car_fused_tum.txt"))


def test_a_robot_no_longer_placed_loses_its_fused_files(tmp_path):
    w = ResultsWriter(tmp_path)
    t, poses = np.arange(3.0), np.tile(np.eye(4), (3, 1, 1))
    w.write_trajectories("car", t, poses, poses)
    assert (tmp_path / "car_fused_tum.txt").is_file()
    w.write_trajectories("car", t, poses, None)  # its placing closures were outvoted
    assert sorted(p.name for p in tmp_path.iterdir()) == ["car_odometry_tum.txt"]


def _checkpoint(w, value):
    """Three files as one checkpoint."""
    with w.checkpoint():
        for name in ("a.json", "b.json", "c.json"):
            w.write_json(name, {"checkpoint": value})


def test_a_checkpoint_replaces_all_files_or_none(tmp_path, monkeypatch):
    w = ResultsWriter(tmp_path)
    _checkpoint(w, 1)
    real_write_text = type(tmp_path).write_text

    def full_at_c(self, text, *args, **kwargs):
        if self.name.startswith(".c.json."):
            raise OSError(28, "No space left on device")
        return real_write_text(self, text, *args, **kwargs)

    monkeypatch.setattr(type(tmp_path), "write_text", full_at_c)
    with pytest.raises(DataError, match=r"c\.json: No space left on device"):
        _checkpoint(w, 2)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "c.json"]  # no temporaries
    assert {json.loads((tmp_path / n).read_text())["checkpoint"] for n in ("a.json", "b.json", "c.json")} == {1}
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C in the middle of a checkpoint
        with w.checkpoint():
            w.write_json("a.json", {"checkpoint": 3})
            raise KeyboardInterrupt
    assert json.loads((tmp_path / "a.json").read_text())["checkpoint"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "c.json"]
    _checkpoint(w, 4)
    assert {json.loads((tmp_path / n).read_text())["checkpoint"] for n in ("a.json", "b.json", "c.json")} == {4}


@pytest.mark.parametrize("in_checkpoint", [False, True])
@pytest.mark.parametrize("where", ["write", "rename"])
def test_a_stop_signal_mid_write_leaves_no_temporary(tmp_path, monkeypatch, in_checkpoint, where):
    """A stop signal (KeyboardInterrupt) while a file's temporary is written or renamed: the previous file
    stays, and no temporary is left beside it (a signal can land between any two bytecodes)."""
    w = ResultsWriter(tmp_path)
    _checkpoint(w, 1)
    real_write_text, real_replace = type(tmp_path).write_text, os.replace

    def interrupted_write(self, text, *args, **kwargs):
        if self.name.startswith(".b.json."):
            real_write_text(self, text[:5], *args, **kwargs)  # half written
            raise KeyboardInterrupt
        return real_write_text(self, text, *args, **kwargs)

    def interrupted_rename(src, dst, *args, **kwargs):
        if Path(dst).name == "b.json":
            raise KeyboardInterrupt
        return real_replace(src, dst, *args, **kwargs)

    if where == "write":
        monkeypatch.setattr(type(tmp_path), "write_text", interrupted_write)
    else:
        monkeypatch.setattr(os, "replace", interrupted_rename)
    with pytest.raises(KeyboardInterrupt):
        if in_checkpoint:
            _checkpoint(w, 2)
        else:
            w.write_json("b.json", {"checkpoint": 2})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "c.json"]
    assert json.loads((tmp_path / "b.json").read_text())["checkpoint"] == 1


def test_a_shared_graph_goes_when_its_robot_loses_its_place(tmp_path):
    """``shared_graph_<agent>.json`` is written while the agent is placed and removed when a later checkpoint finds
    it unplaced (a withdrawn closure), so the folder never shows a map the run no longer stands by; ``--overwrite``
    counts it among a run's files."""
    from shgm_slam.io.graph_json import read_graph
    from shgm_slam.types import GraphArrays

    graph = GraphArrays(np.array([4, 9]), np.array([5, 8]), np.array([[1.0, 2.0, 0.5], [10.0, 2.0, 0.4]]),
                        np.ones(2), np.zeros((0, 2), dtype=np.int64))  # fmt: skip
    w = ResultsWriter(tmp_path)
    w.write_shared_graph("car2#1", graph)
    written = read_graph(tmp_path / "shared_graph_car2#1.json")
    np.testing.assert_allclose(written.positions_xyz, graph.positions_xyz)
    assert tmp_path / "shared_graph_car2#1.json" in export.run_output_files(tmp_path)
    w.write_shared_graph("car2#1", None)
    assert not (tmp_path / "shared_graph_car2#1.json").exists()


def test_a_trajectory_of_no_frames_writes_empty_files(tmp_path):
    """A robot's done message may carry a trajectory of no frames (decodable); writing it stopped the map server
    with numpy's 'cannot reshape array of size 0'."""
    w = ResultsWriter(tmp_path)
    w.write_trajectories("car", np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    assert (tmp_path / "car_odometry_tum.txt").exists() and (tmp_path / "car_fused_tum.txt").exists()
