"""Evaluate a results folder against ground truth in the shared frame (``shgm-slam eval``).

The fused trajectories of a run (``<robot>_fused_tum.txt``) are in ONE shared frame: the first
robot's first camera frame. Ground truth comes in each sequence's own world frame (the simulator's
city, KITTI's first camera of the drive), so it is moved into the shared frame the same way the run
measures its ATE::

    T_shared_cam_gt = inverse(T_world_cam_gt of the first robot's first frame) @ T_world_cam_gt

``shared_frame.shared_frame_ground_truth`` does that; ``ResultsWriter.write_ground_truth`` writes the result as
``<robot>_gt_tum.txt`` / ``<robot>_gt_kitti.txt`` so evo compares without alignment::

    evo_ape tum results/demo/car1_gt_tum.txt results/demo/car1_fused_tum.txt

``evaluate_results`` reads a results folder, takes the ground truth from those files or from the
sequences, associates poses by timestamp and returns each robot's fused ATE (RMSE, metres) in the
shared frame and SE(3)-aligned, through evo (``metrics.ate``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from shgm_slam.data.base import open_sequence
from shgm_slam.errors import ConfigError, DataError, parse_failure
from shgm_slam.io.trajectories import associate, read_comments, read_tum
from shgm_slam.metrics import AlignMode, ate, joint_ate
from shgm_slam.shared_frame import shared_frame_ground_truth
from shgm_slam.types import Sequence


@dataclass
class RobotEvaluation:
    """One robot's fused trajectory against ground truth (metres; NaN when not measurable)."""

    name: str
    fused_poses: int  # rows of <robot>_fused_tum.txt (0 = not placed in the shared frame)
    evaluated_poses: int  # of those, rows with a ground-truth pose at the same time
    ate_fused_m: float = float("nan")  # RMSE in the shared frame, no alignment
    ate_fused_aligned_m: float = float("nan")  # RMSE after an SE(3) fit (shape only)
    max_error_m: float = float("nan")  # largest position error in the shared frame
    note: str = ""
    # placed but not confirmed by an independent graph match (the fused file's "# provisional: ..." line says why)
    provisional: bool = False
    # RMSE after ONE SE(3) fit of all placed robots together (``metrics.joint_ate``): the shared frame without
    # the first robot's own drift; NaN when not in the shared frame
    ate_fused_joint_m: float = float("nan")

    @property
    def localized(self) -> bool:
        return self.fused_poses > 0


@dataclass
class EvaluationResult:
    """What ``evaluate_results`` returns; ``gt_source`` says where the ground truth came from."""

    results_dir: Path
    reference_robot: str
    gt_source: str
    robots: list[RobotEvaluation] = field(default_factory=list)
    gt_files_written: list[Path] = field(default_factory=list)
    ate_joint_m: float = float("nan")  # all placed robots' poses under their one joint SE(3) fit, RMSE
    joint_robots: int = 0  # robots in that fit (placed, with ground truth in the shared frame)
    interrupted: bool = False  # the run was stopped early (``metrics.json``): its trajectories end early

    def to_json_dict(self) -> dict:
        from shgm_slam.io.json_text import finite_or_none

        return finite_or_none({
            "results_dir": str(self.results_dir), "reference_robot": self.reference_robot,
            "gt_source": self.gt_source, "robots": [asdict(r) for r in self.robots],
            "gt_files_written": [str(p) for p in self.gt_files_written],
            "ate_joint_m": self.ate_joint_m, "joint_robots": self.joint_robots, "interrupted": self.interrupted,
        })  # type: ignore[return-value]  # fmt: skip


def open_ground_truth(args: list[str]) -> dict[str, Sequence]:
    """Open ``NAME=PATH[:start-end]`` arguments (as given to ``run --robot``) as robot -> sequence.

    Raises:
        ConfigError: an argument without ``NAME=`` or a name given twice.
        DataError: a sequence cannot be opened.
    """
    sequences: dict[str, Sequence] = {}
    for arg in args:
        name, sep, spec = arg.strip().partition("=")
        if not sep or not name or not spec:
            raise ConfigError(f"--gt {arg!r}: expected NAME=PATH[:start-end], the robot's --robot argument of the run")
        if name in sequences:
            raise ConfigError(f"--gt names robot {name!r} twice")
        try:
            sequences[name] = open_sequence(spec)
        except DataError as exc:  # (what is wrong with the folder, and which --gt said it)
            raise DataError(f"--gt {arg!r}: {exc}") from None
    return sequences


