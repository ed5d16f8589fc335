"""The held-out benchmark's judge: each robot of a finished run against ground truth.

Placement is judged in the shared frame after fixing its gauge by the reference robot's trajectory
(``placement_errors``); odometry by 1 s windows of the reported trajectory whose motion is grossly wrong
(``odometry_breaks``: failures the system did not detect). ``judge_run`` reads a results folder and
returns one ``RobotVerdict`` per robot; nothing here runs the system.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from shgm_slam.data import open_sequence
from shgm_slam.errors import DataError
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import read_tum

MIN_SHARED_VIEW_M = 30.0
"""A robot 'overlaps' when it shares at least this much view with another robot (scenario.json)."""
BREAK_WINDOW_S = 1.0
"""Odometry is judged against ground truth over windows of this length."""


class InputMode(str, Enum):
    """Where depth and labels come from."""

    FILES = "files"  # the rendered depth and labels; KISS-ICP odometry (auto)
    RGB = "rgb"  # the demo ONNX models on the RGB images (odometry: auto)


GROSS_ERROR_M = 20.0
"""A wrong placement farther than this is an outright false merge (an alias), not imprecision."""
PLACED_RIGHT_M = {InputMode.FILES: 2.0, InputMode.RGB: 5.0}
"""A placed robot is right when its placement error (``placement_errors``) is within this, metres, per input mode."""


class Outcome(str, Enum):
    """What became of one robot of one world (``judge_run``)."""

    RIGHT = "right"
    WRONG = "wrong"
    NOT_PLACED = "not placed"


@dataclass
class RobotVerdict:
    """One robot of one world in one mode (a row of the held-out table)."""

    scenario: str
    seed: int
    mode: str
    robot: str
    reference: bool
    overlaps: bool
    outcome: str
    placed_fraction: float
    placement_error_m: float  # how far the best rigid fit moves the fused trajectory onto the truth
    ate_fused_m: float  # fused ATE: gauge fixed by the reference's trajectory (``judge_run``)
    ate_fused_raw_m: float  # no alignment at all (the shared frame as the system defines it)
    max_error_m: float
    ate_odometry_aligned_m: float
    odometry_breaks: int  # ground truth: grossly wrong stretches inside reported segments (missed failures)
    failures_detected: int  # divergences the system detected and cut (new segments)
    path_length_m: float
    notes: list[str] = field(default_factory=list)
    provisional: bool = False  # placed at the end only provisionally: the run said the place was unconfirmed
    waiting: bool = False  # not placed although matches were accepted: too few independent ones (server.json)


def odometry_breaks(
    times_s: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray, boundaries: set[int] | None = None
) -> int:
    """Count ground-truth odometry failures: 1 s windows whose relative motion is grossly wrong.

    A window [i, j] (consecutive valid frames ``BREAK_WINDOW_S`` apart, not straddling a reported
    segment start in ``boundaries``) breaks when its translation error exceeds max(3 m, 50 % of the
    true motion) or its rotation error exceeds 15 deg. Consecutive breaking windows count once.

    Args:
        times_s: (N,) frame times. T_est: (N, 4, 4) odometry poses (NaN rows for missing frames).
        T_gt: (N, 4, 4) ground-truth poses of the same frames.
        boundaries: frame indices where the system started a new odometry segment.
    """
    ok = np.isfinite(T_est.reshape(len(T_est), -1)).all(axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < 2:
        return 0
    j = np.searchsorted(times_s[idx], times_s[idx] + BREAK_WINDOW_S)
    valid = j < len(idx)
    i_f, j_f = idx[valid], idx[j[valid]]
    if boundaries:
        b = np.array(sorted(boundaries))
        straddle = np.searchsorted(b, i_f, side="right") != np.searchsorted(b, j_f, side="right")
        i_f, j_f = i_f[~straddle], j_f[~straddle]
    if len(i_f) == 0:
        return 0
    rel_est = se3.inverse(T_est[i_f]) @ T_est[j_f]
    rel_gt = se3.inverse(T_gt[i_f]) @ T_gt[j_f]
    err = se3.inverse(rel_gt) @ rel_est
    t_err = np.linalg.norm(err[:, :3, 3], axis=1)
    cos = np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    r_err = np.degrees(np.arccos(cos))
    broken = (t_err > np.maximum(3.0, 0.5 * np.linalg.norm(rel_gt[:, :3, 3], axis=1))) | (r_err > 15.0)
    starts = broken & ~np.concatenate([[False], broken[:-1]])
    return int(starts.sum())


def poses_by_time(path: Path, times_s: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses of a TUM file at the sequence's frame times (NaN where the file has none)."""
    out = np.full((len(times_s), 4, 4), np.nan)
    if not path.is_file() or path.stat().st_size == 0:
        return out
    t, T = read_tum(path)
    k = np.searchsorted(times_s, t)
    k = np.clip(k, 0, len(times_s) - 1)
    hit = np.abs(times_s[k] - t) < 1e-3
    out[k[hit]] = T[hit]
    return out


