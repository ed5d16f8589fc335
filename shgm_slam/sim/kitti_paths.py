"""Real KITTI ground-truth drives as robot trajectories, placed in one z-up world.

A drive is a half-open frame range ``SEQ:START-END`` (frames START..END-1) of a KITTI odometry
ground-truth file ``<root>/poses/SEQ.txt``; ``SEQ`` alone is the whole sequence. Each KITTI poses file
has its own origin (its first camera). We rotate them into our z-up world and flatten them onto a flat
road (camera 1.65 m above z = 0, rotations kept). Drives cut from the *same* sequence keep that
sequence's frame (no alignment: they already share it, as the paper's three robots cut from 08 do).
Every further sequence is aligned onto the first one with a 4-DoF (yaw + translation) trimmed ICP on the
2-D tracks, started from a coarse yaw search; the measured overlap and residual are reported. KITTI 07
frames ~80-354 and 00 frames ~2646-2900 drive the same street on different days, the default robot pair.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.errors import ConfigError, DataError, SimulationError
from shgm_slam.geometry.se3 import kabsch_yaw, make_pose, rot_z
from shgm_slam.io.trajectories import read_kitti_poses
from shgm_slam.sim.trajectories import CAR_CAMERA_HEIGHT_M, RobotKind, Trajectory, resample_path

DEFAULT_KITTI_ROOT = Path(__file__).resolve().parents[3] / "shared" / "data" / "kitti"
"""``../shared/data/kitti`` next to the repository (real data is never part of the repository)."""
DEFAULT_KITTI_ROBOTS = ("00:2600-2901", "07:0-351")
"""The default pair: 00 frames 2600-2900 and 07 frames 0-350 (half-open ranges, ends excluded)."""
KITTI_FPS = 10.0
"""Frame rate of KITTI's odometry sequences (their poses files have one row per frame)."""
KITTI_GT_SEQUENCES = tuple(f"{k:02d}" for k in range(11))
"""KITTI odometry publishes ground-truth poses for sequences 00-10 only (11-21 are its test set)."""

R_WORLD_KITTI = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation from KITTI's first-camera frame (x right, y down, z forward) to a z-up world."""

_DRIVE_RE = re.compile(r"^(?P<seq>\d{1,2})(?::(?P<start>\d+)-(?P<end>\d*))?$")


MIN_DRIVE_FRAMES = 3
"""Fewest frames of a drive: its path's direction of travel (a numerical gradient) needs three."""
MAX_FRAME_DIGITS = 9
"""Most digits of a drive's frame number: KITTI's longest sequence has 4,661 frames; a number of thousands of
digits stopped Python's ``int`` with a traceback."""


@dataclass(frozen=True)
class KittiDrive:
    """A half-open frame range ``[start, end)`` of a KITTI ground-truth sequence ``seq`` ("00".."21").

    ``end`` None means "to the end of the sequence".
    """

    seq: str
    start: int = 0
    end: int | None = None

    @property
    def name(self) -> str:
        """The robot name of a drive whose sequence is used once (``kitti07``); see ``drive_names``."""
        return f"kitti{self.seq}"

    @property
    def spec(self) -> str:
        return f"{self.seq}:{self.start}-{'' if self.end is None else self.end}"

    @staticmethod
    def parse(spec: str) -> KittiDrive:
        """``"07:0-350"`` -> KittiDrive("07", 0, 350) (frames 0..349); ``"08"`` -> the whole of 08;
        ``"08:3000-"`` -> frames 3000 to the end.

        Raises:
            ConfigError: not ``SEQ[:START-END]``, a sequence outside KITTI's 00-21, or an empty range.
        """
        m = _DRIVE_RE.match(spec.strip())
        if not m:
            raise ConfigError(
                f"bad KITTI drive {spec!r} (--kitti-drive); write SEQ:START-END (half-open: frames START..END-1), "
                "e.g. 07:0-350, or SEQ alone for the whole sequence"
            )
        seq = m["seq"].zfill(2)
        if int(seq) > 21:
            raise ConfigError(f"unknown KITTI sequence {seq!r} in {spec!r}; KITTI odometry has sequences 00-21")
        if m["start"] is None:
            return KittiDrive(seq)
        if max(len(m["start"]), len(m["end"])) > MAX_FRAME_DIGITS:
            shown = spec if len(spec) <= 30 else f"{spec[:24]}..."
            raise ConfigError(
                f"KITTI drive {shown!r}: a frame number of more than {MAX_FRAME_DIGITS} digits; KITTI's "
                "sequences have at most 4661 frames (--kitti-drive SEQ:START-END, e.g. 07:0-350)"
            )
        start = int(m["start"])
        end = int(m["end"]) if m["end"] else None
        if end is not None and end <= start:
            raise ConfigError(
                f"empty KITTI frame range in {spec!r}: START-END is half-open (frames START..END-1), "
                "so END must be greater than START"
            )
        return KittiDrive(seq, start, end)