def run_robot_order(results_dir: Path) -> list[str]:
    """Robot names in run order from ``metrics.json``, else (a map server's folder) from the
    ``*_odometry_tum.txt`` files: the server's reference robot first (``server_reference``: its odometry frame is
    the shared frame), the others by name. Sorted alone, a server whose ``--reference`` (or first robot to
    connect) was not first by name had its ground truth moved into another robot's frame: the reference itself
    84 m off."""
    metrics = results_dir / "metrics.json"
    if metrics.is_file():
        try:
            data = json.loads(metrics.read_text())
        except (ValueError, RecursionError) as exc:
            raise DataError(
                f"{metrics} is not valid JSON ({parse_failure(exc)}); is {results_dir} a results folder of `run`?"
            ) from None
        robots = data.get("robots") if isinstance(data, dict) else None
        names = [r.get("name") for r in robots if isinstance(r, dict)] if isinstance(robots, list) else []
        if not names or not all(isinstance(n, str) and n for n in names):
            raise DataError(
                f"{metrics} has no list of robots with their names (\"robots\": [{{\"name\": ...}}]); is "
                f"{results_dir} a results folder of `run`, and the file as the run wrote it?"
            )
        return names
    names = sorted(p.name.removesuffix("_odometry_tum.txt") for p in results_dir.glob("*_odometry_tum.txt"))
    if not names:
        raise DataError(
            f"{results_dir} has no metrics.json and no <robot>_odometry_tum.txt: point at the folder `run` wrote"
        )
    reference = server_reference(results_dir)  # first even without a file of its own: it defines the frame
    return names if reference is None else [reference, *(n for n in names if n != reference)]


def server_reference(results_dir: Path) -> str | None:
    """The robot whose odometry frame is a map server's shared frame (``server.json``'s ``reference``), or None
    (no such file or field, or it cannot be read)."""
    try:
        reference = json.loads((results_dir / "server.json").read_text()).get("reference")
    except (OSError, ValueError, AttributeError, RecursionError):
        return None
    if not isinstance(reference, str):
        return None
    from shgm_slam.transport.keys import validate_robot_name

    try:
        validate_robot_name(reference)  # it names files: no path in it
    except ConfigError:
        return None
    return reference


def run_robot_counts(results_dir: Path, key: str = "frames") -> dict[str, int]:
    """Robot -> an integer of its entry in ``metrics.json``: ``frames`` of its sequence (range) in the run (default),
    ``fused_poses`` (rows of its fused trajectory), ``frames_not_reached``; empty when not recorded."""
    try:
        robots = json.loads((results_dir / "metrics.json").read_text())["robots"]
        return {r["name"]: r[key] for r in robots if isinstance(r.get(key), int) and not isinstance(r[key], bool)}
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
        return {}  # no metrics.json (``run_robot_order`` says what is wrong with an unreadable one)


def run_was_interrupted(results_dir: Path) -> bool:
    """Whether ``metrics.json`` says the run was stopped before its end (False when it does not say)."""
    try:
        return json.loads((results_dir / "metrics.json").read_text()).get("interrupted") is True
    except (OSError, ValueError, AttributeError, RecursionError):
        return False


