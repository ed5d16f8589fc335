"""Odometry sources: ground truth and pose files relative to the first frame, errors, the factory."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import OdometryConfig, OdometryKind
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import inverse, make_pose, pose_error, rot_y, so3_exp
from shgm_slam.io.trajectories import write_kitti_poses, write_tum
from shgm_slam.odometry.clouds import depth_to_cloud
from shgm_slam.odometry.sources import (
    GivenOdometrySource,
    GroundTruthSource,
    KissIcpSource,
    OdometrySource,
    PoseFileSource,
    make_odometry,
)
from shgm_slam.types import Frame, Intrinsics

INTR = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_pose(so3_exp(rng.normal(0, 0.5, (n, 3))), rng.normal(0, 1.0, (n, 3)))


def _frames(poses: np.ndarray | None, n: int) -> list[Frame]:
    return [Frame(i, 0.1 * i, INTR, T_world_cam=None if poses is None else poses[i]) for i in range(n)]


def test_ground_truth_source_is_relative_to_the_first_frame():
    poses = _poses(6)
    src = GroundTruthSource()
    assert isinstance(src, OdometrySource)
    est = np.stack([src.update(f, np.zeros((0, 3))).T_odom_cam for f in _frames(poses, 6)])
    np.testing.assert_allclose(est, inverse(poses[0]) @ poses, atol=1e-9)
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-12)
    # relative motion between any two frames is the ground truth's
    np.testing.assert_allclose(inverse(est[2]) @ est[5], inverse(poses[2]) @ poses[5], atol=1e-9)


def test_ground_truth_source_without_poses_raises():
    with pytest.raises(DataError, match="no ground-truth pose"):
        GroundTruthSource().update(_frames(None, 1)[0], np.zeros((0, 3)))


def test_given_odometry_is_the_robots_own_relative_to_the_first_frame_and_to_the_first_after_a_reset():
    """The robot's own odometry (``Frame.T_odom_cam``) runs, not the ground truth the frames also carry; after a
    reset (an odometry failure) the new segment starts at the next frame."""
    truth, own = _poses(6, seed=1), _poses(6, seed=2)
    frames = [Frame(i, 0.1 * i, INTR, T_world_cam=truth[i], T_odom_cam=own[i]) for i in range(6)]
    src = make_odometry(OdometryConfig(kind=OdometryKind.GIVEN), 6)
    assert isinstance(src, GivenOdometrySource) and isinstance(src, OdometrySource)
    est = np.stack([src.update(f, np.zeros((0, 3))).T_odom_cam for f in frames[:4]])
    np.testing.assert_allclose(est, inverse(own[0]) @ own[:4], atol=1e-9)
    src.reset()
    after = src.update(frames[4], np.zeros((0, 3))).T_odom_cam
    np.testing.assert_allclose(after, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(src.update(frames[5], np.zeros((0, 3))).T_odom_cam, inverse(own[4]) @ own[5],
                               atol=1e-9)  # fmt: skip
    with pytest.raises(DataError, match="no odometry pose of the robot's own"):
        GivenOdometrySource().update(_frames(truth, 1)[0], np.zeros((0, 3)))


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_pose_file_source_reads_kitti_and_tum(tmp_path, fmt):
    poses = _poses(5, seed=1)
    path = tmp_path / f"poses_{fmt}.txt"
    if fmt == "kitti":
        write_kitti_poses(path, poses)
    else:
        write_tum(path, np.arange(5) * 0.1, poses)
    src = PoseFileSource(path, 5)
    est = np.stack([src.update(f, np.zeros((0, 3))).T_odom_cam for f in _frames(None, 5)])
    np.testing.assert_allclose(est, inverse(poses[0]) @ poses, atol=1e-6)


def test_pose_file_count_mismatch_names_counts_and_file(tmp_path):
    path = tmp_path / "short.txt"
    write_kitti_poses(path, _poses(4))
    with pytest.raises(DataError, match=r"short\.txt has 4 poses but the sequence has 7 frames"):
        PoseFileSource(path, 7)


def test_tum_rows_are_matched_to_the_frames_by_timestamp(tmp_path):
    poses = _poses(8, seed=2)
    path = tmp_path / "tum.txt"
    write_tum(path, np.arange(8) * 0.1, poses)
    src = make_odometry(OdometryConfig(kind=OdometryKind.FILE, poses_file=path), 3, timestamps_s=[0.3, 0.4, 0.5])
    est = np.stack([src.update(Frame(i, 0.3 + 0.1 * i, INTR), np.zeros((0, 3))).T_odom_cam for i in range(3)])
    np.testing.assert_allclose(est, inverse(poses[3]) @ poses[3:6], atol=1e-6)  # a frame range of the file
    write_tum(path, 1000.0 + np.arange(8) * 0.1, poses)  # the same count, another clock: refused
    with pytest.raises(DataError, match=r"no row at the time of frame 0 \(0\.000000 s; nearest row 1000\.000000 s\)"):
        PoseFileSource(path, 8, np.arange(8) * 0.1)
    poses[:, :3, 3] *= 1000.0  # in millimetres: every step would be cut as an odometry failure
    write_tum(path, np.arange(8) * 0.1, poses)
    with pytest.raises(DataError, match=r"poses file .*tum\.txt: the trajectory moves at .* m/s .*in millimetres"):
        PoseFileSource(path, 8, np.arange(8) * 0.1)


def test_pose_file_frame_out_of_range(tmp_path):
    path = tmp_path / "p.txt"
    write_kitti_poses(path, _poses(3))
    src = PoseFileSource(path, 3)
    with pytest.raises(DataError, match="frame 3 has no pose"):
        src.update(Frame(3, 0.3, INTR), np.zeros((0, 3)))


def test_factory_builds_every_kind(tmp_path):
    path = tmp_path / "p.txt"
    write_kitti_poses(path, make_pose(np.repeat(rot_y(0.1)[None], 3, 0), np.zeros((3, 3))))
    assert isinstance(make_odometry(OdometryConfig(kind=OdometryKind.KISS_ICP), 3), KissIcpSource)
    assert isinstance(make_odometry(OdometryConfig(kind=OdometryKind.GT), 3), GroundTruthSource)
    src = make_odometry(OdometryConfig(kind=OdometryKind.FILE, poses_file=path), 3)
    assert isinstance(src, PoseFileSource)
    with pytest.raises(DataError, match="3 poses but the sequence has 4 frames"):
        make_odometry(OdometryConfig(kind="file", poses_file=path), 4)


def test_kiss_source_reports_degenerate_frames():
    src = make_odometry(OdometryConfig(), 2)
    est = src.update(Frame(0, 0.0, INTR), np.zeros((10, 3)))
    assert not est.ok and "degenerate" in est.note
    np.testing.assert_allclose(est.T_odom_cam, np.eye(4))


def test_pose_file_source_on_kitti_ground_truth(shared_data):
    path = shared_data / "kitti" / "poses" / "07.txt"
    src = PoseFileSource(path, 1101)  # sequence 07 has 1101 frames
    np.testing.assert_allclose(src.T_odom_cam[0], np.eye(4), atol=1e-9)
    with pytest.raises(DataError, match="1101 poses but the sequence has 160 frames"):
        PoseFileSource(path, 160)  # e.g. only the 160 images that are on disk


def _street_clouds(poses: np.ndarray, seed: int, noise: float = 0.0) -> tuple[list[np.ndarray], Intrinsics]:
    """Camera-frame clouds (cloud stride 4) of a ray-cast street seen from ``poses`` (T_world_cam)."""
    from tests.odometry.test_kiss import INTR as STREET_INTR
    from tests.odometry.test_kiss import render_depth, street

    rng = np.random.default_rng(seed)
    boxes = street(rng, length_m=100.0, n_boxes=100)
    clouds = []
    for T in poses:
        depth = render_depth(T, boxes, stride=4)
        depth *= (1 + rng.normal(0, noise, depth.shape)).astype(np.float32)
        clouds.append(depth_to_cloud(depth, STREET_INTR, stride=4, min_range_m=0.5, max_range_m=100.0)[0])
    return clouds, STREET_INTR


def _run(cfg: OdometryConfig, clouds: list[np.ndarray], intr: Intrinsics) -> np.ndarray:
    src = make_odometry(cfg, len(clouds))
    return np.stack([src.update(Frame(i, 0.1 * i, intr), c).T_odom_cam for i, c in enumerate(clouds)])


@pytest.mark.parametrize("shuffle", [False, True])
def test_kiss_tracks_from_the_first_frame_on_a_long_street(shuffle: bool):
    # 1 m/frame down a street with facades and a ground plane out to 100 m: the sparse far/grazing
    # samples move with the camera and, unfiltered, hold ICP near zero motion for the first frames
    gt = np.stack([make_pose(np.eye(3), [0.0, 0.0, 1.0 * i]) for i in range(8)])
    clouds, intr = _street_clouds(gt, seed=0)
    cfg = OdometryConfig(cloud_stride=4, shuffle_points=shuffle)
    est = _run(cfg, clouds, intr)
    steps_m = np.diff(est[:, :3, 3], axis=0)
    np.testing.assert_allclose(steps_m[:, 2], 1.0, atol=0.1)  # every step, the first one included
    assert np.abs(steps_m[:, :2]).max() < 0.15
    if shuffle:  # the random order is seeded: runs are reproducible
        np.testing.assert_allclose(_run(cfg, clouds, intr), est, atol=1e-9)  # TBB sums: not bitwise
    else:
        stalled = _run(cfg.model_copy(update={"max_spacing_m": 1e9}), clouds, intr)
        assert stalled[-1, 2, 3] < 0.5 * est[-1, 2, 3]  # the cause: without the filter it stalls


@pytest.mark.parametrize(("shuffle", "tol_m", "tol_deg"), [(False, 0.05, 0.2), (True, 0.1, 0.6)])
def test_kiss_invents_no_motion_for_a_static_robot(shuffle: bool, tol_m: float, tol_deg: float):
    gt = np.repeat(make_pose(np.eye(3), [0.0, 0.0, 5.0])[None], 15, axis=0)
    clouds, intr = _street_clouds(gt, seed=1, noise=0.003)  # fresh depth noise every frame
    est = _run(OdometryConfig(cloud_stride=4, shuffle_points=shuffle), clouds, intr)
    err_m, err_deg = pose_error(est, np.repeat(np.eye(4)[None], len(est), axis=0))
    assert err_m.max() < tol_m and err_deg.max() < tol_deg  # a random point order jitters a little


def test_icp_convergence_reaches_kiss_icp_and_the_default_tracks_a_street_as_kiss_icps_own():
    """``odometry.icp_convergence`` is KISS-ICP's stop criterion; the default stops long before KISS-ICP's own
    1e-4 and tracks a street as well: every frame's error within 3 cm of the tight run's (either way; on the
    demo's UAV the early stop moved poses 7 mm on average, README)."""
    src = make_odometry(OdometryConfig(icp_convergence=0.02), 1)
    assert src.odometry.config.registration.convergence_criterion == 0.02
    assert OdometryConfig().icp_convergence > 1e-4
    gt = np.stack([make_pose(np.eye(3), [0.0, 0.0, 1.2 * i]) for i in range(10)])
    clouds, intr = _street_clouds(gt, seed=2, noise=0.003)
    errors_m = []
    for criterion in (OdometryConfig().icp_convergence, 1e-4):
        est = _run(OdometryConfig(cloud_stride=4, icp_convergence=criterion), clouds, intr)
        errors_m.append(pose_error(est, gt)[0])
    default_m, tight_m = errors_m
    assert tight_m.max() < 0.3  # the tight run tracks the street: the comparison means something
    assert np.abs(default_m - tight_m).max() < 0.03, (default_m, tight_m)


def test_spacing_filter_settings_are_validated():
    with pytest.raises(ConfigError, match="max_spacing_m"):
        KissIcpSource(make_odometry(OdometryConfig(), 1).odometry, cloud_stride=2, max_spacing_m=0.0)
    with pytest.raises(ValueError):
        OdometryConfig(max_spacing_m=-1.0)


def test_spacing_filter_keeps_the_far_points_of_a_noisy_sensor():
    """3 % depth noise moves neighbouring samples apart along their rays: without the noise allowance the filter
    drops far points a noise-free depth keeps (they hold the forward motion); with it, about as many stay."""
    from shgm_slam.odometry.estimate import keep_well_sampled

    at_origin = make_pose(np.eye(3), [0.0, 0.0, 0.0])[None]
    (clean,), intr = _street_clouds(at_origin, seed=0)
    (noisy,), _ = _street_clouds(at_origin, seed=0, noise=0.03)

    def far(points: np.ndarray) -> int:
        return int((points[:, 2] > 30.0).sum())

    kept_clean = far(keep_well_sampled(clean, intr, 4, 0.6))
    assert far(keep_well_sampled(noisy, intr, 4, 0.6)) < 0.5 * kept_clean
    assert far(keep_well_sampled(noisy, intr, 4, 0.6, noise_rel=0.03)) >= 0.8 * kept_clean
    np.testing.assert_array_equal(keep_well_sampled(clean, intr, 4, 0.6, noise_rel=0.0),
                                  keep_well_sampled(clean, intr, 4, 0.6))  # fmt: skip


def test_the_measured_noise_reaches_kiss_icp_and_the_hybrid():
    cfg = OdometryConfig(cloud_stride=2, max_spacing_m=0.6, depth_noise_rel=0.04)
    assert make_odometry(cfg.model_copy(update={"kind": OdometryKind.KISS_ICP}), 1).depth_noise_rel == 0.04
    assert make_odometry(cfg.model_copy(update={"kind": OdometryKind.HYBRID}), 1).depth_noise_rel == 0.04
    assert OdometryConfig().filled().depth_noise_rel == 0.0  # nothing measured: noise-free


def test_the_image_step_blend_is_built_where_it_is_on_and_the_image_checks_are_too():
    on = OdometryConfig(kind=OdometryKind.KISS_ICP, image_step_blend=True).filled()
    assert make_odometry(on, 1).blend is not None
    assert make_odometry(on.model_copy(update={"image_step_blend": False}), 1).blend is None
    assert OdometryConfig().filled().image_step_blend is False  # nothing measured: noise-free, ICP's steps
    for needed in ("image_flow_check", "image_rotation"):  # no tracks or no image turn to weigh them by
        assert make_odometry(on.model_copy(update={needed: False}), 1).blend is None


@pytest.mark.parametrize(("noise", "seen_only"), [(0.0, True), (None, True), (0.02, False)])
def test_kiss_icp_registers_on_what_the_previous_camera_saw_only_on_noise_free_depth(noise, seen_only):
    src = make_odometry(OdometryConfig(kind=OdometryKind.KISS_ICP, depth_noise_rel=noise), 3)
    assert isinstance(src, KissIcpSource) and src.odometry.register_seen_only is seen_only


@pytest.mark.parametrize(("noise", "reported"), [(0.0, 0.7), (0.02, None)])
def test_the_map_misfit_reaches_the_health_check_only_on_noise_free_depth(monkeypatch, noise, reported):
    """On 2 % noisy depth healthy frames of a UAV fit the map with misfits up to 0.71 (health.py): not reported."""
    from shgm_slam.odometry.kiss import OdometryStatus, Registration

    src = make_odometry(OdometryConfig(kind=OdometryKind.KISS_ICP, depth_noise_rel=noise, image_flow_check=False,
                                       image_rotation=False), 3)  # fmt: skip
    monkeypatch.setattr(src.odometry, "register",
                        lambda *a, **k: Registration(np.eye(4), OdometryStatus.OK, 5000, map_misfit=0.7))  # fmt: skip
    points = np.random.default_rng(0).uniform(-5, 5, (5000, 3)) + np.array([0.0, 0.0, 10.0])
    assert src.update(Frame(0, 0.0, INTR), points).map_misfit == reported
