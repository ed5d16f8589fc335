"""Trajectory files: KITTI (12 numbers a row) and TUM (``t tx ty tz qx qy qz qw``) poses that evo reads.

Poses are (N, 4, 4) float64 ``T_world_cam`` stacks (metres). Readers validate every row: the column
count, finite numbers, and that the rotation part is a rotation. Small rounding errors (max
|RᵀR - I| <= ``ROTATION_TOLERANCE``) are re-orthonormalized with ``project_to_so3``; anything worse
is rejected with a ``DataError`` naming the file and line.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from shgm_slam.errors import DataError
from shgm_slam.geometry.se3 import project_to_so3

ROTATION_TOLERANCE = 1e-2
"""Largest max |RᵀR - I| (or | |q| - 1 | for TUM quaternions) repaired instead of rejected."""
_REPAIR_ABOVE = 1e-6  # rows this close to orthonormal are kept exactly as written
TIME_TOLERANCE_S = 1e-4
"""Two poses (a TUM row and a frame, a fused and a ground-truth pose) are of the same instant when their
timestamps differ by less than this."""


class PoseFormat(str, Enum):
    KITTI = "kitti"
    TUM = "tum"


@dataclass
class PoseFile:
    """Contents of a pose file: (N,) seconds or None (KITTI has no times), (N, 4, 4) poses."""

    timestamps_s: np.ndarray | None
    poses: np.ndarray
    format: PoseFormat = PoseFormat.KITTI


def _check_poses(poses: np.ndarray, path: Path) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise DataError(f"cannot write {path}: poses must be an (N, 4, 4) stack, got shape {poses.shape}")
    if not np.isfinite(poses).all():
        raise DataError(f"cannot write {path}: poses contain non-finite numbers (NaN/inf)")
    return poses


def format_kitti_pose(T_world_cam: np.ndarray) -> str:
    """One KITTI row (no newline): the row-major top 3x4 of a (4, 4) pose, 12 numbers ``%.9f``."""
    return " ".join(f"{v:.9f}" for v in np.asarray(T_world_cam, dtype=np.float64)[:3, :4].ravel())


def write_kitti_poses(path: Path | str, poses: np.ndarray, *, comment: str = "") -> None:
    """Write (N, 4, 4) poses as KITTI rows (12 numbers, ``%.9f``); creates the parent folder.

    ``comment`` (one line) goes first as a ``# `` line, which evo and ``read_kitti_poses`` skip."""
    path = Path(path)
    poses = _check_poses(poses, path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, poses[:, :3, :4].reshape(-1, 12), fmt="%.9f", header=_one_line(comment))


def write_tum(path: Path | str, timestamps_s: np.ndarray, poses: np.ndarray, *, comment: str = "") -> None:
    """Write a TUM file: ``t tx ty tz qx qy qz qw`` (8 columns, scalar-last quaternion, no trailing space).

    Args:
        timestamps_s: (N,) seconds. poses: (N, 4, 4) ``T_world_cam``.
        comment: one line written first as a ``# `` line (evo and ``read_tum`` skip it).
    """
    path = Path(path)
    poses = _check_poses(poses, path)
    t = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
    if t.shape[0] != poses.shape[0] or not np.isfinite(t).all():
        raise DataError(
            f"cannot write {path}: need one finite timestamp per pose "
            f"({t.shape[0]} times, {poses.shape[0]} poses)"
        )
    q_xyzw = Rotation.from_matrix(project_to_so3(poses[:, :3, :3])).as_quat()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.c_[t, poses[:, :3, 3], q_xyzw], fmt=["%.9f"] + ["%.9f"] * 7, header=_one_line(comment))


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def read_comments(path: Path | str) -> list[str]:
    """The ``#`` comment lines of a pose file, without the ``#`` (e.g. a fused trajectory's provisional note).

    Raises:
        DataError: the file is missing or unreadable.
    """
    _, text = _read_text(path)
    return [line.strip().lstrip("#").strip() for line in text.splitlines() if line.strip().startswith("#")]


def _read_text(path: Path | str) -> tuple[Path, str]:
    path = Path(path)
    if not path.is_file():
        what = "is a directory, not a file" if path.is_dir() else "does not exist"
        raise DataError(f"pose file {path} {what}; check the path")
    try:
        return path, path.read_text()
    except UnicodeDecodeError as e:  # (Python's text named a codec and a byte position, not the problem)
        raise DataError(f"pose file {path} is not UTF-8 text (byte {e.start}): a binary file, or another encoding? "
                        "give KITTI or TUM rows of numbers as plain text") from None  # fmt: skip
    except OSError as e:
        raise DataError(f"cannot read pose file {path}: {e}") from e


def _read_rows(path: Path | str) -> tuple[Path, list[int], list[list[str]]]:
    """Non-empty, non-comment rows of a text file split on whitespace, with their 1-based line numbers."""
    path, text = _read_text(path)
    numbers, rows = [], []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            numbers.append(i)
            rows.append(s.replace(",", " ").split())
    return path, numbers, rows


def _to_array(path: Path, line_nos: list[int], rows: list[list[str]], ncols: int, what: str) -> np.ndarray:
    """(N, ncols) float64 of the rows; DataError naming the line for a bad count, word or NaN."""
    for ln, row in zip(line_nos, rows, strict=True):
        if len(row) != ncols:
            raise DataError(
                f"{path} line {ln}: expected {ncols} numbers per row ({what}), got {len(row)}; "
                "fix or remove that line"
            )
    try:
        values = np.array(rows, dtype=np.float64).reshape(-1, ncols)
    except ValueError as e:
        bad = next(ln for ln, row in zip(line_nos, rows, strict=True) if not _all_float(row))
        raise DataError(f"{path} line {bad}: not a number ({e}); fix that line") from e
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        raise DataError(f"{path} line {line_nos[int(np.argmin(finite))]}: non-finite number (NaN/inf)")
    return values


