"""Planar circular motion: the turn from tracks alone, against exact projections and a rendered drive."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import OdometryConfig, OdometryKind
from shgm_slam.geometry.se3 import inverse
from shgm_slam.odometry.image_rotation import rot_y, yaw_of
from shgm_slam.odometry.planar_motion import MIN_CORNERS, epipolar_support, planar_turn
from shgm_slam.odometry.sources import make_odometry
from shgm_slam.odometry.visual import MIN_PLANAR_SUPPORT, DepthVisualOdometry, translation_given_rotation
from shgm_slam.types import Frame, Intrinsics
from tests.odometry.corridor import INTRINSICS, render

K = Intrinsics(fx=300.0, fy=300.0, cx=160.0, cy=48.0, width=320, height=96)


def car_step(yaw_rad: float, chord_m: float) -> np.ndarray:
    """(4, 4) the current camera in the previous one: turned by yaw, moved along the arc's chord."""
    T = np.eye(4)
    T[:3, :3] = rot_y(yaw_rad)
    T[:3, 3] = chord_m * np.array([np.sin(yaw_rad / 2), 0.0, np.cos(yaw_rad / 2)])
    return T


def project(points_prev: np.ndarray, T_prev_cur: np.ndarray, k: Intrinsics = K) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of (N, 3) points (previous camera frame) in the previous and the current image."""
    cur = (points_prev - T_prev_cur[:3, 3]) @ T_prev_cur[:3, :3]

    def px(p: np.ndarray) -> np.ndarray:
        return np.stack([k.fx * p[:, 0] / p[:, 2] + k.cx, k.fy * p[:, 1] / p[:, 2] + k.cy], axis=1)

    return px(points_prev), px(cur)


def essential_planar(yaw_rad: np.ndarray) -> np.ndarray:
    """Reference: (G, 3, 3) essential matrices ``E`` with ``x_cur^T E x_prev = 0`` for turns θ under circular motion:
    the current camera rotated by ``R_y(θ)`` in the previous one, its centre along ``(sin θ/2, 0, cos θ/2)``."""
    th = np.asarray(yaw_rad, dtype=np.float64).reshape(-1)
    c, s = np.cos(th), np.sin(th)
    R_cur_prev = np.zeros((len(th), 3, 3))  # R_y(θ)^T
    R_cur_prev[:, 0, 0], R_cur_prev[:, 0, 2], R_cur_prev[:, 1, 1] = c, -s, 1.0
    R_cur_prev[:, 2, 0], R_cur_prev[:, 2, 2] = s, c
    centre = np.stack([np.sin(th / 2), np.zeros_like(th), np.cos(th / 2)], axis=1)
    t = -np.einsum("gij,gj->gi", R_cur_prev, centre)  # the previous camera's origin in the current frame
    tx = np.zeros((len(th), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    return tx @ R_cur_prev


@pytest.fixture
def scene() -> np.ndarray:
    rng = np.random.default_rng(3)
    return np.column_stack([rng.uniform(-15, 15, 300), rng.uniform(-4, 1.5, 300), rng.uniform(4, 40, 300)])


@pytest.mark.parametrize("yaw_deg", [0.0, 0.7, -3.0, 9.5])
def test_turn_of_a_car_step_is_recovered_from_pixels_alone(scene, yaw_deg):
    uv0, uv1 = project(scene, car_step(np.radians(yaw_deg), 1.2))
    turn = planar_turn(uv0, uv1, K)
    assert turn is not None and turn.corners == len(scene)
    assert np.degrees(turn.yaw_rad) == pytest.approx(yaw_deg, abs=0.01)
    assert turn.support == pytest.approx(1.0)


def test_a_pure_turn_without_translation_is_recovered(scene):
    uv0, uv1 = project(scene, car_step(np.radians(4.0), 0.0))
    assert np.degrees(planar_turn(uv0, uv1, K).yaw_rad) == pytest.approx(4.0, abs=0.01)


def test_tracks_on_other_moving_things_do_not_pull_the_turn(scene):
    """A third of the tracks move at random (a car ahead, mistracks): the truncated cost ignores them and
    the support says how many agreed (a few moved ones land near their epipolar line by chance)."""
    rng = np.random.default_rng(1)
    uv0, uv1 = project(scene, car_step(np.radians(-2.0), 1.0))
    bad = rng.random(len(uv1)) < 1 / 3
    uv1[bad] += rng.normal(0.0, 8.0, (bad.sum(), 2))
    turn = planar_turn(uv0, uv1, K)
    assert np.degrees(turn.yaw_rad) == pytest.approx(-2.0, abs=0.05)
    assert 1 - bad.mean() <= turn.support < 1 - 0.5 * bad.mean()


def test_motion_unlike_a_car_finds_little_support(scene):
    """A UAV sliding sideways and sinking while it turns is not planar circular motion: low support, so the
    visual odometry keeps its own turn."""
    T = np.eye(4)
    T[:3, :3] = rot_y(np.radians(2.0))
    T[:3, 3] = [1.0, 0.6, 0.3]
    uv0, uv1 = project(scene, T)
    assert planar_turn(uv0, uv1, K).support < MIN_PLANAR_SUPPORT


def test_too_few_corners_give_no_turn(scene):
    uv0, uv1 = project(scene[: MIN_CORNERS - 1], car_step(0.01, 1.0))
    assert planar_turn(uv0, uv1, K) is None


def test_the_epipolar_support_of_a_motion_counts_what_it_explains(scene):
    """The true motion explains every corner (any translation length), as the planar turn counts its own support; a
    turn 2 deg off explains far fewer, the translation 5 deg sideways (what PnP trades a turn for) fewer; no
    translation, or too few corners, gives no answer."""
    rng = np.random.default_rng(11)
    T = car_step(np.radians(6.0), 1.5)
    uv0, uv1 = project(scene, T)
    uv1 = uv1 + rng.normal(0.0, 0.3, uv1.shape)
    assert epipolar_support(T, uv0, uv1, K) == pytest.approx(planar_turn(uv0, uv1, K).support)
    assert epipolar_support(T, uv0, uv1, K) > 0.95
    longer = T.copy()
    longer[:3, 3] *= 7.0
    assert epipolar_support(longer, uv0, uv1, K) == epipolar_support(T, uv0, uv1, K)
    off = T.copy()
    off[:3, :3] = rot_y(np.radians(8.0))
    sideways = T.copy()
    sideways[:3, 3] = 1.5 * np.array([np.sin(np.radians(8.0)), 0.0, np.cos(np.radians(8.0))])
    assert epipolar_support(off, uv0, uv1, K) < 0.8
    assert epipolar_support(sideways, uv0, uv1, K) < epipolar_support(T, uv0, uv1, K) - 0.03
    still = T.copy()
    still[:3, 3] = 0.0
    assert epipolar_support(still, uv0, uv1, K) is None
    assert epipolar_support(T, uv0[: MIN_CORNERS - 1], uv1[: MIN_CORNERS - 1], K) is None


def test_essential_matrix_holds_the_epipolar_constraint(scene):
    yaw = np.radians(5.0)
    uv0, uv1 = project(scene, car_step(yaw, 1.5))
    x0 = np.column_stack([(uv0 - [K.cx, K.cy]) / [K.fx, K.fy], np.ones(len(uv0))])
    x1 = np.column_stack([(uv1 - [K.cx, K.cy]) / [K.fx, K.fy], np.ones(len(uv1))])
    E = essential_planar(np.array([yaw, -yaw]))
    assert np.abs(np.einsum("ni,ij,nj->n", x1, E[0], x0)).max() < 1e-9
    assert np.abs(np.einsum("ni,ij,nj->n", x1, E[1], x0)).max() > 1e-3  # the opposite turn does not fit


def test_translation_with_the_rotation_held_is_exact_on_exact_data(scene):
    T_cam_ref = inverse(car_step(np.radians(3.0), 2.0))
    _, uv1 = project(scene, car_step(np.radians(3.0), 2.0))
    t = translation_given_rotation(T_cam_ref[:3, :3], scene, uv1, K)
    np.testing.assert_allclose(t, T_cam_ref[:3, 3], atol=1e-9)
    assert translation_given_rotation(T_cam_ref[:3, :3], -scene[:5], uv1[:5], K) is None  # behind the camera


def weaving_drive(num_frames: int, step_m: float = 1.0, amplitude_rad: float = 0.25) -> np.ndarray:
    """(N, 4, 4) ``T_world_cam`` of a car weaving down the corridor: it drives where it points (chords)."""
    yaw = amplitude_rad * np.sin(np.linspace(0.0, 2.0 * np.pi, num_frames))
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(1, num_frames):
        mid = 0.5 * (yaw[i - 1] + yaw[i])
        poses[i, :3, 3] = poses[i - 1, :3, 3] + step_m * np.array([np.sin(mid), 0.0, np.cos(mid)])
    poses[:, :3, :3] = np.stack([rot_y(y) for y in yaw])
    return poses


def test_planar_turns_stop_the_heading_drift_of_pnp_on_skewed_depth():
    """Depth too far on the left and too near on the right (a smooth scale field, as networks err) turns
    PnP's estimate at every reference; the turns measured from the tracks do not depend on depth."""
    poses = weaving_drive(40, amplitude_rad=0.1)
    u = np.arange(INTRINSICS.width, dtype=np.float32)
    skew = (1.0 - 0.25 * (u - INTRINSICS.cx) / INTRINSICS.cx)[None, :]
    heading_err = {}
    for planar in (False, True):
        vo = DepthVisualOdometry(depth_window_px=1, planar_motion=planar, min_track_fraction=0.9)
        planar_frames = 0
        for T in poses:
            gray, depth = render(T)
            reg = vo.register(gray, depth * skew, INTRINSICS)
            est, planar_frames = reg.T_odom_cam, planar_frames + reg.planar_turn
        truth = inverse(poses[0]) @ poses[-1]
        heading_err[planar] = abs(np.degrees(yaw_of(inverse(truth) @ est)))
        assert planar_frames == (len(poses) - 1 if planar else 0)
    assert heading_err[True] < 0.1  # PnP alone: 1.2 deg here; 40-48 deg over 950 m on a network's depth
    assert heading_err[True] < 0.1 * heading_err[False]


