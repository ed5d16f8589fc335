"""``shgm-slam eval`` / ``evaluate`` fed imperfect inputs: each says what is wrong (one line, exit 2) or why a robot
has no number, never a traceback or an ATE over a few poses of a damaged file.

The results folder is made by hand from a small simulated world (as in ``test_evaluation``): fused trajectories are
the ground truth in the shared frame shifted by ``OFFSET_M``, so the expected ATE is known.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import shgm_slam
from shgm_slam.cli import app
from shgm_slam.data import open_sequence
from shgm_slam.errors import DataError
from shgm_slam.evaluation import evaluate_results
from shgm_slam.geometry import se3
from shgm_slam.io.export import ResultsWriter
from shgm_slam.io.trajectories import read_kitti_poses, read_tum
from shgm_slam.shared_frame import shared_frame_ground_truth

OFFSET_M = np.array([0.0, 0.3, 0.4])  # every fused pose 0.5 m off


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from shgm_slam.sim.simulate import simulate

    out = tmp_path_factory.mktemp("eval_inputs_world")
    simulate("airsim-like", out, resolution=(320, 96), fps=4.0, compact=True, max_frames=12)
    return out


def _results(world: Path, out: Path) -> dict:
    """A finished run's folder for car1 and car2 (12 frames each): fused and ground-truth files, metrics.json."""
    robots = {"car1": open_sequence(world / "car1"), "car2": open_sequence(world / "car2")}
    writer = ResultsWriter(out)
    for r, T_shared_cam in shared_frame_ground_truth(robots).items():
        fused = T_shared_cam.copy()
        fused[:, :3, 3] += OFFSET_M
        writer.write_trajectories(r, robots[r].timestamps_s, se3.inverse(fused[0]) @ fused, fused)
    writer.write_ground_truth(robots)
    writer.write_json("metrics.json", {"robots": [{"name": r, "frames": len(s), "fused_poses": len(s)}
                                                  for r, s in robots.items()]})  # fmt: skip
    return robots


def _eval(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["eval", *args], env={"COLUMNS": "200"})
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception  # no traceback
    return res.exit_code, " ".join(res.output.split())


def _cut(path: Path, rows: int) -> None:
    """Keep the first ``rows`` data rows of a TUM file (a file cut short, or emptied)."""
    lines = [line for line in path.read_text().splitlines(keepends=True) if not line.startswith("#")]
    path.write_text("".join(lines[:rows]))


@pytest.mark.parametrize("robot, rows", [("car1", 3), ("car2", 0)])
def test_a_ground_truth_file_cut_after_the_run_is_refused(world, tmp_path, robot, rows):
    """A <robot>_gt_tum.txt cut to 3 rows gave car1's ATE over those 3 of its 12 poses (exit 0); an emptied one,
    a note only. The run writes one ground-truth row per frame (metrics.json's frames)."""
    _results(world, tmp_path)
    assert evaluate_results(tmp_path).robots[0].evaluated_poses == 12  # as written: fine
    _cut(tmp_path / f"{robot}_gt_tum.txt", rows)
    with pytest.raises(DataError, match=rf"{robot}_gt_tum\.txt holds {rows} poses but the run had 12 frames"):
        evaluate_results(tmp_path)
    code, out = _eval(str(tmp_path))
    assert code == 2 and f"eval --gt {robot}=PATH" in out and "ATE" not in out


def test_a_ground_truth_file_that_is_a_folder_is_refused(world, tmp_path):
    """A folder named car2_gt_tum.txt was taken for "no ground truth given"."""
    _results(world, tmp_path)
    (tmp_path / "car2_gt_tum.txt").unlink()
    (tmp_path / "car2_gt_tum.txt").mkdir()
    with pytest.raises(DataError, match=r"car2_gt_tum\.txt is a directory, not a file"):
        evaluate_results(tmp_path)


def test_the_note_says_why_a_robot_has_no_ground_truth(world, tmp_path):
    """Every robot without ground truth was "no ground truth given", also when the results folder lacked its file
    (nothing is given there) or its sequence, given, had no poses."""
    robots = _results(world, tmp_path)
    (tmp_path / "car2_gt_tum.txt").unlink()
    notes = {r.name: r.note for r in evaluate_results(tmp_path).robots}
    assert "car2_gt_tum.txt is not in the results folder" in notes["car2"]
    car2 = shgm_slam.ArraySequence(np.zeros((12, 96, 320, 3), np.uint8), robots["car2"].intrinsics,
                                   robots["car2"].timestamps_s)  # fmt: skip
    notes = {r.name: r.note for r in evaluate_results(tmp_path, {"car1": robots["car1"], "car2": car2}).robots}
    assert notes["car2"] == "no ground truth: its sequence has none"
    assert {r.name: r.note for r in evaluate_results(tmp_path, {"car1": robots["car1"]}).robots}["car2"] == (
        "no ground truth given"
    )