def check_results_finished(results_dir: Path) -> None:
    """Refuse a results folder that does not hold a finished run's results: one whose run ended with an error
    (``incomplete.txt``), one another process is writing now (its lock file), a checkpoint whose run never
    finished (no ``metrics.json`` and ``server.json`` says the map server had not finished: the run was killed,
    e.g. SIGKILL or out of memory, where nothing could mark it), or a run's folder without its ``metrics.json``
    (killed while writing it, or deleted: the fused trajectories cannot be checked against it). A map server's
    folder (``journal.bin``) has no ``metrics.json``; folders of runs stopped by Ctrl-C / SIGTERM pass: their
    results are what the run reached (``metrics.json`` says ``interrupted``).

    Raises:
        DataError: the folder is one of those, saying why and what to do.
    """
    from shgm_slam.io.export import INCOMPLETE_FILE, RERUN_ADVICE, results_dir_writer

    root = Path(results_dir)
    if (root / INCOMPLETE_FILE).is_file():
        raise DataError(
            f"{root} holds no results: its run ended with an error ({root / INCOMPLETE_FILE} says why and what to "
            "do)"
        )
    writer = results_dir_writer(root)
    if writer is not None:
        raise DataError(
            f"{root} is being written by another shgm-slam process (pid {writer}): its files are a checkpoint, "
            "not results yet; wait for that run to finish"
        )
    server_json = root / "server.json"
    if (root / "metrics.json").is_file() or not server_json.is_file():
        return
    try:
        finished = json.loads(server_json.read_text()).get("finished")
    except (OSError, ValueError, AttributeError, RecursionError):
        return  # unreadable: nothing it says (what else is wrong with the folder is said where it is read)
    journal = (root / "journal.bin").is_file()  # a map server's folder (it keeps its journal; a run does not)
    if finished is False:
        advice = ("start the map server on this folder again: it resumes from its journal (journal.bin)" if journal
                  else RERUN_ADVICE)  # fmt: skip
        raise DataError(
            f"{root} holds no results: its run never finished (no metrics.json, and {server_json.name} says the "
            f"map server had not finished: killed, or still running); its files are a checkpoint; {advice}"
        )
    if not journal:  # a run's folder: metrics.json is the last file it writes
        raise DataError(
            f"{root} has no metrics.json, the last file a run writes: the run was killed while writing its results, "
            f"or the file was deleted since; {RERUN_ADVICE}"
        )


def check_fused_rows(results_dir: Path, robot: str, rows: int) -> None:
    """Refuse a fused trajectory file whose row count differs from what the run wrote (``metrics.json``'s
    ``fused_poses``; nothing to check in folders written before it was recorded).

    Raises:
        DataError: the file was cut short, emptied or extended after the run.
    """
    expected = run_robot_counts(results_dir, "fused_poses").get(robot)
    if expected is not None and expected != rows:
        raise DataError(
            f"{results_dir / f'{robot}_fused_tum.txt'} holds {rows} poses but the run wrote {expected} "
            f"({results_dir / 'metrics.json'}): the file was cut or edited; restore it or run again"
        )


def check_gt_rows(results_dir: Path, robot: str, rows: int) -> None:
    """Refuse a ``<robot>_gt_tum.txt`` whose row count differs from the robot's frames in the run (``metrics.json``'s
    ``frames``): the run writes one ground-truth pose per frame of its sequence. A cut file still associates with
    some fused poses and gave an ATE over those alone (3 of 47 poses, exit 0).

    Raises:
        DataError: the file was cut, emptied or extended after the run.
    """
    expected = run_robot_counts(results_dir).get(robot)
    if expected is not None and expected != rows:
        raise DataError(
            f"{results_dir / f'{robot}_gt_tum.txt'} holds {rows} poses but the run had {expected} frames for {robot} "
            f"({results_dir / 'metrics.json'}): the file was cut or edited; delete it and write it again with eval "
            f"--gt {robot}=PATH[:start-end] (the run's --robot argument for it)"
        )


SAME_SEQUENCE = "give the sequence and frame range the run had for it (its --robot NAME=PATH[:start-end])"
"""How ground truth for evaluation is made to fit the run (the end of its errors)."""


def _given(robot: str) -> str:
    """How an error names the ground truth given for ``robot``, from the CLI or from Python."""
    return f"the ground truth given for {robot} (eval --gt {robot}=..., or evaluate's sequences)"