def test_the_default_visual_source_takes_a_cars_turns_from_planar_motion_and_says_so():
    """The configured source (planar motion on by default) reports each step whose turn came from it."""
    poses = weaving_drive(8)
    src = make_odometry(OdometryConfig(kind=OdometryKind.VISUAL, visual_depth_window_px=1), len(poses))
    flags = []
    for i, T in enumerate(poses):
        gray, depth = render(T)
        frame = Frame(index=i, timestamp_s=0.1 * i, intrinsics=INTRINSICS, image_rgb=np.repeat(gray[..., None], 3, 2))
        est = src.update(frame, np.zeros((0, 3)), depth)
        flags.append(est.planar_turn)
        assert est.ok or not est.planar_turn  # a predicted pose never claims a measured turn
    assert not flags[0]  # the first frame has no turn
    assert sum(flags) >= len(poses) // 2  # frames where the corridor gives PnP enough tracks


def test_the_planar_turn_depends_on_the_two_images_not_on_the_reference():
    """Each frame's turn comes from corners found afresh in the previous image: however long the references'
    tracks are carried (renewed at 90 % or at 30 % survivors), a drive whose every turn was planar ends with
    the same heading, the product of the same turns."""
    poses = weaving_drive(16, amplitude_rad=0.1)
    headings, references = [], []
    for fraction in (0.9, 0.3):
        vo = DepthVisualOdometry(depth_window_px=1, planar_motion=True, min_track_fraction=fraction)
        planar = 0
        for T in poses:
            gray, depth = render(T)
            reg = vo.register(gray, depth, INTRINSICS)
            planar += reg.planar_turn
        assert planar == len(poses) - 1
        headings.append(reg.T_odom_cam[:3, :3])
        references.append(vo.num_references)
    assert references[0] > references[1]  # the references did differ
    np.testing.assert_allclose(headings[0], headings[1], atol=1e-9)


