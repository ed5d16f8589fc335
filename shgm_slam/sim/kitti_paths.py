"""Real KITTI ground-truth drives as robot trajectories, placed in one z-up world.

Each KITTI poses file has its own origin (its first camera). We rotate them into our z-up world,
flatten them onto a flat road (camera 1.65 m above z = 0, rotations kept) and align every further
drive onto the first one with a 4-DoF (yaw + translation) trimmed ICP on the 2-D tracks, started from a
coarse yaw search; the measured overlap and residual are reported. KITTI 07 frames ~80-354 and 00
frames ~2646-2900 drive the same street on different days, the default robot pair.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.errors import DataError, SimulationError
from shgm_slam.geometry.se3 import kabsch_yaw, make_pose, rot_z
from shgm_slam.io.trajectories import read_kitti_poses
from shgm_slam.sim.trajectories import CAR_CAMERA_HEIGHT_M, RobotKind, Trajectory, resample_path

DEFAULT_KITTI_ROOT = Path(__file__).resolve().parents[3] / "shared" / "data" / "kitti"
"""``../shared/data/kitti`` next to the repository (real data is never part of the repository)."""
DEFAULT_KITTI_ROBOTS = ("00:2600-2900", "07:0-350")

R_WORLD_KITTI = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation from KITTI's first-camera frame (x right, y down, z forward) to a z-up world."""


@dataclass(frozen=True)
class KittiDrive:
    """A frame range of a KITTI ground-truth sequence: ``seq`` and frames ``start..end`` inclusive."""

    seq: str
    start: int
    end: int

    @property
    def name(self) -> str:
        return f"kitti{self.seq}"

    @staticmethod
    def parse(spec: str) -> KittiDrive:
        """``"07:0-350"`` -> KittiDrive("07", 0, 350)."""
        try:
            seq, rng = spec.split(":")
            a, b = (int(x) for x in rng.split("-"))
        except ValueError:
            raise SimulationError(f"bad KITTI drive {spec!r}; write SEQ:START-END, e.g. 07:0-350") from None
        if a < 0 or b <= a:
            raise SimulationError(f"bad KITTI frame range in {spec!r}: need 0 <= START < END")
        return KittiDrive(seq.zfill(2), a, b)


def load_drive(root: Path, drive: KittiDrive) -> np.ndarray:
    """(N, 4, 4) KITTI poses of ``drive`` mapped into a z-up frame and flattened onto z = 1.65 m."""
    path = root / "poses" / f"{drive.seq}.txt"
    if not path.is_file():
        raise SimulationError(
            f"the kitti-paths scenario needs KITTI ground truth at {path}; put the KITTI odometry poses "
            f"there or pass --kitti-root DIR (a folder with poses/{drive.seq}.txt)"
        )
    try:
        poses = read_kitti_poses(path)
    except DataError as exc:
        raise SimulationError(f"cannot use {path}: {exc}") from None
    if drive.end >= len(poses):
        raise SimulationError(
            f"{path} has {len(poses)} poses; frame range {drive.start}-{drive.end} is outside it"
        )
    T = poses[drive.start : drive.end + 1].copy()
    T_world_kitti = make_pose(R_WORLD_KITTI, np.zeros(3))
    T = T_world_kitti @ T
    T[:, 2, 3] = CAR_CAMERA_HEIGHT_M
    return T


def _icp_yaw(src_xy: np.ndarray, tree: cKDTree, dst_xy: np.ndarray, yaw0: float, iters: int = 40):
    """Trimmed 2-D ICP from a start yaw (about the centroids); returns (T_dst_src (4, 4), inlier mask)."""
    src3 = np.column_stack([src_xy, np.zeros(len(src_xy))])
    dst3 = np.column_stack([dst_xy, np.zeros(len(dst_xy))])
    R0 = rot_z(yaw0)
    T = make_pose(R0, np.r_[dst_xy.mean(0), 0.0] - R0 @ np.r_[src_xy.mean(0), 0.0])
    gate = 40.0
    ok = np.zeros(len(src_xy), bool)
    for _ in range(iters):
        moved = src3 @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(moved[:, :2])
        ok = d < gate
        if ok.sum() < 10:
            break
        T = kabsch_yaw(src3[ok], dst3[j[ok]])
        gate = max(3.0, 0.7 * gate)
    return T, ok


def align_drive(T_ref: np.ndarray, T_src: np.ndarray, min_overlap: float = 0.3) -> tuple[np.ndarray, dict]:
    """Yaw + translation ``T_ref_src`` that lays drive ``src`` onto drive ``ref`` where they overlap.

    Args:
        T_ref, T_src: (N, 4, 4) / (M, 4, 4) poses in their own z-up frames.
        min_overlap: fraction of ``src`` that must end within 3 m of ``ref``.

    Returns: the (4, 4) transform and stats (overlap fraction and length, RMSE of the overlap, metres).
    """
    ref = resample_path(T_ref[:, :2, 3], 1.0)
    src = resample_path(T_src[:, :2, 3], 1.0)
    tree = cKDTree(ref)
    best = None
    for yaw0 in np.radians(np.arange(0.0, 360.0, 10.0)):  # coarse search, then ICP refines
        T, _ = _icp_yaw(src, tree, ref, yaw0)
        moved = src @ T[:2, :2].T + T[:2, 3]
        d = tree.query(moved)[0]
        score = int((d < 3.0).sum())
        if best is None or score > best[0]:
            best = (score, T, d)
    score, T, d = best
    near = d < 3.0
    if score < min_overlap * len(src):
        raise SimulationError(
            f"could not find where the drives overlap (only {score} of {len(src)} m within 3 m); "
            "choose KITTI frame ranges that drive the same street (e.g. 00:2600-2900 and 07:0-350)"
        )
    stats = {
        "overlap_fraction": round(float(near.mean()), 3),
        "overlap_length_m": round(float(near.sum()), 1),
        "rmse_m": round(float(np.sqrt(np.mean(d[near] ** 2))), 3),
        "yaw_deg": round(float(np.degrees(np.arctan2(T[1, 0], T[0, 0]))), 3),
        "translation_m": [round(float(v), 3) for v in T[:2, 3]],
    }
    return T, stats


def kitti_trajectories(
    root: Path | None, specs: tuple[str, ...] = DEFAULT_KITTI_ROBOTS, fps: float = 10.0
) -> tuple[list[Trajectory], dict]:
    """Trajectories of the KITTI drives ``specs`` in one world (the first drive's, z up).

    Returns the trajectories (KITTI's 10 Hz frames, timestamps ``k / fps``) and per-robot alignment stats.
    """
    root = Path(root) if root is not None else DEFAULT_KITTI_ROOT
    drives = [KittiDrive.parse(s) for s in specs]
    if len({d.name for d in drives}) != len(drives):
        raise SimulationError(f"KITTI drives {specs} repeat a sequence; use each sequence once")
    poses = [load_drive(root, d) for d in drives]
    notes: dict = {drives[0].name: {"reference": True, "frames": [drives[0].start, drives[0].end]}}
    for k in range(1, len(drives)):
        T, stats = align_drive(poses[0], poses[k])
        poses[k] = T @ poses[k]
        notes[drives[k].name] = {**stats, "frames": [drives[k].start, drives[k].end]}
    robots = [
        Trajectory(d.name, RobotKind.CAR, T, np.arange(len(T)) / fps)
        for d, T in zip(drives, poses, strict=True)
    ]
    return robots, notes
