"""Depth-assisted visual odometry on an exactly rendered corridor (true depth), checked against its path."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.config import OdometryConfig, OdometryKind
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import inverse, pose_error
from shgm_slam.metrics import ate, trajectory_length
from shgm_slam.odometry.image_rotation import rot_y, yaw_of
from shgm_slam.odometry.sources import (
    VisualOdometrySource,
    choose_odometry,
    make_odometry,
    resolve_kind,
    yaw_prior,
)
from shgm_slam.odometry.visual import (
    DepthVisualOdometry,
    VisualRegistration,
    VisualStatus,
    backproject_pixels,
    depth_window_on_image,
)
from shgm_slam.types import Frame
from tests.odometry.corridor import INTRINSICS, path, render


def run_vo(poses: np.ndarray, depth_fn=lambda d, i: d, **kwargs) -> tuple[np.ndarray, list]:
    kwargs.setdefault("depth_window_px", 1)  # true depth: a corner's own pixel
    vo = DepthVisualOdometry(**kwargs)
    est, regs = [], []
    for i, T in enumerate(poses):
        gray, depth = render(T)
        reg = vo.register(gray, depth_fn(depth, i), INTRINSICS)
        est.append(reg.T_odom_cam)
        regs.append(reg)
    return np.stack(est), regs


@pytest.fixture(scope="module")
def corridor() -> np.ndarray:
    return path(30)


def test_true_depth_follows_the_path_within_centimetres(corridor):
    est, regs = run_vo(corridor)
    gt = inverse(corridor[0]) @ corridor
    assert regs[0].status is VisualStatus.FIRST_FRAME
    assert all(r.ok for r in regs)
    assert ate(gt, est, align="none").rmse < 0.15
    assert trajectory_length(est) == pytest.approx(trajectory_length(gt), rel=0.01)
    t_err, r_err = pose_error(gt[-1], est[-1])
    assert t_err < 0.3 and r_err < 0.5


def test_noisy_depth_keeps_the_scale(corridor):
    """Per-pixel depth noise of 10 % (log-normal) barely moves the estimate: the scale comes from many points."""
    rng = np.random.default_rng(0)
    est, _ = run_vo(corridor, lambda d, i: (d * np.exp(rng.normal(0.0, 0.1, d.shape))).astype(np.float32))
    gt = inverse(corridor[0]) @ corridor
    assert trajectory_length(est) == pytest.approx(trajectory_length(gt), rel=0.03)
    assert ate(gt, est, align="none").rmse < 0.5


def test_depth_scale_error_scales_the_path(corridor):
    """A depth model 20 % short makes the path 20 % short: scale is the depth's, not invented."""
    est, _ = run_vo(corridor, lambda d, i: d * np.float32(0.8))
    gt = inverse(corridor[0]) @ corridor
    assert trajectory_length(est) == pytest.approx(0.8 * trajectory_length(gt), rel=0.02)


def test_depth_window_undoes_foreground_bleeding(corridor):
    """Depth blurred toward the foreground at edges (a 5x5 minimum, as networks do) shortens the path;
    taking the largest depth around each corner brings it back."""
    import cv2

    def bleed(d, i):
        return cv2.erode(d, np.ones((5, 5), np.uint8))

    gt_len = trajectory_length(inverse(corridor[0]) @ corridor)
    own, _ = run_vo(corridor, bleed, depth_window_px=1)
    window, _ = run_vo(corridor, bleed, depth_window_px=5)
    assert abs(trajectory_length(window) - gt_len) < abs(trajectory_length(own) - gt_len)
    assert trajectory_length(window) == pytest.approx(gt_len, rel=0.03)


@pytest.mark.parametrize(
    ("window", "image_w", "model_w", "expected"),
    [(5, 320, 320, 5), (5, 640, 320, 9), (5, 1226, 320, 19), (5, 1226, 518, 11), (1, 1226, 320, 1), (5, 200, 320, 5)],
)
def test_depth_window_on_image_is_odd_and_never_shrinks(window, image_w, model_w, expected):
    out = depth_window_on_image(window, image_w, model_w)
    assert out == expected and out % 2 == 1 and out >= window