def drive_names(drives: list[KittiDrive]) -> list[str]:
    """Robot names: ``kitti07`` for a sequence used once, ``kitti08a``, ``kitti08b``, ... (in the order
    given) for several drives cut from one sequence. All match the runner's robot-name rule."""
    count: dict[str, int] = {}
    for d in drives:
        count[d.seq] = count.get(d.seq, 0) + 1
    seen: dict[str, int] = {}
    names = []
    for d in drives:
        if count[d.seq] == 1:
            names.append(d.name)
            continue
        k = seen.get(d.seq, 0)
        seen[d.seq] = k + 1
        names.append(f"{d.name}{_letters(k)}")
    return names


def _letters(k: int) -> str:
    """0 -> a, 25 -> z, 26 -> ba, ... (base-26 letters)."""
    out = ""
    while True:
        out = chr(ord("a") + k % 26) + out
        k //= 26
        if k == 0:
            return out


def read_sequence_poses(root: Path, seq: str) -> np.ndarray:
    """(N, 4, 4) KITTI ground truth ``T_cam0_cam`` of sequence ``seq`` from ``<root>/poses/<seq>.txt``.

    Raises:
        DataError: the poses folder or file is missing or unreadable.
        ConfigError: a sequence without public ground truth (11-21) and no file for it.
    """
    folder = Path(root) / "poses"
    path = folder / f"{seq}.txt"
    if not folder.is_dir():
        raise DataError(
            f"the kitti-paths scenario needs KITTI ground truth at {folder}/NN.txt, but there is no {folder}; "
            "put the KITTI odometry poses there or pass --kitti-root DIR (a folder with poses/)"
        )
    if not path.is_file():
        if seq not in KITTI_GT_SEQUENCES:
            raise ConfigError(
                f"KITTI sequence {seq} has no public ground truth (only 00-10 do) and {path} does not exist"
            )
        raise DataError(
            f"the kitti-paths scenario needs KITTI ground truth at {path}; put the KITTI odometry poses "
            f"there or pass --kitti-root DIR (a folder with poses/{seq}.txt)"
        )
    try:
        return read_kitti_poses(path)
    except DataError as exc:
        raise DataError(f"cannot use {path}: {exc}") from None


def drive_frames(drive: KittiDrive, num_poses: int) -> tuple[int, int]:
    """The half-open ``(start, end)`` of ``drive`` in a sequence of ``num_poses`` frames.

    Raises:
        DataError: the range reaches outside the sequence.
        ConfigError: it holds fewer than ``MIN_DRIVE_FRAMES`` frames.
    """
    end = num_poses if drive.end is None else drive.end
    if drive.start >= num_poses or end > num_poses:
        raise DataError(
            f"KITTI {drive.seq} has {num_poses} poses (frames 0-{num_poses}, half-open); frame range "
            f"{drive.spec} is outside it: give START below {num_poses} and END at most {num_poses} (--kitti-drive)"
        )
    if end - drive.start < MIN_DRIVE_FRAMES:
        raise ConfigError(
            f"KITTI drive {drive.spec} has {end - drive.start} frame(s); a drive needs at least {MIN_DRIVE_FRAMES} "
            "(frame ranges are half-open: START-END holds frames START..END-1)"
        )
    return drive.start, end