def check_sequence_truth(sequences: dict[str, Sequence]) -> None:
    """Refuse a sequence whose timestamps are not (N,) finite, increasing seconds, one per frame, or whose ground
    truth is not (N, 4, 4) finite rigid transforms in metres (``data.memory.checked_poses``,
    ``data.kitti.check_pose_units``). Folders and ``ArraySequence`` check that as they open; any other object of
    the ``Sequence`` protocol comes here unchecked: (N, 16) poses ended in an IndexError, poses in millimetres gave
    an ATE of 67 km without a word, too few poses an error about a temporary file.

    Raises:
        DataError: naming the robot and what is wrong.
    """
    from shgm_slam.data.kitti import check_pose_units
    from shgm_slam.data.memory import checked_numbers, checked_poses

    for name, seq in sequences.items():
        times = checked_numbers(seq.timestamps_s, "timestamps_s", name)
        if times.shape != (len(seq),) or not np.isfinite(times).all() or (np.diff(times) <= 0).any():
            raise DataError(f"{_given(name)}: its timestamps_s (shape {times.shape}) are not {len(seq)} finite, "
                            "increasing times in seconds, one per frame")  # fmt: skip
        if seq.gt_poses is not None:
            poses = checked_poses(seq.gt_poses, len(seq), name, "gt_poses")
            check_pose_units(poses, times, _given(name), "the ground truth")


def check_frame_counts(results_dir: Path, sequences: dict[str, Sequence]) -> None:
    """Refuse ground-truth sequences whose frame count differs from the one the run recorded.

    A shorter, longer or shifted sequence (another range, another drive) still associates some poses by
    time and gives a plausible but wrong ATE.

    Raises:
        DataError: a sequence's frame count differs from ``metrics.json``'s for that robot.
    """
    counts = run_robot_counts(results_dir)
    for name, seq in sequences.items():
        if name in counts and len(seq) != counts[name]:
            raise DataError(
                f"{_given(name)}: its sequence has {len(seq)} frames but the run had {counts[name]} for {name} "
                f"({results_dir / 'metrics.json'}); {SAME_SEQUENCE}"
            )
        odometry = results_dir / f"{name}_odometry_tum.txt"
        if odometry.is_file():  # the same count from another range: the run's frame times are not the sequence's
            t_run = read_tum(odometry)[0]
            t_seq = np.asarray(seq.timestamps_s, dtype=np.float64)
            if len(associate(t_run, t_seq)[0]) < len(t_run):
                raise DataError(
                    f"{_given(name)}: the run's frame times ({t_run[0]:.3f}-{t_run[-1]:.3f} s, {odometry.name}) are "
                    f"not this sequence's ({t_seq[0]:.3f}-{t_seq[-1]:.3f} s); {SAME_SEQUENCE}"
                )


def _evaluate_robot(
    name: str, fused_file: Path, t_gt: np.ndarray, gt: np.ndarray
) -> tuple[RobotEvaluation, tuple[np.ndarray, np.ndarray] | None]:
    """The robot's evaluation and its associated (M, 4, 4) ground-truth and fused poses (None: not placed)."""
    if not fused_file.is_file():
        if fused_file.exists():  # a folder (or another non-file) of that name: not "not placed"
            raise DataError(f"{fused_file} is not a file; it must be the TUM trajectory `run` wrote for {name}")
        check_fused_rows(fused_file.parent, name, 0)  # the run wrote one: deleted since
        return RobotEvaluation(name, 0, 0, note="not placed (no fused trajectory)"), None
    t_est, est = read_tum(fused_file)
    check_fused_rows(fused_file.parent, name, len(t_est))
    rows_est, rows_gt = associate(t_est, t_gt)
    rep = RobotEvaluation(name, len(t_est), len(rows_est), provisional=is_provisional(fused_file))
    notes = ["provisional: no independent graph match confirms its place"] if rep.provisional else []
    if len(rows_est) < len(t_est):
        notes.append(f"{len(t_est) - len(rows_est)} fused pose(s) have no ground truth at their time")
    shared = ate(gt[rows_gt], est[rows_est], align=AlignMode.NONE)
    aligned = ate(gt[rows_gt], est[rows_est], align=AlignMode.SE3)
    rep.ate_fused_m, rep.max_error_m, rep.ate_fused_aligned_m = shared.rmse, shared.max, aligned.rmse
    if not shared.valid:
        notes.append(shared.reason)
    rep.note = "; ".join(notes)
    return rep, (gt[rows_gt], est[rows_est])