def test_static_camera_invents_no_motion():
    poses = np.tile(path(2)[:1], (8, 1, 1))
    est, regs = run_vo(poses)
    assert all(r.ok for r in regs)
    assert np.abs(est[-1] - np.eye(4)).max() < 1e-3


def test_blank_frames_coast_on_constant_velocity_and_recover(corridor):
    """Frames without texture give no tracks: the pose follows the last motion and tracking restarts."""
    vo = DepthVisualOdometry()
    statuses = []
    for i, T in enumerate(corridor[:12]):
        gray, depth = render(T)
        if i in (6, 7):
            gray = np.full_like(gray, 128)
        statuses.append(vo.register(gray, depth, INTRINSICS).status)
    assert statuses[6] is not VisualStatus.OK and statuses[7] is not VisualStatus.OK
    assert statuses[9:] == [VisualStatus.OK] * 3
    # coasting kept the car moving forward about 1 m per frame
    assert 9.0 < vo.T_odom_cam[2, 3] < 13.0


def test_nan_and_missing_depth_are_ignored(corridor):
    def holes(d, i):
        d = d.copy()
        d[:, ::3] = np.nan
        d[::4] = 0.0
        return d

    est, regs = run_vo(corridor[:10], holes)
    gt = inverse(corridor[0]) @ corridor[:10]
    assert all(r.ok for r in regs)
    assert ate(gt, est, align="none").rmse < 0.2


def test_no_depth_at_all_coasts_without_crashing(corridor):
    est, regs = run_vo(corridor[:4], lambda d, i: np.zeros_like(d))
    assert [r.status for r in regs[1:]] == [VisualStatus.FEW_TRACKS] * 3
    assert np.isfinite(est).all()


def test_excluded_labels_give_no_corners(corridor):
    gray, depth = render(corridor[0])
    labels = np.full(gray.shape, 10, np.uint8)  # all sky
    vo = DepthVisualOdometry()
    vo.register(gray, depth, INTRINSICS, labels)
    gray1, depth1 = render(corridor[1])
    assert vo.register(gray1, depth1, INTRINSICS, labels).status is VisualStatus.FEW_TRACKS


@pytest.mark.parametrize(
    ("gray", "depth", "labels", "message"),
    [
        (np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5)), None, "grayscale"),
        (np.zeros((4, 5), np.float32), np.zeros((4, 5)), None, "uint8"),
        (np.zeros((4, 5), np.uint8), np.zeros((4, 6)), None, "differ in size"),
        (np.zeros((4, 5), np.uint8), np.zeros((4, 5)), np.zeros((3, 5)), "labels"),
    ],
)
def test_bad_inputs_raise_data_errors(gray, depth, labels, message):
    with pytest.raises(DataError, match=message):
        DepthVisualOdometry().register(gray, depth, INTRINSICS, labels)


def test_image_size_change_is_a_data_error(corridor):
    vo = DepthVisualOdometry()
    gray, depth = render(corridor[0])
    vo.register(gray, depth, INTRINSICS)
    with pytest.raises(DataError, match="image size changed"):
        vo.register(gray[:, :-2], depth[:, :-2], INTRINSICS)


def test_invalid_settings_raise_config_errors():
    with pytest.raises(ConfigError):
        DepthVisualOdometry(min_depth_m=5.0, max_depth_m=2.0)
    with pytest.raises(ConfigError):
        DepthVisualOdometry(min_track_fraction=0.0)
    with pytest.raises(ConfigError):
        DepthVisualOdometry(reprojection_px=0.0)


def test_backprojection_inverts_projection():
    depth = np.full((192, 640), 7.5, np.float32)
    uv = np.array([[319.5, 95.5], [10.0, 20.0], [600.0, 150.0]])
    pts = backproject_pixels(uv, depth, INTRINSICS)
    assert np.allclose(pts[:, 2], 7.5)
    proj = pts[:, :2] / pts[:, 2:] * [INTRINSICS.fx, INTRINSICS.fy] + [INTRINSICS.cx, INTRINSICS.cy]
    assert np.allclose(proj, np.rint(uv), atol=1e-9) or np.allclose(proj, uv)


def test_source_needs_image_and_depth():
    src = make_odometry(OdometryConfig(kind=OdometryKind.VISUAL), 3)
    assert isinstance(src, VisualOdometrySource)
    frame = Frame(index=0, timestamp_s=0.0, intrinsics=INTRINSICS, image_rgb=None)
    with pytest.raises(DataError, match="RGB image and a depth image"):
        src.update(frame, np.zeros((0, 3)), None)