def test_real_kitti_07_turns_from_tracks_beat_the_image_shift(shared_data):
    """Real KITTI 07 (the 160 shared frames, 1226x370, a right and a left turn of about 90 deg each): the
    planar turn agrees with the ground truth per frame where the tracks support it, and its sum drifts far
    less than the phase-correlation yaw's."""
    cv2 = pytest.importorskip("cv2")
    from shgm_slam.data.kitti import read_projection
    from shgm_slam.io.trajectories import read_kitti_poses
    from shgm_slam.odometry.image_rotation import ImageYawEstimator

    seq = shared_data / "kitti" / "sequences" / "07"
    files = sorted((seq / "image_0").glob("*.png"))
    P0 = read_projection(seq / "calib.txt", "P0")
    first = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
    k = Intrinsics(fx=P0[0, 0], fy=P0[1, 1], cx=P0[0, 2], cy=P0[1, 2], width=first.shape[1], height=first.shape[0])
    gt = read_kitti_poses(shared_data / "kitti" / "poses" / "07.txt")[: len(files)]
    shift = ImageYawEstimator()
    err_planar, err_shift, support, turns = [], [], [], []
    prev = None
    for i, f in enumerate(files):
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        yaw_shift = shift.update(np.repeat(gray[..., None], 3, axis=2), k.fx)
        if prev is not None:
            truth = yaw_of(inverse(gt[i - 1]) @ gt[i])
            p0 = cv2.goodFeaturesToTrack(prev, 1000, 0.01, 7)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, None, winSize=(21, 21), maxLevel=3)
            turn = planar_turn(p0[st[:, 0] == 1, 0], p1[st[:, 0] == 1, 0], k)
            err_planar.append(turn.yaw_rad - truth)
            support.append(turn.support)
            err_shift.append((yaw_shift or 0.0) - truth)
            turns.append(truth)
        prev = gray
    err_planar, support = np.degrees(err_planar), np.array(support)
    agreed = support >= MIN_PLANAR_SUPPORT
    assert np.degrees(np.abs(turns).sum()) > 150.0  # the drive does turn
    assert agreed.mean() > 0.9  # real car motion fits the model (1 px truncation left half the frames out)
    assert np.sqrt(np.mean(err_planar[agreed] ** 2)) < 0.2  # deg per frame
    assert abs(err_planar.sum()) < 0.5 * abs(np.degrees(np.sum(err_shift)))