def kitti_to_world(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) KITTI poses (first camera = origin) rotated into the z-up world, flattened onto
    z = 1.65 m (rotations kept). Drives of one sequence map through the same transform."""
    T = make_pose(R_WORLD_KITTI, np.zeros(3)) @ poses
    T[:, 2, 3] = CAR_CAMERA_HEIGHT_M
    return T


def load_drive(root: Path, drive: KittiDrive) -> np.ndarray:
    """(N, 4, 4) KITTI poses of ``drive`` mapped into a z-up frame and flattened onto z = 1.65 m."""
    poses = read_sequence_poses(Path(root), drive.seq)
    start, end = drive_frames(drive, len(poses))
    return kitti_to_world(poses[start:end].copy())


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


def _track_xy(drives: np.ndarray | list[np.ndarray]) -> np.ndarray:
    """(M, 2) positions every 1 m along one (N, 4, 4) pose stack or along each of several (concatenated)."""
    stacks = drives if isinstance(drives, list) else [drives]
    return np.concatenate([resample_path(T[:, :2, 3], 1.0) for T in stacks])


def align_drive(
    T_ref: np.ndarray | list[np.ndarray],
    T_src: np.ndarray | list[np.ndarray],
    min_overlap: float = 0.3,
    min_overlap_m: float = 150.0,
) -> tuple[np.ndarray, dict]:
    """Yaw + translation ``T_ref_src`` that lays drive ``src`` onto drive ``ref`` where they overlap.

    Args:
        T_ref, T_src: (N, 4, 4) / (M, 4, 4) poses in their own z-up frames, or lists of such stacks that
            share one frame (several drives of one sequence).
        min_overlap, min_overlap_m: the fraction of ``src`` that must end within 3 m of ``ref``, or failing
            that the metres of it (long drives, e.g. whole sequences, share a small fraction).

    The transform is *an* alignment under which the drives share street, which is all a generated world
    needs; for drives of different days it need not be KITTI's true relation (07 onto the whole of 00
    finds 254 m of fit at another place than the street they really share).

    Returns: the (4, 4) transform and stats (overlap fraction and length, RMSE of the overlap, metres).
    """
    ref = _track_xy(T_ref)
    src = _track_xy(T_src)
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
    if score < min(min_overlap * len(src), min_overlap_m):
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
    """Trajectories of the KITTI drives ``specs`` (``SEQ[:START-END]``, half-open) in one world, z up.

    The first drive's sequence defines the world; every drive of that sequence keeps it as it is.
    Each further sequence is aligned onto the drives placed so far (all of its drives together, by one
    transform, so drives of one sequence always share that sequence's frame). Robot names: ``drive_names``.

    Returns the trajectories (KITTI's 10 Hz frames sampled at ``fps``: ``at_frame_rate``) and per-robot notes
    (frames, sequence, and for aligned sequences the alignment stats).

    Raises:
        ConfigError: no drives, or a malformed/unknown/empty drive spec.
        DataError: missing poses, or a range outside its sequence.
        SimulationError: a sequence whose drives do not overlap the drives placed before.
    """
    root = Path(root) if root is not None else DEFAULT_KITTI_ROOT
    if not specs:
        raise ConfigError("kitti-paths needs at least one KITTI drive (SEQ:START-END)")
    drives = [KittiDrive.parse(s) for s in specs]
    names = drive_names(drives)
    if len(set(drives)) != len(drives):
        dup = next(d.spec for k, d in enumerate(drives) if d in drives[:k])
        raise ConfigError(f"KITTI drive {dup} is given twice; two robots on the very same frames see the same")
    sequences = {d.seq: read_sequence_poses(root, d.seq) for d in drives}
    frames = [drive_frames(d, len(sequences[d.seq])) for d in drives]
    poses = [kitti_to_world(sequences[d.seq][a:b].copy()) for d, (a, b) in zip(drives, frames, strict=True)]
    notes: dict = {}
    ref_seq = drives[0].seq
    placed = [k for k, d in enumerate(drives) if d.seq == ref_seq]
    for k in placed:
        notes[names[k]] = {"reference": True, "sequence": ref_seq, "frames": list(frames[k])}
    for seq in dict.fromkeys(d.seq for d in drives):
        if seq == ref_seq:
            continue
        mine = [k for k, d in enumerate(drives) if d.seq == seq]
        T, stats = align_drive([poses[k] for k in placed], [poses[k] for k in mine])
        for k in mine:
            poses[k] = T @ poses[k]
            notes[names[k]] = {**stats, "sequence": seq, "frames": list(frames[k])}
        placed += mine
    robots = [Trajectory(name, RobotKind.CAR, *at_frame_rate(T, fps)) for name, T in zip(names, poses, strict=True)]
    return robots, notes


def at_frame_rate(T_world_cam: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """A drive's (N, 4, 4) poses, one per KITTI frame (``KITTI_FPS``), sampled at ``fps`` frames/s: positions
    interpolated linearly, rotations spherically, from the drive's first frame to its last.

    Returns ((M, 4, 4) poses, (M,) timestamps ``j / fps`` seconds). At ``KITTI_FPS`` the very poses; at 5 every
    second one, at 10/3 every third (what users do to KITTI to run faster), above 10 poses between frames.
    """
    if fps == KITTI_FPS or len(T_world_cam) < 2:  # a single pose has nothing to sample between
        return T_world_cam, np.arange(len(T_world_cam)) / fps
    from scipy.spatial.transform import Rotation, Slerp

    t_kitti = np.arange(len(T_world_cam)) / KITTI_FPS
    count = int(np.floor(t_kitti[-1] * fps + 1e-9)) + 1
    t = np.minimum(np.arange(count) / fps, t_kitti[-1])
    out = np.tile(np.eye(4), (count, 1, 1))
    out[:, :3, :3] = Slerp(t_kitti, Rotation.from_matrix(T_world_cam[:, :3, :3]))(t).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(t, t_kitti, T_world_cam[:, axis, 3])
    return out, np.arange(count) / fps
