"""``evaluate_results`` / ``shgm-slam eval`` and the ground truth written in the shared frame.

A results folder is made by hand from a simulated scenario: fused trajectories = the ground truth in
the shared frame plus a known error, so the expected ATE is known without running the system.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.data import open_sequence
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.evaluation import associate, evaluate_results, open_ground_truth, run_robot_order
from shgm_slam.geometry import se3
from shgm_slam.io.export import ResultsWriter
from shgm_slam.io.trajectories import read_kitti_poses, read_tum, write_tum
from shgm_slam.metrics import ate
from shgm_slam.shared_frame import shared_frame_ground_truth

OFFSET_M = np.array([0.3, 0.0, 0.4])  # car2's fused error: a constant 0.5 m shift


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from shgm_slam.sim.simulate import simulate

    out = tmp_path_factory.mktemp("eval_world")
    simulate("airsim-like", out, resolution=(320, 96), fps=4.0, compact=True, max_frames=12)
    return out


def _results(world: Path, out: Path, *, place_car2: bool = True) -> dict:
    """A results folder whose fused car1 is exact and car2 is off by OFFSET_M (car2's frames 3-11 only)."""
    robots = {"car1": open_sequence(world / "car1"), "car2": open_sequence(f"{world / 'car2'}:3-")}
    gt = shared_frame_ground_truth(robots)
    writer = ResultsWriter(out)
    for r, seq in robots.items():
        fused = gt[r].copy()
        if r == "car2":
            fused[:, :3, 3] += OFFSET_M
        odo = se3.inverse(fused[0]) @ fused
        writer.write_trajectories(r, seq.timestamps_s, odo, fused if (r == "car1" or place_car2) else None)
    writer.write_json("metrics.json", {"robots": [{"name": r, "frames": len(seq)} for r, seq in robots.items()]})
    return robots


def test_shared_frame_is_the_first_robots_first_camera(world):
    robots = {"car2": open_sequence(world / "car2"), "car1": open_sequence(world / "car1")}
    gt = shared_frame_ground_truth(robots)
    np.testing.assert_allclose(gt["car2"][0], np.eye(4), atol=1e-9)
    raw = robots["car1"].gt_poses
    np.testing.assert_allclose(gt["car1"], se3.inverse(robots["car2"].gt_poses[0]) @ raw, atol=1e-9)
    assert list(shared_frame_ground_truth(robots, gt_shared_frame=False)) == ["car2"]


def test_eval_from_sequences_writes_gt_files_that_evo_reads(world, tmp_path):
    robots = _results(world, tmp_path)
    result = evaluate_results(tmp_path, robots)
    rows = {r.name: r for r in result.robots}
    assert result.reference_robot == "car1" and result.gt_source == "sequences"
    assert rows["car1"].ate_fused_m < 1e-6 and rows["car1"].evaluated_poses == 12
    assert rows["car2"].ate_fused_m == pytest.approx(0.5, abs=1e-6) and rows["car2"].evaluated_poses == 9
    assert rows["car2"].ate_fused_aligned_m < 1e-6  # a pure shift: nothing left after alignment
    # one fit of both: car2's shift relative to car1 is shared out between them, never hidden
    assert result.joint_robots == 2 and 0.1 < rows["car2"].ate_fused_joint_m < 0.5
    assert 0.0 < rows["car1"].ate_fused_joint_m < 0.5 and 0.0 < result.ate_joint_m < 0.5
    assert result.to_json_dict()["ate_joint_m"] == pytest.approx(result.ate_joint_m)
    t_gt, gt = read_tum(tmp_path / "car2_gt_tum.txt")
    t_fused, fused = read_tum(tmp_path / "car2_fused_tum.txt")
    np.testing.assert_allclose(t_gt, t_fused)  # same instants: evo associates them one to one
    assert ate(gt, fused, align="none").rmse == pytest.approx(0.5, abs=1e-6)
    assert read_kitti_poses(tmp_path / "car2_gt_kitti.txt").shape == (9, 4, 4)
    # the world-frame poses.txt is NOT comparable (the newcomer's 975 m): the shared frame is needed
    raw = open_sequence(world / "car1").gt_poses
    assert ate(raw, read_tum(tmp_path / "car1_fused_tum.txt")[1], align="none").rmse > 5.0
    # and the folder alone now evaluates the same
    again = {r.name: r for r in evaluate_results(tmp_path).robots}
    assert again["car2"].ate_fused_m == pytest.approx(0.5, abs=1e-6)


def test_unplaced_robot_and_errors(world, tmp_path):
    robots = _results(world, tmp_path, place_car2=False)
    with pytest.raises(DataError, match="no <robot>_gt_tum"):
        evaluate_results(tmp_path)
    rows = {r.name: r for r in evaluate_results(tmp_path, robots).robots}
    assert not rows["car2"].localized and "not placed" in rows["car2"].note
    with pytest.raises(DataError, match="must include car1"):
        evaluate_results(tmp_path, {"car2": robots["car2"]})
    with pytest.raises(DataError, match="not in"):
        evaluate_results(tmp_path, {**robots, "bus": robots["car1"]})
    with pytest.raises(DataError, match="does not exist"):
        evaluate_results(tmp_path / "nope")
    with pytest.raises(DataError, match="is a file, not a folder"):
        evaluate_results(tmp_path / "metrics.json")
    with pytest.raises(ConfigError, match="NAME=PATH"):
        open_ground_truth(["just/a/path"])


def test_ground_truth_with_another_frame_count_than_the_run_is_refused(world, tmp_path):
    robots = _results(world, tmp_path)
    short = {**robots, "car1": open_sequence(f"{world / 'car1'}:0-5")}  # a wrong range still associates 5 poses
    with pytest.raises(DataError, match=r"given for car1 .*: its sequence has 5 frames but the run had 12"):
        evaluate_results(tmp_path, short)
    assert not (tmp_path / "car1_gt_tum.txt").exists()  # nothing written from the wrong sequence
    res = CliRunner().invoke(app, ["eval", str(tmp_path), "--gt", f"car1={world / 'car1'}", "--gt",
                                   f"car2={world / 'car2'}:2-"])  # fmt: skip
    assert res.exit_code == 2 and "has 10 frames but the run had 9 for car2" in " ".join(res.output.split())
    shifted = {**robots, "car2": open_sequence(f"{world / 'car2'}:0-9")}  # the run's count, another range
    with pytest.raises(DataError, match=r"given for car2 .*: the run.s frame times .* are not this sequence.s"):
        evaluate_results(tmp_path, shifted)
    assert not (tmp_path / "car1_gt_tum.txt").exists()


def test_a_fused_trajectory_that_is_a_directory_is_not_taken_for_an_unplaced_robot(world, tmp_path):
    robots = _results(world, tmp_path)
    (tmp_path / "car2_fused_tum.txt").unlink()
    (tmp_path / "car2_fused_tum.txt").mkdir()
    with pytest.raises(DataError, match=r"car2_fused_tum\.txt is not a file"):
        evaluate_results(tmp_path, robots)


def test_a_fused_trajectory_cut_or_deleted_after_the_run_is_refused(world, tmp_path):
    """A truncated file evaluated as "3/3 poses" with an ATE; a deleted one as "not placed"."""
    robots = _results(world, tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for r in metrics["robots"]:
        r["fused_poses"] = len(read_tum(tmp_path / f"{r['name']}_fused_tum.txt")[0])
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    assert len(evaluate_results(tmp_path, robots).robots) == 2  # as written: fine
    lines = (tmp_path / "car2_fused_tum.txt").read_text().splitlines(keepends=True)
    (tmp_path / "car2_fused_tum.txt").write_text("".join(lines[:-3]))
    with pytest.raises(DataError, match=r"car2_fused_tum\.txt holds 6 poses but the run wrote 9"):
        evaluate_results(tmp_path)
    (tmp_path / "car2_fused_tum.txt").unlink()
    with pytest.raises(DataError, match="holds 0 poses but the run wrote 9"):
        evaluate_results(tmp_path, robots)


def test_associate_by_nearest_time():
    est, gt = associate(np.array([0.1, 0.2, 0.35, 0.5]), np.array([0.5, 0.2, 0.1]))
    assert est.tolist() == [0, 1, 3] and gt.tolist() == [2, 1, 0]


def test_cli_eval(world, tmp_path):
    _results(world, tmp_path)
    args = ["eval", str(tmp_path), "--gt", f"car1={world / 'car1'}", "--gt", f"car2={world / 'car2'}:3-"]
    res = CliRunner().invoke(app, [*args, "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output)
    assert [r["name"] for r in data["robots"]] == ["car1", "car2"]
    assert data["robots"][1]["ate_fused_m"] == pytest.approx(0.5, abs=1e-6)
    res = CliRunner().invoke(app, ["eval", str(tmp_path)], env={"COLUMNS": "80"})
    assert res.exit_code == 0 and "0.50" in res.output and "car2" in res.output
    res = CliRunner().invoke(app, ["eval", str(tmp_path / "missing")])
    assert res.exit_code == 2


def test_without_a_shared_ground_truth_frame_only_aligned_errors(world, tmp_path):
    robots = _results(world, tmp_path)
    rows = {r.name: r for r in evaluate_results(tmp_path, robots, gt_shared_frame=False).robots}
    assert rows["car1"].ate_fused_m < 1e-6
    assert np.isnan(rows["car2"].ate_fused_m) and rows["car2"].ate_fused_aligned_m < 1e-6
    assert "aligned only" in rows["car2"].note
    assert not (tmp_path / "car2_gt_tum.txt").exists() and (tmp_path / "car1_gt_tum.txt").is_file()


def test_cli_run_writes_ground_truth_that_eval_and_evo_read(world, tmp_path):
    out = tmp_path / "run"
    args = ["run", "--robot", f"car1={world / 'car1'}", "--robot", f"car2={world / 'car2'}:2-", "--rerun", "off",
            "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args, env={"COLUMNS": "80"})
    assert res.exit_code == 0, res.output
    assert (out / "car1_gt_tum.txt").is_file() and (out / "car2_gt_tum.txt").is_file()
    metrics = {r["name"]: r for r in json.loads((out / "metrics.json").read_text())["robots"]}
    for name in ("car1", "car2"):  # what eval checks the files against
        fused = out / f"{name}_fused_tum.txt"
        assert metrics[name]["fused_poses"] == (len(read_tum(fused)[0]) if fused.exists() else 0)
    rows = {r.name: r for r in evaluate_results(out).robots}
    assert rows["car1"].ate_fused_m == pytest.approx(metrics["car1"]["ate_fused_m"], abs=1e-6)
    if metrics["car2"]["localized"]:
        assert rows["car2"].ate_fused_m == pytest.approx(metrics["car2"]["ate_fused_m"], abs=1e-6)
        # the joint fit of the run's summary and of eval agree (the same poses, read back from the files)
        for name in ("car1", "car2"):
            assert rows[name].ate_fused_joint_m == pytest.approx(metrics[name]["ate_fused_joint_m"], abs=1e-5)


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ('{"robots": [{"nam": "car1"}]}', "has no list of robots with their names"),
        ('{"robots": ["car1"]}', "has no list of robots"),
        ("[1, 2]", "has no list of robots"),
        ('{"robots": [', "is not valid JSON"),
    ],
)
def test_a_damaged_metrics_file_is_said_in_our_words(world, tmp_path, text, says):
    """Python's own text leaked before: "unreadable ('name')", "list indices must be integers"."""
    _results(world, tmp_path)
    (tmp_path / "metrics.json").write_text(text)
    with pytest.raises(DataError, match=says):
        evaluate_results(tmp_path)


def test_ground_truth_of_another_sequence_does_not_replace_the_runs(world, tmp_path):
    """Another sequence with the run's frame count and times passed every check and overwrote the right
    car2_gt_tum.txt; every later `eval` then measured against it."""
    robots = _results(world, tmp_path)
    evaluate_results(tmp_path, robots)  # writes the right ground truth, as `run` does
    right = (tmp_path / "car2_gt_tum.txt").read_bytes()
    other = {**robots, "car2": open_sequence(f"{world / 'uav'}:3-")}  # the same times, another drive
    with pytest.raises(DataError, match=r"given for car2 .*: its ground truth differs from .*car2_gt_tum\.txt"):
        evaluate_results(tmp_path, other)
    assert (tmp_path / "car2_gt_tum.txt").read_bytes() == right
    evaluate_results(tmp_path, robots)  # the same sequences again: fine


def test_eval_that_measures_nothing_fails(world, tmp_path):
    """A ground truth at other times than the fused poses left every robot without an ATE, and `eval` said
    nothing was wrong (exit 0): a script would have read it as a result."""
    _results(world, tmp_path)
    for name in ("car1", "car2"):
        times, fused = read_tum(tmp_path / f"{name}_fused_tum.txt")
        write_tum(tmp_path / f"{name}_gt_tum.txt", times + 1000.0, fused)
    for extra in ([], ["--json"]):
        res = CliRunner().invoke(app, ["eval", str(tmp_path), *extra], env={"COLUMNS": "120"})
        assert res.exit_code == 2
        assert "no ATE was measured" in " ".join(res.output.split())


_HOLD = """
import sys
from pathlib import Path
from shgm_slam.io.export import _lock_results_dir
_lock_results_dir(Path(sys.argv[1]))  # as a run writing the folder holds it
print("held", flush=True)
sys.stdin.read()
"""


def test_a_checkpoint_of_a_run_that_never_finished_is_refused(world, tmp_path):
    """A run killed mid-run (SIGKILL, out of memory: nothing can mark the folder) left its last checkpoint, no
    metrics.json and no incomplete.txt, and ``eval`` printed its ATE as the run's; so did ``eval`` on a folder
    a run was still writing."""
    import subprocess
    import sys

    from shgm_slam.api import read_fused

    robots = _results(world, tmp_path)
    (tmp_path / "metrics.json").unlink()
    (tmp_path / "server.json").write_text(json.dumps({"reference": "car1", "finished": False}))
    for read in (lambda: evaluate_results(tmp_path), lambda: evaluate_results(tmp_path, robots),
                 lambda: read_fused(tmp_path, "car1")):  # fmt: skip
        with pytest.raises(DataError, match=r"its run never finished .* checkpoint; run it again with --overwrite"):
            read()
    (tmp_path / "journal.bin").write_bytes(b"j")  # a map server's folder: it resumes
    with pytest.raises(DataError, match="start the map server on this folder again"):
        evaluate_results(tmp_path)
    (tmp_path / "server.json").write_text(json.dumps({"reference": "car1", "finished": True}))
    assert len(evaluate_results(tmp_path, robots).robots) == 2  # a server that finished writes no metrics.json
    (tmp_path / "journal.bin").unlink()  # a run's folder whose metrics.json is gone: its rows cannot be checked
    with pytest.raises(DataError, match=r"has no metrics\.json, the last file a run writes"):
        evaluate_results(tmp_path, robots)
    (tmp_path / "journal.bin").write_bytes(b"j")
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(DataError, match=rf"being written by another shgm-slam process \(pid {holder.pid}\)"):
            evaluate_results(tmp_path)
    finally:
        holder.communicate("")
    assert len(evaluate_results(tmp_path, robots).robots) == 2


def test_a_map_servers_folder_is_evaluated_in_its_reference_robots_frame(world, tmp_path):
    """A map server's folder has no metrics.json; its robots were taken by name, so a server whose reference
    (``--reference car2``, or the first robot to connect) was not first by name had the ground truth moved into
    car1's frame: car2, the reference itself, 84 m off, and those files written for evo."""
    robots = {"car2": open_sequence(f"{world / 'car2'}:3-"), "car1": open_sequence(world / "car1")}
    gt = shared_frame_ground_truth(robots)  # car2's first camera: the server's shared frame
    writer = ResultsWriter(tmp_path)
    for r, seq in robots.items():
        writer.write_trajectories(r, seq.timestamps_s, se3.inverse(gt[r][0]) @ gt[r], gt[r])
    (tmp_path / "server.json").write_text(json.dumps({"reference": "car2", "finished": True}))
    (tmp_path / "journal.bin").write_bytes(b"")
    for result in (evaluate_results(tmp_path, dict(reversed(robots.items()))), evaluate_results(tmp_path)):
        assert result.reference_robot == "car2" and [r.name for r in result.robots] == ["car2", "car1"]
        assert all(r.ate_fused_m < 1e-6 for r in result.robots)
    _, truth = read_tum(tmp_path / "car1_gt_tum.txt")
    np.testing.assert_allclose(truth[:, :3, 3], gt["car1"][:, :3, 3], atol=1e-6)  # what evo_ape compares with
    (tmp_path / "server.json").write_text(json.dumps({"reference": "../car2", "finished": True}))
    assert run_robot_order(tmp_path) == ["car1", "car2"]  # a reference that is no robot name names no file


def test_a_robot_with_a_trajectory_segment_not_placed_is_said_so(world, tmp_path):
    """A robot whose second trajectory segment was never placed has a fused file of its first segment's frames
    only (``metrics.json``: localized false, 1 of 2 segments placed); ``eval`` showed it as "9/9" poses with no
    word that its later frames are missing."""
    robots = _results(world, tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for r in metrics["robots"]:
        r.update(segments=2 if r["name"] == "car2" else 1, segments_placed=1)
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    rows = {r.name: r.note for r in evaluate_results(tmp_path, robots).robots}
    assert "1 of its 2 trajectory segments placed" in rows["car2"] and rows["car1"] == ""