def test_the_written_out_sampson_distance_is_the_matrix_one(scene):
    from shgm_slam.odometry.planar_motion import _sampson_px2

    rng = np.random.default_rng(5)
    uv0, uv1 = project(scene, car_step(np.radians(3.0), 1.0))
    uv1 += rng.normal(0.0, 1.0, uv1.shape)
    x0 = np.column_stack([(uv0 - [K.cx, K.cy]) / [K.fx, K.fy], np.ones(len(uv0))])
    x1 = np.column_stack([(uv1 - [K.cx, K.cy]) / [K.fx, K.fy], np.ones(len(uv1))])
    yaw = np.radians(np.array([-7.0, 0.0, 2.9, 3.0, 12.0]))
    E = essential_planar(yaw)
    Ex0, Etx1 = np.einsum("gij,nj->gni", E, x0), np.einsum("gji,nj->gni", E, x1)
    num = np.einsum("ni,gni->gn", x1, Ex0)
    den = Ex0[..., 0] ** 2 + Ex0[..., 1] ** 2 + Etx1[..., 0] ** 2 + Etx1[..., 1] ** 2
    np.testing.assert_allclose(_sampson_px2(yaw, x0, x1, K.fx), num**2 / den * K.fx**2, rtol=1e-9, atol=1e-12)