def is_provisional(fused_file: Path) -> bool:
    """True when a fused trajectory file says its robot was placed provisionally (``# provisional: ...``)."""
    from shgm_slam.io.export import PROVISIONAL_COMMENT

    return any(c.startswith(PROVISIONAL_COMMENT) for c in read_comments(fused_file))


def _no_truth_note(robot: str, sequences: dict[str, Sequence] | None) -> str:
    """Why ``robot`` has no ground truth in an evaluation: its sequence (given in ``sequences``) has none, none was
    given for it, or (``sequences`` None: from the results folder) the folder has no ``<robot>_gt_tum.txt``."""
    if not sequences:
        return f"no ground truth ({robot}_gt_tum.txt is not in the results folder; eval --gt gives it)"
    return "no ground truth: its sequence has none" if robot in sequences else "no ground truth given"


GT_AGREEMENT_M = 0.01
"""Largest position difference (metres) between ``--gt``'s ground truth and the ``<robot>_gt_tum.txt`` the run
wrote for the two to be the same ground truth (the file keeps positions to 0.1 mm)."""


def _check_against_written_truth(root: Path, truth: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Refuse ``--gt`` ground truth that differs from the ``<robot>_gt_tum.txt`` already in the results folder
    (written by the run from the sequences it ran on): another sequence of the same length and times passes
    every other check, and writing it would replace the right file.

    Raises:
        DataError: a robot's file exists and its times or positions differ from ``truth``'s.
    """
    for robot, (times_s, T) in truth.items():
        path = root / f"{robot}_gt_tum.txt"
        if not path.is_file():
            continue
        old_times, old_T = read_tum(path)
        same_times = old_times.shape == np.shape(times_s) and np.allclose(old_times, times_s, atol=1e-6)
        apart = float(np.max(np.linalg.norm(old_T[:, :3, 3] - T[:, :3, 3], axis=1))) if same_times else np.inf
        if not apart <= GT_AGREEMENT_M:
            how = f"positions up to {apart:.2f} m apart" if same_times else "other frame times"
            raise DataError(
                f"{_given(robot)}: its ground truth differs from {path} that the run wrote ({how}); check the "
                "sequence and frame range, or delete that file to replace it"
            )


def evaluate_results(
    results_dir: Path | str,
    sequences: dict[str, Sequence] | None = None,
    *,
    gt_shared_frame: bool = True,
    write_gt: bool = True,
) -> EvaluationResult:
    """Fused ATE of every robot of a results folder against ground truth in the shared frame.

    Args:
        results_dir: the folder ``run``/``demo`` wrote (``metrics.json`` gives the robot order).
        sequences: robot -> its sequence (the same ``NAME=PATH[:start-end]`` as the run) to take the
            ground truth from; None = the ``<robot>_gt_tum.txt`` files in ``results_dir``.
        gt_shared_frame: the sequences' ground truths share one world frame (see
            ``shared_frame_ground_truth``); otherwise only the shared-frame robot is evaluated unaligned.
        write_gt: with ``sequences``, also write ``<robot>_gt_tum.txt`` / ``_kitti.txt`` into the folder.

    Raises:
        DataError: not a results folder (or one of a run that failed, was killed or is still running:
            ``check_results_finished``), unknown robot names, a sequence with
            another frame count than the run's or malformed times or ground truth (``check_sequence_truth``), a
            ``<robot>_gt_tum.txt`` cut or edited after the run (``check_gt_rows``), or no ground truth anywhere.
    """
    from shgm_slam.io.export import ResultsWriter

    root = Path(results_dir)
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise DataError(f"results folder {root} {what}; pass the --out folder of `run` or `demo`")
    check_results_finished(root)
    order = run_robot_order(root)
    result = EvaluationResult(root, order[0], "", interrupted=run_was_interrupted(root))
    not_reached, frames = run_robot_counts(root, "frames_not_reached"), run_robot_counts(root)
    truth: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    own_frame: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if sequences:
        unknown = sorted(set(sequences) - set(order))
        if unknown:
            raise DataError(f"ground truth given (eval --gt, evaluate's sequences) for robot(s) {', '.join(unknown)} "
                            f"that are not in {root} ({', '.join(order)})")
        if order[0] not in sequences:
            raise DataError(
                f"the ground truth given (eval --gt, evaluate's sequences) must include {order[0]}: the first robot "
                "of the run defines the shared frame"
            )
        check_sequence_truth(sequences)
        check_frame_counts(root, sequences)
        ordered = {r: sequences[r] for r in order if r in sequences}
        poses = shared_frame_ground_truth(ordered, gt_shared_frame)
        if not poses:
            raise DataError(f"the sequence of {order[0]} has no ground truth (poses.txt or <root>/poses/<seq>.txt)")
        truth = {r: (np.asarray(ordered[r].timestamps_s), poses[r]) for r in poses}
        own_frame = {  # not in the shared frame: only the SE(3)-aligned error is measurable
            r: (np.asarray(seq.timestamps_s), np.asarray(seq.gt_poses))
            for r, seq in ordered.items() if r not in poses and seq.gt_poses is not None
        }  # fmt: skip
        result.gt_source = "sequences"
        _check_against_written_truth(root, truth)
        if write_gt:
            result.gt_files_written = ResultsWriter(root).write_ground_truth(ordered, gt_shared_frame)
    else:
        for r in order:
            path = root / f"{r}_gt_tum.txt"
            if path.exists():  # (read_tum refuses a folder of that name: not "no ground truth")
                truth[r] = read_tum(path)
                check_gt_rows(root, r, len(truth[r][0]))
        if not truth:
            raise DataError(
                f"{root} has no <robot>_gt_tum.txt files: pass the run's sequences, e.g. "
                f"--gt {order[0]}=PATH[:start-end] for every robot"
            )
        result.gt_source = "results folder"
    joint: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # row in result.robots -> associated gt, fused
    for r in order:
        if r in truth:
            rep, poses = _evaluate_robot(r, root / f"{r}_fused_tum.txt", *truth[r])
            if poses is not None and len(poses[0]):
                joint[len(result.robots)] = poses
            result.robots.append(rep)
        elif r in own_frame:
            rep, _ = _evaluate_robot(r, root / f"{r}_fused_tum.txt", *own_frame[r])
            rep.ate_fused_m = rep.max_error_m = float("nan")
            rep.note = rep.note or "ground truth in another frame: aligned only"
            result.robots.append(rep)
        else:
            fused = root / f"{r}_fused_tum.txt"
            count = len(read_tum(fused)[0]) if fused.exists() else 0  # read_tum refuses a folder of that name
            if count:
                check_fused_rows(root, r, count)
            provisional = count > 0 and is_provisional(fused)
            note = _no_truth_note(r, sequences)
            result.robots.append(RobotEvaluation(r, count, 0, note=note, provisional=provisional))
    segments, placed = run_robot_counts(root, "segments"), run_robot_counts(root, "segments_placed")
    for rep in result.robots:
        if rep.fused_poses and rep.name in placed and placed[rep.name] < segments.get(rep.name, 0):
            part = (f"{placed[rep.name]} of its {segments[rep.name]} trajectory segments placed: the frames of the "
                    "others are not in its fused trajectory (not localized)")  # fmt: skip
            rep.note = f"{rep.note}; {part}" if rep.note else part
        if not_reached.get(rep.name):
            cut = f"interrupted: {not_reached[rep.name]} of its {frames.get(rep.name)} frames were not run"
            rep.note = f"{rep.note}; {cut}" if rep.note else cut
    if joint:
        per_robot, together = joint_ate([g for g, _ in joint.values()], [e for _, e in joint.values()])
        for row, stats in zip(joint, per_robot, strict=True):
            result.robots[row].ate_fused_joint_m = stats.rmse
        result.ate_joint_m, result.joint_robots = together.rmse, len(joint)
    return result
