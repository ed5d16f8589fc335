"""KITTI drives as robots (``sim.kitti_paths``): drive specs (half-open ranges), several robots cut from one
sequence sharing its frame, and clear refusals."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import inverse
from shgm_slam.io.trajectories import read_kitti_poses, write_kitti_poses
from shgm_slam.sim.kitti_paths import (
    CAR_CAMERA_HEIGHT_M,
    KittiDrive,
    at_frame_rate,
    drive_names,
    kitti_trajectories,
)


@pytest.mark.parametrize(
    ("spec", "drive"),
    [
        ("07:0-350", KittiDrive("07", 0, 350)),
        ("8:100-200", KittiDrive("08", 100, 200)),
        ("08", KittiDrive("08", 0, None)),
        ("10:3000-", KittiDrive("10", 3000, None)),
    ],
)
def test_parse_drive(spec, drive):
    assert KittiDrive.parse(spec) == drive


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("07:0_350", "SEQ:START-END"),
        ("seven", "SEQ:START-END"),
        ("07:-5-10", "SEQ:START-END"),
        ("99:0-10", "unknown KITTI sequence '99'"),
        ("07:350-350", "empty KITTI frame range"),
        ("07:400-300", "half-open"),
    ],
)
def test_parse_drive_refuses_bad_specs(spec, match):
    with pytest.raises(ConfigError, match=match):
        KittiDrive.parse(spec)


def test_names_tell_drives_of_one_sequence_apart_and_are_valid_robot_names():
    from shgm_slam.runner import parse_robot_arg

    drives = [KittiDrive.parse(s) for s in ("08:0-300", "00:0-10", "08:1400-1850", "08:740-1000")]
    names = drive_names(drives)
    assert names == ["kitti08a", "kitti00", "kitti08b", "kitti08c"]
    for name in names:
        assert parse_robot_arg(f"{name}=some/path:0-10")[0] == name


def _fake_root(tmp_path, seqs=("03", "05"), n=120):
    """A KITTI-like poses folder: curved drives (ground truth ``T_cam0_cam``) for ``seqs``."""
    (tmp_path / "poses").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for seq in seqs:
        yaw = np.cumsum(rng.normal(0, 0.02, n))
        T = np.tile(np.eye(4), (n, 1, 1))
        c, s = np.cos(yaw), np.sin(yaw)  # KITTI camera: y down, so a yaw is a rotation about y
        T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
        step = np.stack([s, np.zeros(n), c], 1)
        T[:, :3, 3] = np.cumsum(step, 0) + np.array([0.0, rng.normal(0, 0.05), 0.0])
        write_kitti_poses(tmp_path / "poses" / f"{seq}.txt", T)
    return tmp_path


def test_robots_of_one_sequence_share_its_frame(tmp_path):
    """Two drives of one sequence: their poses are that sequence's KITTI poses of those frames, mapped by ONE
    transform (no alignment), so any relative pose between the robots is KITTI's own."""
    root = _fake_root(tmp_path)
    robots, notes = kitti_trajectories(root, ("03:10-60", "03:70-120"))
    a, b = robots
    assert (a.name, b.name, len(a), len(b)) == ("kitti03a", "kitti03b", 50, 50)
    assert notes["kitti03b"]["reference"] and notes["kitti03b"]["frames"] == [70, 120]
    kitti = read_kitti_poses(root / "poses" / "03.txt")
    both = np.concatenate([a.T_world_cam, b.T_world_cam])
    truth = np.concatenate([kitti[10:60], kitti[70:120]])
    # one rigid map for both robots: world = T_world_kitti @ kitti (z flattened to the camera height)
    T_world_kitti = both[0] @ inverse(truth[0])
    mapped = T_world_kitti @ truth
    np.testing.assert_allclose(both[:, :3, :3], mapped[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(both[:, :2, 3], mapped[:, :2, 3], atol=1e-6)
    np.testing.assert_allclose(both[:, 2, 3], CAR_CAMERA_HEIGHT_M)
    # the relative pose between a frame of robot a and one of robot b is KITTI's (up to the flattened height)
    rel = inverse(a.T_world_cam[5]) @ b.T_world_cam[40]
    rel_kitti = inverse(kitti[15]) @ kitti[110]
    np.testing.assert_allclose(rel[:3, :3], rel_kitti[:3, :3], atol=1e-9)


def test_whole_sequence_and_open_end(tmp_path):
    root = _fake_root(tmp_path)
    robots, _ = kitti_trajectories(root, ("05", "05:100-"))
    assert [len(r) for r in robots] == [120, 20]


@pytest.mark.parametrize(
    ("specs", "error", "match"),
    [
        (("03:0-121",), DataError, "has 120 poses"),
        (("03:120-130",), DataError, "outside"),
        (("04:0-10",), DataError, "poses/04.txt"),
        (("15:0-10",), ConfigError, "only 00-10"),
        (("03:0-50", "03:0-50"), ConfigError, "given twice"),
        ((), ConfigError, "at least one"),
        (("03:5-7",), ConfigError, "has 2 frame"),  # a traceback in the path's gradient before
        (("03:119-",), ConfigError, "has 1 frame"),
    ],
)
def test_refusals(tmp_path, specs, error, match):
    root = _fake_root(tmp_path)
    with pytest.raises(error, match=match):
        kitti_trajectories(root, specs)


def test_missing_poses_folder(tmp_path):
    with pytest.raises(DataError, match=r"no .*poses"):
        kitti_trajectories(tmp_path, ("07:0-10",))


def test_real_kitti_08_three_way_split(shared_data):
    """The paper's 08 split: three robots from one sequence, in 08's own frame, overlapping as the paper's."""
    from shgm_slam.sim.trajectories import shared_view_length_m

    specs = ("08:0-300", "08:1400-1850", "08:740-1000")
    robots, notes = kitti_trajectories(shared_data / "kitti", specs)
    assert [r.name for r in robots] == ["kitti08a", "kitti08b", "kitti08c"]
    assert all(n["reference"] for n in notes.values())
    kitti = read_kitti_poses(shared_data / "kitti" / "poses" / "08.txt")
    for robot, (a, b) in zip(robots, ((0, 300), (1400, 1850), (740, 1000)), strict=True):
        # 08's frame for all three (z up): world x = KITTI z (forward at frame 0), world y = -KITTI x
        np.testing.assert_allclose(robot.positions_xyz[:, 0], kitti[a:b, 2, 3], atol=1e-9)
        np.testing.assert_allclose(robot.positions_xyz[:, 1], -kitti[a:b, 0, 3], atol=1e-9)
    rel = inverse(robots[0].T_world_cam[100]) @ robots[1].T_world_cam[300]
    np.testing.assert_allclose(rel[:3, :3], (inverse(kitti[100]) @ kitti[1700])[:3, :3], atol=1e-9)
    assert shared_view_length_m(robots[0], robots[1]) > 150.0  # 08A: ~200 m of shared street
    assert shared_view_length_m(robots[2], robots[1]) > 10.0  # 08B: ~50 m, driven the other way


def test_cli_simulate_kitti_drives(tmp_path):
    """``shgm-slam simulate --scenario kitti-paths --kitti-drive ...`` (repeatable) renders one robot per drive."""
    import json

    from typer.testing import CliRunner

    from shgm_slam.cli import app

    root = _fake_root(tmp_path / "kitti")
    out = tmp_path / "world"
    args = ["simulate", "-s", "kitti-paths", "-o", str(out), "--kitti-root", str(root), "--resolution", "32x16",
            "--max-frames", "3", "--kitti-drive", "03:0-60", "--kitti-drive", "03:50-120"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    scen = json.loads((out / "scenario.json").read_text())
    assert [r["name"] for r in scen["robots"]] == ["kitti03a", "kitti03b"]
    assert scen["notes"]["kitti_alignment"]["kitti03b"]["frames"] == [50, 120]
    bad = CliRunner().invoke(app, [*args[:4], str(tmp_path / "w2"), *args[5:-1], "03:50-50"])
    assert bad.exit_code == 2 and "empty KITTI frame range" in bad.output
    other = CliRunner().invoke(app, ["simulate", "-s", "disjoint", "-o", str(tmp_path / "w3"),
                                     "--kitti-drive", "03:0-10"])  # fmt: skip
    assert other.exit_code == 2 and "only apply to the kitti-paths" in other.output


def test_real_kitti_whole_sequences(shared_data):
    """Whole sequences as robots: 09 and 10 share ~175 m, a small fraction of 10's 918 m, still accepted."""
    robots, notes = kitti_trajectories(shared_data / "kitti", ("09", "10"))
    assert [(r.name, len(r)) for r in robots] == [("kitti09", 1591), ("kitti10", 1201)]
    assert notes["kitti10"]["overlap_length_m"] > 150.0 and notes["kitti10"]["rmse_m"] < 2.0


@pytest.mark.parametrize(("fps", "step"), [(5.0, 2), (10.0 / 3.0, 3)])
def test_a_lower_frame_rate_takes_every_nth_kitti_frame(tmp_path, fps, step):
    """``--fps 5`` is KITTI's every 2nd frame at 0.2 s, 3.3 its every 3rd (what users do to run faster), not
    KITTI's frames slowed down; at 10 Hz the very poses."""
    root = _fake_root(tmp_path)
    (full,), _ = kitti_trajectories(root, ("03:10-60",))
    (sub,), _ = kitti_trajectories(root, ("03:10-60",), fps=fps)
    np.testing.assert_allclose(sub.T_world_cam, full.T_world_cam[::step], atol=1e-9)
    np.testing.assert_allclose(sub.timestamps_s, np.arange(len(sub)) / fps)
    assert len(sub) == len(range(0, 50, step))
    assert full.timestamps_s[1] == pytest.approx(0.1)


def test_a_higher_frame_rate_interpolates_between_kitti_frames(tmp_path):
    root = _fake_root(tmp_path)
    (full,), _ = kitti_trajectories(root, ("03:10-60",))
    (fast,), _ = kitti_trajectories(root, ("03:10-60",), fps=20.0)
    assert len(fast) == 2 * len(full) - 1
    np.testing.assert_allclose(fast.T_world_cam[::2], full.T_world_cam, atol=1e-9)
    mid = fast.T_world_cam[1::2, :3, 3]
    np.testing.assert_allclose(mid, 0.5 * (full.T_world_cam[:-1, :3, 3] + full.T_world_cam[1:, :3, 3]), atol=1e-9)
    R = fast.T_world_cam[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


@pytest.mark.parametrize("fps", [5.0, 20.0])
def test_a_single_pose_is_kept_at_any_frame_rate(fps):
    pose = np.eye(4)[None].copy()
    pose[0, :3, 3] = [1.0, 2.0, 3.0]
    T, t = at_frame_rate(pose, fps)
    np.testing.assert_array_equal(T, pose)
    np.testing.assert_array_equal(t, [0.0])
