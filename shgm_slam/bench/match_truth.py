"""Accepted graph matches judged against ground truth at their own place (held-out benchmark).

A robot can be placed far from the truth for two reasons: a **false match** (an alias: the map server
joined two places that are not the same) or a right match under a trajectory that drifts (its own
odometry bends it away from the place where it was joined). The placement verdicts cannot tell them
apart; this check can. Each accepted match is read at the keyframes it anchors (``keyframe_a`` of agent
A, ``keyframe_b`` of agent B): the match's transform puts B's keyframe at

    T_kfa_kfb = inv(T_odom_kf[A][keyframe_a]) @ T_a_b @ T_odom_kf[B][keyframe_b]

in A's keyframe camera frame, while the truth is ``inv(T_world_cam[A][frame_a]) @ T_world_cam[B][frame_b]``.
The translation between the two is the match's error at its place: odometry drift over the few keyframes
between the anchors and the matched nodes adds little, so a right match stays within a few metres and an
alias is off by its street's repetition.

A **rejected** match (the verification found its best hypothesis not beyond chance, or too few, too
clustered or too loose partners) is judged the same way where the run recorded that hypothesis
(``evidence`` in ``matches.json``): at B's newest keyframe when the match was made and the keyframe of A
nearest to it under the hypothesis. One within the tolerance is a right alignment the verification
missed: the share of those is the verification's sensitivity, next to the accepted aliases (its false
alarms).

The final trajectories hide a false match that placed a robot for a while and was withdrawn when later
matches outvoted it. ``server.json`` lists every **anchoring** (each time an agent entered the shared
frame, with the closure that placed it); the closure's keyframe-to-keyframe transform is judged the same
way, so a robot once placed through a false closure is counted even when it ends up right.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.errors import DataError
from shgm_slam.geometry import se3


@dataclass(frozen=True)
class MatchTruth:
    """Accepted matches of one run against the truth.

    Attributes:
        accepted: accepted matches judged (both anchor keyframes known).
        off: of those, matches whose error at their place exceeds the mode's placement tolerance.
        gross: of those, matches off by more than the gross-error bound (aliases, not imprecision).
        worst_m: the largest error at its place, metres (NaN without accepted matches).
        anchorings: times an agent entered the shared frame (None: the run's ``server.json`` predates
            the record).
        anchorings_off, anchorings_gross: of those, through a closure off by more than the tolerance
            (the gross bound): a robot placed wrong, at least for a while.
        anchorings_gross_confirmed: of the gross ones, those whose place the server ever confirmed (two
            independent matches agreed on it); the others stayed provisional, and said so, until withdrawn.
        rejected: matches the matcher rejected whose best hypothesis was recorded and judged (None: the
            run's ``matches.json`` predates the record).
        rejected_right: of those, hypotheses within the tolerance at their place (right alignments missed).
    """

    accepted: int
    off: int
    gross: int
    worst_m: float
    anchorings: int | None = None
    anchorings_off: int = 0
    anchorings_gross: int = 0
    anchorings_gross_confirmed: int = 0
    rejected: int | None = None
    rejected_right: int = 0


def match_errors_m(
    T_a_b: np.ndarray, T_odom_kfa: np.ndarray, T_odom_kfb: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray
) -> np.ndarray:
    """(M,) translation error in metres of M matches at their anchor keyframes (module docstring).

    Args:
        T_a_b: (M, 4, 4) each match's transform from agent B's odometry frame into agent A's.
        T_odom_kfa, T_odom_kfb: (M, 4, 4) the anchor keyframes' camera poses in their agents' odometry frames.
        T_world_a, T_world_b: (M, 4, 4) the same keyframes' ground-truth camera poses (one world frame).
    """
    return _translation_gap_m(se3.inverse(T_odom_kfa) @ T_a_b @ T_odom_kfb, se3.inverse(T_world_a) @ T_world_b)


def _translation_gap_m(T_kfa_kfb: np.ndarray, T_kfa_kfb_true: np.ndarray) -> np.ndarray:
    """(M,) distance in metres between measured and true positions of keyframe b in keyframe a's camera frame,
    for (M, 4, 4) stacks (M may be 0)."""
    return np.linalg.norm(T_kfa_kfb[:, :3, 3] - T_kfa_kfb_true[:, :3, 3], axis=1).reshape(-1)


def judge_matches(
    run_dir: Path, gt_poses: dict[str, np.ndarray], tolerance_m: float, gross_m: float
) -> MatchTruth:
    """Judge the accepted matches and the anchorings of one results folder (its ``matches.json``,
    ``server.json`` and ``journal.bin``).

    Args:
        run_dir: a results folder written with a journal (the held-out benchmark's runs are).
        gt_poses: robot name -> (N, 4, 4) ground-truth camera poses of its frames (world frame).
        tolerance_m: a match (closure) farther off than this at its place counts as off.
        gross_m: ... and farther than this as gross.
    """
    run_dir = Path(run_dir)
    keyframes = _keyframes(run_dir / "journal.bin")
    try:
        return _judge(run_dir, keyframes, gt_poses, tolerance_m, gross_m)
    except (KeyError, IndexError, TypeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        raise DataError(
            f"{run_dir}: matches.json or server.json does not hold what a run writes ({exc!r}); judge the "
            "results folder of a finished run, or run it again"
        ) from None


def _judge(
    run_dir: Path, keyframes: dict[tuple[str, int], tuple[int, np.ndarray]], gt_poses: dict[str, np.ndarray],
    tolerance_m: float, gross_m: float,
) -> MatchTruth:  # fmt: skip
    """``judge_matches`` on the keyframes of the run's journal."""

    def known(agent_a: str, kf_a: int, agent_b: str, kf_b: int) -> bool:
        return (agent_a, kf_a) in keyframes and (agent_b, kf_b) in keyframes

    def true_kfa_kfb(agent_a: str, kf_a: int, agent_b: str, kf_b: int) -> np.ndarray:
        """(4, 4) true pose of keyframe ``kf_b`` of ``agent_b`` in keyframe ``kf_a``'s camera frame of ``agent_a``."""
        fa, fb = keyframes[(agent_a, kf_a)][0], keyframes[(agent_b, kf_b)][0]
        return se3.inverse(gt_poses[agent_robot(agent_a)[0]][fa]) @ gt_poses[agent_robot(agent_b)[0]][fb]

    measured, truth = [np.zeros((0, 4, 4))], [np.zeros((0, 4, 4))]  # an empty run stacks too
    missed_measured, missed_truth = [np.zeros((0, 4, 4))], [np.zeros((0, 4, 4))]
    rows = json.loads((run_dir / "matches.json").read_text())
    positions = _keyframe_positions(keyframes)
    for m in rows:
        pair = (m["robot_a"], m["keyframe_a"], m["robot_b"], m["keyframe_b"])
        if m.get("accepted") and known(*pair):
            T_odom_kfa, T_odom_kfb = keyframes[pair[:2]][1], keyframes[pair[2:]][1]
            measured.append((se3.inverse(T_odom_kfa) @ np.asarray(m["T_a_b"], dtype=np.float64) @ T_odom_kfb)[None])
            truth.append(true_kfa_kfb(*pair)[None])
        evidence = m.get("evidence")
        if m.get("success") or evidence is None or (m["robot_b"], evidence["keyframe_b"]) not in keyframes:
            continue
        T_hyp = np.asarray(evidence["T_a_b_hypothesis"], dtype=np.float64)
        T_odom_kfb = keyframes[(m["robot_b"], evidence["keyframe_b"])][1]
        kf_a = _nearest_keyframe(positions, m["robot_a"], (T_hyp @ T_odom_kfb)[:3, 3])
        if kf_a is None:
            continue
        missed_measured.append((se3.inverse(keyframes[(m["robot_a"], kf_a)][1]) @ T_hyp @ T_odom_kfb)[None])
        missed_truth.append(true_kfa_kfb(m["robot_a"], kf_a, m["robot_b"], evidence["keyframe_b"])[None])
    err = _translation_gap_m(np.concatenate(measured), np.concatenate(truth))
    worst = float(err.max()) if err.size else float("nan")
    missed_err = _translation_gap_m(np.concatenate(missed_measured), np.concatenate(missed_truth))
    recorded = any("evidence" in m for m in rows) or not rows
    rejected = {"rejected": len(missed_err) if recorded else None,
                "rejected_right": int((missed_err <= tolerance_m).sum())}  # fmt: skip
    server = run_dir / "server.json"
    records = json.loads(server.read_text()).get("anchorings") if server.is_file() else None
    if records is None:
        return MatchTruth(len(err), int((err > tolerance_m).sum()), int((err > gross_m).sum()), worst, **rejected)
    judged = [a for a in records
              if a["robot_a"] != a["robot_b"] and known(a["robot_a"], a["kf_a"], a["robot_b"], a["kf_b"])]  # fmt: skip
    anchor_err = _translation_gap_m(
        np.asarray([a["T_a_b"] for a in judged], dtype=np.float64).reshape(-1, 4, 4),
        np.asarray([true_kfa_kfb(a["robot_a"], a["kf_a"], a["robot_b"], a["kf_b"]) for a in judged]).reshape(-1, 4, 4),
    )
    confirmed = np.array([bool(a.get("confirmed")) for a in judged], dtype=bool)
    return MatchTruth(
        len(err), int((err > tolerance_m).sum()), int((err > gross_m).sum()), worst,
        anchorings=len(anchor_err), anchorings_off=int((anchor_err > tolerance_m).sum()),
        anchorings_gross=int((anchor_err > gross_m).sum()),
        anchorings_gross_confirmed=int(((anchor_err > gross_m) & confirmed).sum()), **rejected,
    )  # fmt: skip


def _keyframe_positions(
    keyframes: dict[tuple[str, int], tuple[int, np.ndarray]],
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Agent -> ((K,) keyframe indices, (K, 3) camera positions in its odometry frame)."""
    out: dict[str, tuple[list[int], list[np.ndarray]]] = {}
    for (agent, k), (_, T) in keyframes.items():
        out.setdefault(agent, ([], []))
        out[agent][0].append(k)
        out[agent][1].append(T[:3, 3])
    return {a: (np.asarray(ks, dtype=np.int64), np.stack(ps)) for a, (ks, ps) in out.items()}


def _nearest_keyframe(
    positions: dict[str, tuple[np.ndarray, np.ndarray]], agent: str, point_odom: np.ndarray
) -> int | None:
    """Index of ``agent``'s keyframe whose camera is nearest to (3,) ``point_odom`` (its odometry frame), or None
    when the journal holds none of its keyframes (``positions``: ``_keyframe_positions``)."""
    if agent not in positions:
        return None
    kfs, xyz = positions[agent]
    return int(kfs[int(np.argmin(np.linalg.norm(xyz - point_odom, axis=1)))])


def _keyframes(journal: Path) -> dict[tuple[str, int], tuple[int, np.ndarray]]:
    """(agent, keyframe index) -> (frame index, (4, 4) T_odom_kf) of every keyframe a run's journal holds."""
    from shgm_slam.messages import KeyframeMessage
    from shgm_slam.server.journal import Journal
    from shgm_slam.wire import decode

    if not journal.is_file():
        raise DataError(f"{journal} is missing: matches are judged from the run's journal")
    keyframes = {}
    for payload in Journal(journal).replay():
        m = decode(payload)
        if isinstance(m, KeyframeMessage):
            keyframes[(m.robot, m.kf_index)] = (m.frame_index, np.asarray(m.T_odom_kf, dtype=np.float64))
    return keyframes