MAX_TRANSLATION_M = 1e9
"""Positions farther than this (metres) are refused, as in graph files: distances would overflow."""


def _all_float(row: list[str]) -> bool:
    try:
        [float(v) for v in row]
    except ValueError:
        return False
    return True


def _validated_rotations(R: np.ndarray, path: Path, line_numbers: list[int]) -> np.ndarray:
    """(N, 3, 3) rotations, re-orthonormalized when slightly off; DataError when far off or reflected."""
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2)) if len(R) else np.zeros(0)
    bad = (err > ROTATION_TOLERANCE) | (np.linalg.det(R) <= 0.0) if len(R) else np.zeros(0, dtype=bool)
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(
            f"{path} line {line_numbers[i]}: the 3x3 part is not a rotation (max |RᵀR - I| = {err[i]:.3g}, "
            f"det = {np.linalg.det(R[i]):.3g}); the file is not a pose file or is corrupt"
        )
    repair = err > _REPAIR_ABOVE
    if repair.any():
        R = R.copy()
        R[repair] = project_to_so3(R[repair])
    return R


def read_kitti_poses(path: Path | str) -> np.ndarray:
    """Read a KITTI pose file (12 numbers a row, row-major top 3x4) into (N, 4, 4) float64 poses."""
    path, line_numbers, rows = _read_rows(path)
    values = _to_array(path, line_numbers, rows, 12, "KITTI: r11 r12 r13 tx r21 ... tz")
    poses = np.tile(np.eye(4), (values.shape[0], 1, 1))
    poses[:, :3, :4] = values.reshape(-1, 3, 4)
    poses[:, :3, :3] = _validated_rotations(poses[:, :3, :3], path, line_numbers)
    _check_translations(poses[:, :3, 3], path, line_numbers)
    return poses


def _check_translations(t_xyz: np.ndarray, path: Path, line_numbers: list[int]) -> None:
    """DataError when a (N, 3) translation lies farther than ``MAX_TRANSLATION_M`` (overflows downstream)."""
    far = np.abs(t_xyz).max(axis=1) > MAX_TRANSLATION_M if len(t_xyz) else np.zeros(0, dtype=bool)
    if far.any():
        i = int(np.argmax(far))
        raise DataError(f"{path} line {line_numbers[i]}: a position farther than {MAX_TRANSLATION_M:g} m from the "
                        "origin; positions are metres (the file's units or columns are wrong)")


def read_tum(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file (``t tx ty tz qx qy qz qw``, '#' comments) into ((N,) seconds, (N, 4, 4) poses)."""
    path, line_numbers, rows = _read_rows(path)
    values = _to_array(path, line_numbers, rows, 8, "TUM: t tx ty tz qx qy qz qw")
    q_xyzw = values[:, 4:8]
    norm = np.linalg.norm(q_xyzw, axis=1)
    bad = np.abs(norm - 1.0) > ROTATION_TOLERANCE
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(
            f"{path} line {line_numbers[i]}: quaternion norm {norm[i]:.4g} is not 1; "
            "TUM rows are 't tx ty tz qx qy qz qw' with a unit quaternion"
        )
    poses = np.tile(np.eye(4), (values.shape[0], 1, 1))
    if len(values):
        poses[:, :3, :3] = Rotation.from_quat(q_xyzw / norm[:, None]).as_matrix()
    poses[:, :3, 3] = values[:, 1:4]
    _check_translations(poses[:, :3, 3], path, line_numbers)
    steps = np.diff(values[:, 0])
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0])
        raise DataError(
            f"{path} line {line_numbers[k + 1]}: timestamp {values[k + 1, 0]:g} s is not after the previous row's "
            f"{values[k, 0]:g} s; TUM rows must be in time order, one per time"
        )
    return values[:, 0].copy(), poses


def associate(t_est: np.ndarray, t_gt: np.ndarray, tol_s: float = TIME_TOLERANCE_S) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (est rows, gt rows) of the same instants: nearest gt time within ``tol_s`` (seconds)."""
    if t_gt.size == 0 or t_est.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(t_gt)
    ts = t_gt[order]
    after = np.searchsorted(ts, t_est).clip(0, len(ts) - 1)
    before = (after - 1).clip(0)
    pick = np.where(np.abs(ts[before] - t_est) < np.abs(ts[after] - t_est), before, after)
    ok = np.abs(ts[pick] - t_est) < tol_s
    return np.flatnonzero(ok), order[pick[ok]]


def read_poses_file(path: Path | str) -> PoseFile:
    """Read KITTI (12 columns) or TUM (8 columns) poses, detected from the first data row."""
    checked, line_numbers, rows = _read_rows(path)
    if not rows:
        raise DataError(f"pose file {checked} has no pose rows; write KITTI (12 numbers) or TUM (8) rows")
    ncols = len(rows[0])
    if ncols == 12:
        return PoseFile(None, read_kitti_poses(checked), PoseFormat.KITTI)
    if ncols == 8:
        t, poses = read_tum(checked)
        return PoseFile(t, poses, PoseFormat.TUM)
    raise DataError(
        f"{checked} line {line_numbers[0]}: {ncols} columns is neither KITTI (12 numbers) nor TUM "
        "(8: t tx ty tz qx qy qz qw)"
    )