class _OwnSequence:
    """A sequence class of the user's own (the ``Sequence`` protocol, no checks of its own) around ``base``."""

    def __init__(self, base, gt_poses=None, timestamps_s=None) -> None:
        self.base, self.name, self.intrinsics = base, base.name, base.intrinsics
        self._gt = base.gt_poses if gt_poses is None else gt_poses
        self._t = base.timestamps_s if timestamps_s is None else timestamps_s
        self.has_depth = self.has_labels = True

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int):
        return self.base[index]

    @property
    def timestamps_s(self) -> np.ndarray:
        return self._t

    @property
    def gt_poses(self) -> np.ndarray | None:
        return self._gt


def _flat(g):
    return g.reshape(len(g), 16)


def _millimetres(g):
    g = g.copy()
    g[:, :3, 3] *= 1000.0
    return g


def _nan(g):
    g = g.copy()
    g[5, 0, 3] = np.nan
    return g


@pytest.mark.parametrize("gt, says", [
    (_flat, r"gt_poses has shape \(12, 16\); give \(12, 4, 4\)"),  # an IndexError before
    (_millimetres, "moves at .* m/s between frames"),  # an ATE of kilometres before
    (lambda g: g[:8], r"gt_poses has shape \(8, 4, 4\)"),  # "cannot write .../.car1_gt_tum.txt.x8y7z6" before
    (_nan, "gt_poses of frame 5 is not finite"),  # the same temporary file before
    (lambda g: np.zeros_like(g), "not a rigid transform"),  # an ATE of tens of metres before
])  # fmt: skip
def test_a_sequence_of_ones_own_with_malformed_ground_truth_is_refused(world, tmp_path, gt, says):
    robots = _results(world, tmp_path)
    for path in tmp_path.glob("*_gt_*.txt"):  # nothing written to compare with: the sequence itself is checked
        path.unlink()
    own = _OwnSequence(robots["car1"], gt_poses=gt(np.array(robots["car1"].gt_poses)))
    with pytest.raises(DataError, match=says):
        shgm_slam.evaluate(tmp_path, {"car1": own, "car2": robots["car2"]})
    assert not (tmp_path / "car1_gt_tum.txt").exists()


def test_a_sequence_of_ones_own_with_other_timestamps_is_refused(world, tmp_path):
    robots = _results(world, tmp_path)
    times = np.array(robots["car1"].timestamps_s)
    for bad in (times[:8], np.r_[times[:-1], np.nan]):
        with pytest.raises(DataError, match="are not 12 finite, increasing times in seconds"):
            evaluate_results(tmp_path, {"car1": _OwnSequence(robots["car1"], timestamps_s=bad)})


def test_gt_given_a_poses_file_says_it_needs_the_sequence_folder(world, tmp_path):
    """``--gt car1=.../poses.txt`` said "sequence folder .../poses.txt does not exist" of a file that exists."""
    _results(world, tmp_path)
    for spec in (f"{world / 'car1' / 'poses.txt'}", f"{world / 'car1' / 'poses.txt'}:0-5"):
        code, out = _eval(str(tmp_path), "--gt", f"car1={spec}")
        assert code == 2 and "is a file; give the robot's sequence folder" in out and "--gt" in out


def test_a_binary_pose_file_is_said_to_be_no_text(tmp_path):
    """Python's "'utf-8' codec can't decode byte 0x89 in position 0" named neither the problem nor the fix."""
    path = tmp_path / "car1_gt_tum.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    for read in (read_tum, read_kitti_poses):
        with pytest.raises(DataError, match=r"car1_gt_tum\.txt is not UTF-8 text \(byte 0\): a binary file"):
            read(path)


def test_eval_of_an_empty_path_is_refused(world, tmp_path, monkeypatch):
    """``eval "$DIR"`` with DIR unset evaluated the current folder, whatever results it held."""
    _results(world, tmp_path)
    monkeypatch.chdir(tmp_path)
    assert _eval(".")[0] == 0
    code, out = _eval("")
    assert code == 2 and "is empty" in out
