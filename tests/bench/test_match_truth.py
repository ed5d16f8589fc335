"""Accepted matches judged at their own place: a right match under drift is right, an alias is off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.bench.match_truth import judge_matches, match_errors_m
from shgm_slam.errors import DataError
from shgm_slam.geometry import se3
from shgm_slam.graph.semantic_graph import GraphUpdate
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.journal import Journal
from shgm_slam.wire import encode

RNG = np.random.default_rng(7)


def _pose(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    return se3.make_pose(se3.rot_y(yaw), np.asarray(t, dtype=np.float64))


def _world() -> dict[str, np.ndarray]:
    """Ground truth: robot a drives along +z, robot b the same street the other way (camera frames)."""
    a = np.stack([_pose(0.01 * k, (0.2 * k, 0.0, 5.0 * k)) for k in range(20)])
    b = np.stack([_pose(np.pi + 0.01 * k, (3.0, 0.0, 95.0 - 5.0 * k)) for k in range(20)])
    return {"a": a, "b": b}


def test_a_true_match_is_exact_and_a_shifted_one_is_off_by_its_shift():
    gt = _world()
    # each robot's odometry frame is its first camera frame; its odometry is exact here
    T_odom = {r: se3.inverse(p[0])[None] @ p for r, p in gt.items()}
    T_a_b = se3.inverse(gt["a"][0]) @ gt["b"][0]
    ka, kb = np.array([3, 12]), np.array([15, 6])
    args = (T_odom["a"][ka], T_odom["b"][kb], gt["a"][ka], gt["b"][kb])
    np.testing.assert_allclose(match_errors_m(np.stack([T_a_b, T_a_b]), *args), 0.0, atol=1e-9)
    shift = np.array([4.0, 0.0, -13.0])  # an alias: the street repeats 13.6 m further on, in A's frame
    wrong = se3.make_pose(np.eye(3), shift) @ T_a_b
    np.testing.assert_allclose(match_errors_m(np.stack([wrong, wrong]), *args), np.linalg.norm(shift))


def test_odometry_drift_far_from_the_anchors_does_not_count():
    gt = _world()
    T_odom = {r: se3.inverse(p[0])[None] @ p for r, p in gt.items()}
    # b's odometry turns 3 degrees wrong after its keyframe 10: keyframes before it keep their true poses
    bend = _pose(np.radians(3.0), (0.0, 0.0, 0.0))
    T_odom["b"][10:] = T_odom["b"][10:11] @ bend @ se3.inverse(T_odom["b"][10:11]) @ T_odom["b"][10:]
    T_a_b = se3.inverse(gt["a"][0]) @ gt["b"][0]
    err = match_errors_m(T_a_b[None], T_odom["a"][[15]], T_odom["b"][[4]], gt["a"][[15]], gt["b"][[4]])
    assert err[0] < 1e-9


def _run_dir(
    tmp_path: Path, gt: dict[str, np.ndarray], matches: list[dict], anchorings: list[dict] | None = None
) -> Path:
    """A results folder with a journal of both robots' keyframes (every other frame) and ``matches``."""
    run = tmp_path / "run"
    run.mkdir()
    journal = Journal(run / "journal.bin")
    for robot, agent in (("a", "a"), ("b", "b#1")):  # b's keyframes come from its second segment
        poses = se3.inverse(gt[robot][0])[None] @ gt[robot]
        for kf, frame in enumerate(range(0, 20, 2)):
            update = GraphUpdate(kf, poses[frame], (), ())
            journal.append(encode(KeyframeMessage(agent, kf, frame, 0.1 * frame, poses[frame], update)))
    journal.close()
    (run / "matches.json").write_text(json.dumps(matches))
    if anchorings is not None:
        (run / "server.json").write_text(json.dumps({"anchorings": anchorings}))
    return run


def _match(T_a_b: np.ndarray, accepted: bool = True, kf_a: int = 2, kf_b: int = 7) -> dict:
    return {"robot_a": "a", "robot_b": "b#1", "keyframe_a": kf_a, "keyframe_b": kf_b, "accepted": accepted,
            "T_a_b": T_a_b.tolist()}  # fmt: skip


def test_judge_reads_the_journal_and_counts_only_accepted_matches(tmp_path: Path):
    gt = _world()
    T_a_b = se3.inverse(gt["a"][0]) @ gt["b"][0]
    alias = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 30.0])) @ T_a_b
    near = se3.make_pose(np.eye(3), np.array([3.0, 0.0, 0.0])) @ T_a_b
    run = _run_dir(tmp_path, gt, [_match(T_a_b), _match(alias), _match(near), _match(alias, accepted=False),
                                  _match(T_a_b, kf_b=99)])  # fmt: skip
    truth = judge_matches(run, gt, tolerance_m=2.0, gross_m=20.0)
    assert (truth.accepted, truth.off, truth.gross) == (3, 2, 1)
    assert truth.worst_m == pytest.approx(30.0)
    assert truth.anchorings is None  # a run from before anchorings were recorded: unknown, not zero