def test_source_runs_on_rgb_frames(corridor):
    # the corridor's camera slides sideways as it weaves: not a car's planar circular motion
    cfg = OdometryConfig(kind=OdometryKind.VISUAL, visual_depth_window_px=1, visual_planar_motion=False)
    src = make_odometry(cfg, 5)
    for i, T in enumerate(corridor[:5]):
        gray, depth = render(T)
        rgb = np.repeat(gray[..., None], 3, axis=2)
        frame = Frame(index=i, timestamp_s=0.1 * i, intrinsics=INTRINSICS, image_rgb=rgb)
        est = src.update(frame, np.zeros((0, 3)), depth)
        assert est.ok
    gt = inverse(corridor[0]) @ corridor[4]
    assert pose_error(gt, est.T_odom_cam)[0] < 0.1


@pytest.mark.parametrize(
    ("kind", "from_model", "expected"),
    [
        (OdometryKind.AUTO, True, OdometryKind.VISUAL),
        (OdometryKind.AUTO, False, OdometryKind.KISS_ICP),
        (OdometryKind.KISS_ICP, True, OdometryKind.KISS_ICP),
        ("visual", False, OdometryKind.VISUAL),
    ],
)
def test_auto_picks_by_where_the_depth_comes_from_and_says_why(kind, from_model, expected):
    assert resolve_kind(kind, from_model) is expected
    choice = choose_odometry(kind, from_model)
    assert choice.kind is expected
    assert choice.reason.startswith("auto: ") == (OdometryKind(kind) is OdometryKind.AUTO)


@pytest.mark.parametrize("from_model", [True, False])
def test_auto_runs_the_robots_own_odometry_where_the_frames_bring_it(from_model):
    assert choose_odometry(OdometryKind.AUTO, from_model, odometry_given=True).kind is OdometryKind.GIVEN
    assert choose_odometry(OdometryKind.KISS_ICP, from_model, odometry_given=True).kind is OdometryKind.KISS_ICP


def test_a_motion_prior_replaces_the_constant_velocity_prediction_when_pnp_fails(corridor):
    """A blank frame keeps the given prior step exactly (not the last measured motion)."""
    vo = DepthVisualOdometry(depth_window_px=1)
    for T in corridor[:6]:
        vo.register(*render(T), INTRINSICS)
    prior = np.eye(4)
    prior[:3, :3] = rot_y(np.radians(8.0))
    prior[:3, 3] = [0.0, 0.0, 0.7]
    T_before = vo.T_odom_cam.copy()
    gray, depth = render(corridor[6])
    reg = vo.register(np.full_like(gray, 128), depth, INTRINSICS, motion_prior=prior)
    assert reg.status is not VisualStatus.OK
    np.testing.assert_allclose(inverse(T_before) @ reg.T_odom_cam, prior, atol=1e-9)


def test_yaw_prior_turns_the_prediction_to_the_image_yaw_and_keeps_its_translation():
    delta = np.eye(4)
    delta[:3, :3] = rot_y(np.radians(2.0))
    delta[:3, 3] = [0.1, 0.0, 1.0]
    assert yaw_prior(delta, np.radians(2.5), np.radians(1.0)) is None  # close enough: no prior
    prior = yaw_prior(delta, np.radians(-7.0), np.radians(1.0))
    assert prior is not None
    assert np.degrees(yaw_of(prior)) == pytest.approx(-7.0)
    np.testing.assert_array_equal(prior[:3, 3], delta[:3, 3])
    assert np.degrees(yaw_of(delta)) == pytest.approx(2.0)  # the input is not modified


class _FixedYaw:
    """Stands in for ``ImageYawEstimator``: every frame after the first turned by ``yaw_rad``."""

    def __init__(self, yaw_rad: float) -> None:
        self.yaw_rad, self._seen = yaw_rad, False

    def reset(self) -> None:
        self._seen = False

    def update(self, image_rgb: np.ndarray, fx_px: float) -> float | None:
        seen, self._seen = self._seen, True
        return self.yaw_rad if seen else None