@dataclass(frozen=True)
class PlacementError:
    """How far one robot's fused trajectory is from the truth (metres; NaN without placed poses).

    Attributes:
        placement_m: how far the best rigid fit (yaw + translation) moves its gauge-fixed trajectory onto the truth
            (RMS over its placed poses; NaN with fewer than 3): where it was placed, not its own drift.
        ate_m: fused ATE once the shared frame's gauge is fixed by the reference's trajectory.
        ate_raw_m: fused ATE with no alignment at all (the shared frame as the system defines it).
        max_m: the largest gauge-fixed position error.
    """

    placement_m: float
    ate_m: float
    ate_raw_m: float
    max_m: float


def placement_errors(
    fused: list[np.ndarray], gt_world: list[np.ndarray], up_world: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> list[PlacementError]:
    """Judge each robot's placement in the shared frame, the first robot being the reference (``judge_run``).

    The shared frame is the reference's first camera frame, so a small heading error of that one estimated pose
    turns every robot's whole trajectory by the same amount: the gauge, not a placement error. One rigid
    transform (yaw about the world's vertical + translation; a straight reference drive leaves the roll about
    its own line undetermined in a 6-DoF fit) lays the reference's fused trajectory onto its truth and is
    applied to every robot alike; each robot's placement error is then what its own best rigid fit still moves.

    Args:
        fused: per robot, (N_k, 4, 4) fused ``T_shared_cam`` at its frames, NaN where not placed.
        gt_world: per robot, (N_k, 4, 4) ground truth ``T_world_cam`` in one world frame (all robots').
        up_world: the world frame's vertical (the simulator's worlds: z up).
    """
    T_ref_world = se3.inverse(gt_world[0][0])
    up_shared = T_ref_world[:3, :3] @ np.asarray(up_world, dtype=np.float64)
    placed = [np.isfinite(f.reshape(len(f), -1)).all(axis=1) for f in fused]
    T_gauge = np.eye(4)
    if placed[0].sum() >= 3:
        ref_gt = T_ref_world @ gt_world[0][placed[0]]
        T_gauge = se3.kabsch_yaw(fused[0][placed[0], :3, 3], ref_gt[:, :3, 3], up=up_shared)
    out = []
    for f, gt, ok in zip(fused, gt_world, placed, strict=True):
        truth = (T_ref_world @ gt[ok])[:, :3, 3]
        xyz = f[ok, :3, 3]
        xyz_g = se3.transform_points(T_gauge, xyz)
        err = np.linalg.norm(xyz_g - truth, axis=1)
        raw = np.linalg.norm(xyz - truth, axis=1)
        placement = float("nan")
        if ok.sum() >= 3:
            T_fit = se3.kabsch_yaw(xyz_g, truth, up=up_shared)
            placement = float(np.sqrt(np.mean(np.sum((se3.transform_points(T_fit, xyz_g) - xyz_g) ** 2, axis=1))))
        out.append(PlacementError(placement, _rms(err), _rms(raw), float(err.max()) if err.size else float("nan")))
    return out


def _rms(values: np.ndarray) -> float:
    """Root mean square of (N,) values; NaN when empty."""
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def judge_run(
    run_dir: Path, world: Path, robots: list[str], mode: InputMode, scenario: str, seed: int, metrics: dict
) -> list[RobotVerdict]:
    """Judge every robot of one finished run against ground truth (reads the results folder).

    The shared frame is the reference robot's first camera frame, so a small heading error of that one
    estimated pose turns every robot's whole trajectory by the same amount: the gauge, not a placement
    error. Placement is therefore judged after one rigid transform (yaw about the vertical +
    translation) that lays the *reference's* fused trajectory onto its ground truth, applied to every
    robot alike (a robot merged in the wrong place stays wrong; the reference's own error is its aligned
    ATE). ``ate_fused_raw_m`` keeps the error with no alignment at all.
    """
    scen = json.loads((world / "scenario.json").read_text())
    shared = scen.get("overlap", {}).get("shared_view_m", {})
    reports = {r["name"]: r for r in metrics.get("robots", [])}
    server = run_dir / "server.json"
    server_robots = json.loads(server.read_text()).get("robots", {}) if server.is_file() else {}
    loaded = []
    for name in robots:
        seq = open_sequence(str(world / name))
        times = np.asarray(seq.timestamps_s, dtype=np.float64)
        if seq.gt_poses is None:
            raise DataError(f"{world / name} has no poses.txt: the held-out benchmark needs ground truth")
        fused = poses_by_time(run_dir / f"{name}_fused_tum.txt", times)
        loaded.append((name, times, seq.gt_poses, fused))
    errors = placement_errors([fused for *_, fused in loaded], [gt for _, _, gt, _ in loaded])
    verdicts = []
    for k, ((name, times, gt, fused), e) in enumerate(zip(loaded, errors, strict=True)):
        overlaps = max(shared.get(name, {}).values(), default=0.0) >= MIN_SHARED_VIEW_M
        odo = poses_by_time(run_dir / f"{name}_odometry_tum.txt", times)
        rep = reports.get(name, {})
        boundaries = set(rep.get("segment_start_frames", []) or [])
        placed = np.isfinite(fused.reshape(len(times), -1)).all(axis=1)
        frac = float(placed.mean()) if len(times) else 0.0
        notes = []
        if placed.sum() >= 3:
            outcome = Outcome.RIGHT if e.placement_m <= PLACED_RIGHT_M[mode] else Outcome.WRONG
            if k == 0:  # the reference defines the frame: judged on its own fused trajectory's error
                outcome = Outcome.RIGHT if e.ate_m <= PLACED_RIGHT_M[mode] else Outcome.WRONG
            elif not overlaps:
                outcome = Outcome.WRONG
                notes.append("merged a robot that shares no view with any other")
        else:
            outcome = Outcome.NOT_PLACED if overlaps else Outcome.RIGHT
        if 0 < frac < 0.999 and placed.sum() >= 3:
            notes.append(f"{frac:.0%} of frames placed")
        free_m = rep.get("path_from_closures_m")
        if outcome is Outcome.WRONG and free_m is not None:  # placed by closures, then off on its own odometry?
            notes.append(f"{free_m:.0f} m of its path on its own odometry, away from its closures")
        provisional = bool(rep.get("provisional")) and placed.sum() >= 3
        if provisional:
            notes.append("provisional: the run flagged this place as unconfirmed")
        waiting = outcome is Outcome.NOT_PLACED and bool(server_robots.get(name, {}).get("waiting"))
        if waiting:
            notes.append("matches accepted, but too few independent ones to enter the shared frame")
        verdicts.append(
            RobotVerdict(
                scenario=scenario,
                seed=seed,
                mode=mode.value,
                robot=name,
                reference=k == 0,
                overlaps=overlaps,
                outcome=outcome.value,
                placed_fraction=frac,
                placement_error_m=e.placement_m,
                ate_fused_m=e.ate_m,
                ate_fused_raw_m=e.ate_raw_m,
                max_error_m=e.max_m,
                ate_odometry_aligned_m=_number(rep.get("ate_odometry_aligned_m")),
                odometry_breaks=odometry_breaks(times, odo, gt, boundaries),
                failures_detected=int(rep.get("odometry_failures", 0) or 0),
                path_length_m=_number(rep.get("path_length_m")),
                notes=notes,
                provisional=provisional,
                waiting=waiting,
            )
        )
    return verdicts


def _number(value: object) -> float:
    """A metrics.json number (null for 'not measured') as a float (NaN)."""
    return float("nan") if value is None else float(value)