def _anchoring(gt: dict[str, np.ndarray], frame_a: int, frame_b: int, shift_m: float) -> dict:
    """b's segment anchored to a through a closure between two keyframes, ``shift_m`` off along x."""
    T = se3.inverse(gt["a"][frame_a]) @ gt["b"][frame_b]
    T[0, 3] += shift_m
    return {"agent": "b#1", "closure_id": 0, "robot_a": "a", "kf_a": frame_a // 2, "robot_b": "b#1",
            "kf_b": frame_b // 2, "T_a_b": T.tolist(), "withdrawn": shift_m > 0, "confirmed": shift_m < 1}  # fmt: skip


def test_a_robot_once_placed_through_a_false_closure_is_counted(tmp_path: Path):
    gt = _world()
    T_a_b = se3.inverse(gt["a"][0]) @ gt["b"][0]
    # placed through an alias 150 m off, withdrawn, then placed again through a right closure (0.5 m off)
    anchorings = [_anchoring(gt, 4, 14, 150.0), _anchoring(gt, 10, 8, 0.5)]
    truth = judge_matches(_run_dir(tmp_path, gt, [_match(T_a_b)], anchorings), gt, tolerance_m=2.0, gross_m=20.0)
    assert (truth.anchorings, truth.anchorings_off, truth.anchorings_gross) == (2, 1, 1)
    assert truth.anchorings_gross_confirmed == 0  # it stayed provisional
    anchorings[0]["confirmed"] = True  # ... had two aliases agreed on it
    (tmp_path / "run" / "server.json").write_text(json.dumps({"anchorings": anchorings}))
    assert judge_matches(tmp_path / "run", gt, tolerance_m=2.0, gross_m=20.0).anchorings_gross_confirmed == 1
    assert (truth.accepted, truth.off) == (1, 0)


def test_no_accepted_match_and_a_missing_journal(tmp_path: Path):
    gt = _world()
    run = _run_dir(tmp_path, gt, [])
    truth = judge_matches(run, gt, tolerance_m=2.0, gross_m=20.0)
    assert (truth.accepted, truth.off, truth.gross) == (0, 0, 0) and np.isnan(truth.worst_m)
    (run / "journal.bin").unlink()
    with pytest.raises(DataError, match="journal"):
        judge_matches(run, gt, tolerance_m=2.0, gross_m=20.0)


def test_malformed_results_are_a_clear_error(tmp_path: Path):
    gt = _world()
    run = _run_dir(tmp_path, gt, [{"robot_a": "a", "accepted": True}])  # a match without keyframes
    with pytest.raises(DataError, match=r"matches\.json or server\.json"):
        judge_matches(run, gt, tolerance_m=2.0, gross_m=20.0)
    (run / "matches.json").write_text("[]")
    (run / "server.json").write_text("{not json")
    with pytest.raises(DataError, match=r"matches\.json or server\.json"):
        judge_matches(run, gt, tolerance_m=2.0, gross_m=20.0)


def _rejected(T_hyp: np.ndarray, kf_b: int = 7, success: bool = False) -> dict:
    """A match the matcher rejected (``success`` False) with its recorded best hypothesis."""
    return {"robot_a": "a", "robot_b": "b#1", "keyframe_a": None, "keyframe_b": None, "accepted": False,
            "success": success, "T_a_b": None, "evidence": {"T_a_b_hypothesis": T_hyp.tolist(), "keyframe_b": kf_b,
            "llr": 2.0, "llr_threshold": 9.0, "support": 12, "expected_chance": 8.0, "overlap_a": 30,
            "overlap_b": 28}}  # fmt: skip


def test_rejected_hypotheses_are_judged_at_bs_newest_keyframe(tmp_path: Path):
    gt = _world()
    T_a_b = se3.inverse(gt["a"][0]) @ gt["b"][0]
    near = se3.make_pose(np.eye(3), np.array([1.5, 0.0, 0.0])) @ T_a_b  # right, within 2 m: a miss
    alias = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 30.0])) @ T_a_b
    rows = [_rejected(T_a_b), _rejected(near, kf_b=2), _rejected(alias), _rejected(T_a_b, kf_b=99),
            _rejected(alias, success=True), _match(T_a_b)]  # fmt: skip
    truth = judge_matches(_run_dir(tmp_path, gt, rows), gt, tolerance_m=2.0, gross_m=20.0)
    # kf_b 99 is not in the journal; a successful match (closures refused by the back end) is not a miss
    assert (truth.rejected, truth.rejected_right) == (3, 2)
    assert (truth.accepted, truth.off) == (1, 0)


def test_rejected_matches_of_a_run_without_the_record_are_unknown(tmp_path: Path):
    gt = _world()
    rows = [{**_rejected(np.eye(4)), "evidence": None}]
    assert judge_matches(_run_dir(tmp_path, gt, rows), gt, tolerance_m=2.0, gross_m=20.0).rejected == 0
    legacy = [{k: v for k, v in rows[0].items() if k != "evidence"}]
    (tmp_path / "run" / "matches.json").write_text(json.dumps(legacy))
    assert judge_matches(tmp_path / "run", gt, tolerance_m=2.0, gross_m=20.0).rejected is None