def test_a_source_reset_with_motion_coasts_at_it_where_pnp_fails(corridor):
    """A re-initialisation inside a turn: the new segment's first frame is its origin, and a second frame that
    PnP cannot register (textureless, no image yaw) keeps the seeded motion, not rest."""
    motion = inverse(corridor[3]) @ corridor[4]
    for seed, expected in ((motion, motion), (None, np.eye(4))):
        src = make_odometry(OdometryConfig(kind=OdometryKind.VISUAL, visual_depth_window_px=1), 5)
        src.image_yaw = None
        poses = []
        for i, T in enumerate(corridor[:7]):
            if i == 5:
                src.reset(seed)
            gray, depth = render(T)
            if i == 6:
                gray = np.full_like(gray, 128)
            frame = Frame(index=i, timestamp_s=0.1 * i, intrinsics=INTRINSICS,
                          image_rgb=np.repeat(gray[..., None], 3, 2))  # fmt: skip
            est = src.update(frame, np.zeros((0, 3)), depth)
            poses.append(est.T_odom_cam)
        assert not est.ok
        np.testing.assert_allclose(poses[5], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(poses[6], expected, atol=1e-9)


class _FailingPnP:
    """Stands in for ``DepthVisualOdometry``: every frame after the first fails PnP, its step from the road or not."""

    def __init__(self, road_step: bool) -> None:
        self.road_step, self.T_odom_cam, self.predicted_delta, self.frames = road_step, np.eye(4), np.eye(4), 0

    def register(self, gray, depth_m, intrinsics, label_ids=None, motion_prior=None) -> VisualRegistration:
        self.frames += 1
        if self.frames == 1:
            return VisualRegistration(np.eye(4), VisualStatus.FIRST_FRAME, 0, 0, True)
        return VisualRegistration(np.eye(4), VisualStatus.PNP_FAILED, 20, 8, False, road_step=self.road_step)


@pytest.mark.parametrize(
    ("road_step", "yaw_deg", "measured"), [(True, 9.0, True), (False, 9.0, False), (True, None, False)]
)
def test_a_step_from_the_images_yaw_and_the_road_is_measured_where_pnp_fails(road_step, yaw_deg, measured):
    """PnP failing (a street of smooth trees): the step counts as measured when the images gave its turn (a sure
    peak) and the road its length and direction; either alone leaves it a prediction (the health check's coasting)."""
    yaw = _FixedYaw(0.0 if yaw_deg is None else np.radians(yaw_deg))
    src = VisualOdometrySource(_FailingPnP(road_step), image_yaw=yaw)
    if yaw_deg is None:
        src.image_yaw.update = lambda image_rgb, fx_px: None  # no sure peak
    rgb = np.zeros((INTRINSICS.height, INTRINSICS.width, 3), np.uint8)
    depth = np.full((INTRINSICS.height, INTRINSICS.width), 10.0, np.float32)
    for i in range(2):
        frame = Frame(index=i, timestamp_s=0.1 * i, intrinsics=INTRINSICS, image_rgb=rgb)
        est = src.update(frame, np.zeros((0, 3)), depth)
    assert est.ok is measured
    assert "pnp-failed" in est.note and ("road's motion kept" in est.note) is measured


def test_source_follows_the_image_turn_while_pnp_fails(corridor):
    """A textureless frame in a turn: the source's pose turns by the image yaw, not by the last step's."""
    src = make_odometry(OdometryConfig(kind=OdometryKind.VISUAL, visual_depth_window_px=1), 5)
    assert isinstance(src, VisualOdometrySource)
    src.image_yaw = _FixedYaw(0.0)
    poses = []
    for i, T in enumerate(corridor[:7]):
        gray, depth = render(T)
        if i == 6:
            src.image_yaw.yaw_rad = np.radians(9.0)
            gray = np.full_like(gray, 128)
        frame = Frame(index=i, timestamp_s=0.1 * i, intrinsics=INTRINSICS, image_rgb=np.repeat(gray[..., None], 3, 2))
        est = src.update(frame, np.zeros((0, 3)), depth)
        poses.append(est.T_odom_cam)
    assert not est.ok
    assert np.degrees(yaw_of(inverse(poses[5]) @ poses[6])) == pytest.approx(9.0, abs=0.2)
    assert est.rotation_disagreement_deg == pytest.approx(0.0, abs=0.2)

