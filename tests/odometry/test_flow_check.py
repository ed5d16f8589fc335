"""KISS-ICP's step against the image's own motion: the residual of right and wrong steps, PnP from the tracks,
the choice between them, and KISS-ICP over flat ground (where ICP alone stalls) kept on track."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shgm_slam.geometry.camera import backproject, project
from shgm_slam.geometry.se3 import make_pose
from shgm_slam.odometry import flow_check
from shgm_slam.odometry.flow_check import (
    SLIP_FLOOR_RAD,
    SLIP_RATIO,
    FlowTracks,
    Tracks,
    choose_step,
    flow_residual_rad,
    pnp_step,
)
from shgm_slam.odometry.image_rotation import ImageYawEstimator, rot_y, yaw_of
from shgm_slam.odometry.kiss import KissOdometry
from shgm_slam.odometry.sources import KissIcpSource
from shgm_slam.types import Frame, Intrinsics

K = Intrinsics(fx=160.0, fy=160.0, cx=159.5, cy=47.5, width=320, height=96)
HEIGHT_M = 20.0  # camera straight above flat ground, looking down (its z axis)
STEP_M = 0.5  # along the camera's x axis per frame: the ground moves 4 px per frame in the image


@pytest.fixture(scope="module")
def ground_texture() -> np.ndarray:
    """(H, long, 3) uint8 smooth random texture of the ground strip the camera flies along."""
    rng = np.random.default_rng(0)
    noise = rng.uniform(0, 255, (K.height, 2000)).astype(np.float32)
    grey = cv2.GaussianBlur(noise, (0, 0), 2.0)
    grey = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def _view(texture: np.ndarray, k: int) -> np.ndarray:
    """Image of frame k: the strip seen 4 px further along per frame (integer shifts, no resampling)."""
    shift = round(k * STEP_M * K.fx / HEIGHT_M)
    return np.ascontiguousarray(texture[:, shift : shift + K.width])


def _depth() -> np.ndarray:
    return np.full((K.height, K.width), HEIGHT_M, dtype=np.float32)


def _true_step() -> np.ndarray:
    return make_pose(np.eye(3), np.array([STEP_M, 0.0, 0.0]))


def test_the_true_step_explains_the_tracks_and_no_motion_does_not(ground_texture) -> None:
    flow = FlowTracks()
    assert flow.update(_view(ground_texture, 0), _depth(), K) is None  # the first frame: nothing to track
    tracks = flow.update(_view(ground_texture, 1), _depth(), K)
    assert tracks is not None and len(tracks.uv_cur) > 200
    assert flow_residual_rad(tracks, _true_step()) < 0.1 / K.fx  # a tenth of a pixel
    assert flow_residual_rad(tracks, np.eye(4)) == pytest.approx(4.0 / K.fx, rel=0.05)  # 4 px unexplained
    pnp = pnp_step(tracks)
    assert pnp is not None
    np.testing.assert_allclose(pnp[:3, 3], [STEP_M, 0.0, 0.0], atol=0.02)


def test_a_slipped_step_is_replaced_and_a_right_one_kept(ground_texture) -> None:
    flow = FlowTracks()
    flow.update(_view(ground_texture, 0), _depth(), K)
    tracks = flow.update(_view(ground_texture, 1), _depth(), K)
    stalled = np.eye(4)
    step, replaced = choose_step(stalled, tracks)
    assert replaced
    np.testing.assert_allclose(step, pnp_step(tracks))
    near = make_pose(np.eye(3), np.array([STEP_M * 0.97, 0.0, 0.0]))  # 0.12 px off: within the floor
    assert flow_residual_rad(tracks, near) < SLIP_FLOOR_RAD
    step, replaced = choose_step(near, tracks)
    assert not replaced and step is near
    assert choose_step(stalled, None) == (stalled, False)  # nothing to check against: ICP's


def test_pnp_is_solved_once_per_set_of_tracks_and_callers_get_their_own_arrays(ground_texture, monkeypatch) -> None:
    flow = FlowTracks()
    flow.update(_view(ground_texture, 0), _depth(), K)
    tracks = flow.update(_view(ground_texture, 1), _depth(), K)
    calls = []
    solve = flow_check._solve_pnp
    monkeypatch.setattr(flow_check, "_solve_pnp", lambda t: calls.append(t) or solve(t))
    first = pnp_step(tracks)
    first[:3, 3] = 99.0  # a caller's own copy: the answer asked for next is untouched
    second = pnp_step(tracks)
    step, inliers = flow_check.solve_pnp(tracks)
    assert len(calls) == 1
    np.testing.assert_allclose(second[:3, 3], [STEP_M, 0.0, 0.0], atol=0.02)
    np.testing.assert_array_equal(step, second)
    assert len(inliers) >= flow_check.MIN_TRACKS
    assert solve(tracks)[0] is not None and np.array_equal(solve(tracks)[0], second)  # the same answer solved anew


def _noisy_tracks(ground_texture, noise_px: float) -> Tracks:
    """Frame 1's tracks with their image positions jittered by ``noise_px`` (px std): tracks that no step explains
    well, so that a stalled step's residual stays below ``SLIP_RATIO`` times PnP's."""
    flow = FlowTracks()
    flow.update(_view(ground_texture, 0), _depth(), K)
    tracks = flow.update(_view(ground_texture, 1), _depth(), K)
    rng = np.random.default_rng(3)
    return Tracks(tracks.points_prev_cam, tracks.uv_cur + rng.normal(0.0, noise_px, tracks.uv_cur.shape), K)


def test_a_step_the_images_cannot_decide_is_replaced_where_the_depth_refuses_icps(ground_texture) -> None:
    tracks = _noisy_tracks(ground_texture, 1.0)
    short = make_pose(np.eye(3), np.array([0.2 * STEP_M, 0.0, 0.0]))  # ICP stopped short (as from rest)
    pnp = pnp_step(tracks)
    r_icp, r_pnp = flow_residual_rad(tracks, short), flow_residual_rad(tracks, pnp)
    assert SLIP_FLOOR_RAD < r_icp < SLIP_RATIO * r_pnp  # above the floor, but the images alone cannot decide

    def misfit_by_error(*steps: np.ndarray) -> tuple[float, ...]:  # the depth: worse the farther from the truth
        return tuple(0.002 + 0.5 * float(np.linalg.norm(s[:3, 3] - [STEP_M, 0.0, 0.0])) for s in steps)

    step, replaced = choose_step(short, tracks, misfits=misfit_by_error)
    assert replaced
    np.testing.assert_allclose(step, pnp)
    assert choose_step(short, tracks) == (short, False)  # without the depth's word: ICP's
    alike = choose_step(short, tracks, misfits=lambda *steps: tuple(0.01 for _ in steps))
    assert alike[0] is short and not alike[1]  # both fit the map alike (a slide along a plane): ICP's
    worse = choose_step(short, tracks, misfits=lambda *steps: tuple(0.02 if s is pnp else 0.01 for s in steps))
    assert not worse[1]
    asked = []

    def one_motion(a: np.ndarray, b: np.ndarray) -> bool:  # ICP's threshold: the two steps are one motion
        asked.append((a, b))
        return False

    same = choose_step(short, tracks, misfits=misfit_by_error, distinct=one_motion)
    assert same == (short, False) and len(asked) == 1  # the depth is not asked
    assert choose_step(short, tracks, misfits=misfit_by_error, distinct=lambda a, b: True)[1]


def test_tracks_left_behind_do_not_replace_a_step_the_prediction_and_the_depth_agree_on(ground_texture) -> None:
    """Tracks that agree on a quarter of the motion (pixels Lucas-Kanade left behind) against ICP's step, which
    kept pace with the constant-velocity prediction: refused where the cloud fits the map worse under the tracks'
    step, however little; kept where it fits better, where no prior is given (noisy depth) or nothing was predicted,
    or where the prior is as short as the tracks' step."""
    flow = FlowTracks()
    flow.update(_view(ground_texture, 0), _depth(), K)
    behind = flow.update(np.ascontiguousarray(ground_texture[:, 1 : 1 + K.width]), _depth(), K)  # 1 px: 0.125 m
    pnp = pnp_step(behind)
    assert pnp is not None and abs(pnp[0, 3] - STEP_M / 4) < 0.02
    icp = _true_step()  # ICP's step, the truth: 4 px, which the tracks do not explain
    assert flow_residual_rad(behind, icp) > SLIP_RATIO * flow_residual_rad(behind, pnp)
    predicted = make_pose(np.eye(3), np.array([0.95 * STEP_M, 0.0, 0.0]))

    def slightly_worse(*steps: np.ndarray) -> tuple[float, ...]:  # well within MISFIT_RATIO and the slack
        return tuple(0.012 if s is pnp or np.allclose(s, pnp) else 0.01 for s in steps)

    assert choose_step(icp, behind, misfits=slightly_worse, motion_prior=predicted) == (icp, False)
    step, replaced = choose_step(icp, behind, predicted, misfits=slightly_worse)  # no prior (noisy depth): replaced
    assert replaced and np.allclose(step, pnp)
    assert choose_step(icp, behind, misfits=slightly_worse, motion_prior=np.eye(4))[1]  # predicted rest
    short = make_pose(np.eye(3), np.array([STEP_M / 4, 0.0, 0.0]))
    assert choose_step(icp, behind, misfits=slightly_worse, motion_prior=short)[1]  # a prior as short as the tracks
    better = choose_step(
        icp, behind, misfits=lambda *steps: tuple(reversed(slightly_worse(*steps))), motion_prior=predicted
    )
    assert better[1] and np.allclose(better[0], pnp)  # the depth sides with the tracks


def test_images_that_do_not_move_together_give_no_tracks(ground_texture) -> None:
    flow = FlowTracks()
    flow.update(_view(ground_texture, 0), _depth(), K)
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 255, (K.height, K.width, 3), dtype=np.uint8)  # an unrelated image
    assert flow.update(noise, _depth(), K) is None
    flow.reset()
    assert flow.update(_view(ground_texture, 1), _depth(), K) is None  # after a reset: a first frame again


def _fly(texture: np.ndarray, flow: FlowTracks | None, frames: int = 30) -> tuple[np.ndarray, int]:
    """(frames, 3) positions KISS-ICP (with or without the flow check) gives the camera flying over flat ground."""
    source = KissIcpSource(KissOdometry(voxel_size_m=1.0, max_range_m=100.0), flow=flow)
    out, replaced = [], 0
    for k in range(frames):
        points, _ = backproject(_depth(), K, stride=2)
        est = source.update(Frame(k, 0.1 * k, K, image_rgb=_view(texture, k)), points, _depth())
        out.append(est.T_odom_cam[:3, 3])
        replaced += est.image_step
    return np.array(out), replaced


def test_kiss_icp_over_flat_ground_stalls_and_the_flow_check_keeps_it_moving(ground_texture) -> None:
    """The cloud is one plane: nothing pulls ICP along it, so from its zero-velocity start it stays put.
    The image tracks show the ground moving 4 px per frame; PnP's steps are kept and the camera moves
    as it should (and once KISS-ICP's velocity is right, its own steps are kept again)."""
    truth = np.arange(30)[:, None] * np.array([STEP_M, 0.0, 0.0])
    alone, _ = _fly(ground_texture, None)
    assert np.linalg.norm(alone[-1] - truth[-1]) > 10.0  # stalled: most of the 14.5 m missing
    checked, replaced = _fly(ground_texture, FlowTracks())
    assert np.linalg.norm(checked - truth, axis=1).max() < 0.5
    assert 1 <= replaced < 29


CYLINDER_M = 15.0  # the turning camera stands on the axis of a textured cylinder of this radius


def _cylinder_view(panorama: np.ndarray, yaw_rad: float, forward_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) uint8, z-depth (H, W) metres) of a camera inside a vertical cylinder whose inside is
    ``panorama`` (columns: heading -pi..pi; rows: height -6..6 m), turned by ``yaw_rad`` about its y axis from
    looking along +z and then moved ``forward_m`` along its own z axis from the cylinder's axis."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    dx, dy = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    ray_x, ray_z = c * dx + s, c - s * dx  # the ray (dx, dy, 1) turned into the cylinder's frame
    origin_x, origin_z = s * forward_m, c * forward_m
    a = ray_x**2 + ray_z**2
    b = 2 * (origin_x * ray_x + origin_z * ray_z)
    t = (-b + np.sqrt(b**2 - 4 * a * (origin_x**2 + origin_z**2 - CYLINDER_M**2))) / (2 * a)  # z-depth
    heading = np.arctan2(origin_x + t * ray_x, origin_z + t * ray_z)
    ph, pw = panorama.shape[:2]
    map_x = ((heading + np.pi) / (2 * np.pi) * pw).astype(np.float32)
    map_y = ((t * dy + 6.0) / 12.0 * ph).astype(np.float32)
    image = cv2.remap(panorama, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return image, t.astype(np.float32)


def _panorama(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grey = cv2.GaussianBlur(rng.uniform(0, 255, (400, 2400)).astype(np.float32), (0, 0), 2.5)
    return np.repeat(cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)[:, :, None], 3, 2)


def test_a_sharp_turn_is_tracked_from_the_turn_guess_and_solved_by_pnp() -> None:
    # 22 deg in one frame moves the image 65 px: Lucas-Kanade from zero motion keeps too few tracks to
    # check ICP's step (a car at an intersection with 4 frames/s); started where the guessed turn puts the
    # pixels it follows them, and PnP solves the turn.
    panorama = _panorama(1)
    turn = np.radians(22.0)
    frames = [_cylinder_view(panorama, yaw) for yaw in (0.0, turn)]

    def tracks_with(yaw_guess_rad: float | None):
        flow = FlowTracks()
        flow.update(*frames[0], K)
        guess = None if yaw_guess_rad is None else make_pose(rot_y(yaw_guess_rad), np.zeros(3))
        return flow.update(*frames[1], K, guess_step=guess)

    plain = tracks_with(None)
    assert plain is None or len(plain.uv_cur) < 100
    guessed = tracks_with(turn + np.radians(2.0))  # a guess 2 deg off (7 px) is enough
    assert guessed is not None and len(guessed.uv_cur) > 200
    pnp = pnp_step(guessed)
    assert pnp is not None
    assert np.degrees(yaw_of(pnp)) == pytest.approx(22.0, abs=0.3)
    step, replaced = choose_step(np.eye(4), guessed)  # ICP that missed the turn
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(22.0, abs=0.3)
    tiny = tracks_with(np.radians(0.5))  # under SEED_MIN_PX: not tried, as without a guess
    assert tiny is None or len(tiny.uv_cur) < 100


def test_the_tracking_not_chosen_is_kept_as_the_rival() -> None:
    # A 7 deg turn (21 px): Lucas-Kanade follows it from rest and from the guess alike; one tracking is chosen,
    # the other kept for choose_step, and both agree on the turn.
    panorama = _panorama(2)
    turn = np.radians(7.0)
    frames = [_cylinder_view(panorama, yaw) for yaw in (0.0, turn)]
    flow = FlowTracks()
    assert flow.update(*frames[0], K) is None and flow.rival is None
    chosen = flow.update(*frames[1], K, guess_step=make_pose(rot_y(turn), np.zeros(3)))
    assert chosen is not None and flow.rival is not None and flow.rival is not chosen
    for tracks in (chosen, flow.rival):
        assert np.degrees(yaw_of(pnp_step(tracks))) == pytest.approx(7.0, abs=0.3)
    flow.update(*frames[0], K)  # no guess: one tracking, no rival
    assert flow.rival is None
    flow.reset()
    assert flow.rival is None


def test_the_yaw_estimator_keeps_a_weak_peak_as_a_candidate_only() -> None:
    panorama = _panorama(2)
    estimator = ImageYawEstimator(min_response=0.99)  # no real peak is this strong
    assert estimator.update(_cylinder_view(panorama, 0.0)[0], K.fx) is None and estimator.candidate_rad is None
    assert estimator.update(_cylinder_view(panorama, np.radians(10.0))[0], K.fx) is None
    assert np.degrees(estimator.candidate_rad) == pytest.approx(10.0, abs=1.0)
    estimator.reset()
    assert estimator.candidate_rad is None


def test_a_fast_first_step_is_found_by_matched_features() -> None:
    # The odometry's first step assumes rest: 5 m toward a wall 15 m away (the image grows by half) leaves
    # Lucas-Kanade from rest no tracks; matched features give them, and the step they solve.
    panorama = _panorama(1)
    start, moved = _cylinder_view(panorama, 0.0), _cylinder_view(panorama, 0.0, forward_m=5.0)

    def tracks_with(motion_unknown: bool):
        flow = FlowTracks()
        flow.update(*start, K)
        return flow.update(*moved, K, np.eye(4), motion_unknown=motion_unknown)

    assert tracks_with(False) is None
    tracks = tracks_with(True)
    assert tracks is not None
    step, replaced = choose_step(np.eye(4), tracks)  # ICP that stayed at rest
    assert replaced
    np.testing.assert_allclose(step[:3, 3], [0.0, 0.0, 5.0], atol=0.2)


def test_a_turn_beyond_lucas_kanade_is_decided_by_matched_features() -> None:
    # 30 deg in one frame (a car at an intersection at 3 frames/s) moves the image by ~95 px, a third of its
    # width: Lucas-Kanade keeps too few tracks to decide, with no guess or a guess that missed the turn; the
    # matched ORB features of the same two frames follow it, and their PnP step replaces ICP's missed turn.
    panorama = _panorama(3)
    turn = np.radians(30.0)
    flow = FlowTracks()
    flow.update(*_cylinder_view(panorama, 0.0), K)
    tracks = flow.update(*_cylinder_view(panorama, turn), K, guess_step=np.eye(4))
    assert tracks is None or pnp_step(tracks) is None
    step, replaced = choose_step(np.eye(4), tracks)  # the tracks alone cannot decide: ICP's step stays
    assert not replaced
    step, replaced = choose_step(np.eye(4), tracks, matched=flow.matched)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(30.0, abs=1.0)
    assert flow.matched() is flow.matched()  # matched once per pair of frames
    right = make_pose(rot_y(turn), np.zeros(3))
    assert choose_step(right, tracks, matched=flow.matched) == (right, False)  # ICP that made the turn: kept
    flow.reset()
    assert not flow.pairable and flow.matched() is None


def test_the_source_asks_for_matched_features_where_lucas_kanade_lost_the_image(monkeypatch) -> None:
    # A 30 deg turn after the first step: Lucas-Kanade keeps too few tracks, yet the step is still checked,
    # against matched features of the same two frames (inside a cylinder ICP cannot tell turns apart, and its
    # cloud fits the part of the wall it mapped best without the turn: the map's fit then keeps ICP's step).
    import shgm_slam.odometry.sources as sources

    asked = []

    def spy(icp_step, tracks, guess_step=None, realign=None, matched=None, misfits=None, judged=None, *rest, **kw):
        other = None if matched is None else matched()
        asked.append((tracks is None, other is not None))
        return choose_step(icp_step, tracks, guess_step, realign, matched, misfits, judged, *rest, **kw)

    monkeypatch.setattr(sources, "choose_step", spy)
    panorama = _panorama(3)
    source = KissIcpSource(KissOdometry(voxel_size_m=0.5, max_range_m=30.0), flow=FlowTracks())
    for k, yaw_deg in enumerate((0.0, 1.0, 31.0)):  # the turn after the first step (that one is always matched)
        image, depth = _cylinder_view(panorama, np.radians(yaw_deg))
        points, _ = backproject(depth, K, stride=2)
        source.update(Frame(k, 0.3 * k, K, image_rgb=image), points, depth)
    assert asked[-1] == (True, True)


def _forward_tracks(step_m: float, noise_px: float = 0.3) -> Tracks:
    """Tracks of points 6-40 m ahead of a camera that moved ``step_m`` along its optical axis."""
    rng = np.random.default_rng(5)
    n = 80
    points = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-2, 1.5, n), rng.uniform(6, 40, n)])
    uv, _ = project(points - [0.0, 0.0, step_m], K)
    return Tracks(points, uv + rng.normal(0.0, noise_px, uv.shape), K)


def test_a_robot_already_at_speed_is_found_along_the_camera_axis_where_pnp_cannot_solve() -> None:
    tracks = _forward_tracks(3.0)
    rest = np.eye(4)
    start = flow_check._along_axis(rest, tracks)
    assert start is not None and abs(start[2, 3] - 3.0) < 0.2  # within the search's spacing (12 m / 64)
    assert flow_check._along_axis(make_pose(np.eye(3), [0.0, 0.0, 3.0]), tracks) is None  # nothing explains them better

    def misfit_by_error(*steps: np.ndarray) -> tuple[float, ...]:
        return tuple(0.002 + 0.05 * float(np.linalg.norm(s[:3, 3] - [0.0, 0.0, 3.0])) for s in steps)

    realigned = []

    def realign(guess: np.ndarray) -> np.ndarray:  # ICP from the start converges to the truth near it
        realigned.append(guess)
        return make_pose(np.eye(3), [0.0, 0.0, 3.0]) if abs(guess[2, 3] - 3.0) < 0.5 else guess

    r_rest = flow_residual_rad(tracks, rest)
    step, replaced = flow_check._judged_search(rest, tracks, r_rest, realign, misfit_by_error, lambda *s: 100, None)
    assert replaced
    np.testing.assert_allclose(step[:3, 3], [0.0, 0.0, 3.0])
    # tracks of a camera at rest back ICP's standstill: nothing along the axis explains them better
    still = _forward_tracks(0.0)
    step, replaced = flow_check._judged_search(rest, still, flow_residual_rad(still, rest), realign, misfit_by_error,
                                               lambda *s: 100, None)  # fmt: skip
    assert not replaced and step is rest


def test_the_source_searches_for_the_speed_only_at_the_first_step_from_rest(monkeypatch) -> None:
    """Only the first step of an odometry started from rest has nothing to predict it; after a restart that remembers
    the motion before it (``reset(motion)``), and at every later step, the prediction stands."""
    import shgm_slam.odometry.sources as sources

    calls: list[int] = []

    def spy(icp_step, *rest, **kw):
        calls.append(len(frames_seen))
        return icp_step, False

    monkeypatch.setattr(sources, "speed_search", spy)
    panorama = _panorama(3)
    source = KissIcpSource(KissOdometry(voxel_size_m=0.5, max_range_m=30.0), flow=FlowTracks())
    frames_seen: list[int] = []
    for start in (None, make_pose(rot_y(np.radians(1.0)), np.zeros(3))):
        source.reset(start)
        for k, yaw_deg in enumerate((0.0, 1.0, 2.0, 3.0)):
            image, depth = _cylinder_view(panorama, np.radians(yaw_deg))
            points, _ = backproject(depth, K, stride=2)
            frames_seen.append(k)
            source.update(Frame(k, 0.3 * k, K, image_rgb=image), points, depth)
    assert calls == [2]  # the second frame of the start from rest only


@pytest.mark.parametrize(("noise", "prior_given"), [(0.0, True), (0.02, False)])
def test_the_source_gives_its_motion_prior_to_the_step_choice_only_on_noise_free_depth(
    monkeypatch, noise, prior_given
) -> None:
    """On noisy depth two steps' misfits differ by the noise: the left-behind rule (``_left_behind``) is not asked."""
    import shgm_slam.odometry.sources as sources

    priors: list[np.ndarray | None] = []

    def spy(icp_step, *rest, motion_prior=None, **kw):
        priors.append(motion_prior)
        return icp_step, False

    monkeypatch.setattr(sources, "choose_step", spy)
    panorama = _panorama(3)
    source = KissIcpSource(KissOdometry(voxel_size_m=0.5, max_range_m=30.0), flow=FlowTracks(), depth_noise_rel=noise)
    for k, yaw_deg in enumerate((0.0, 1.0, 2.0)):
        image, depth = _cylinder_view(panorama, np.radians(yaw_deg))
        points, _ = backproject(depth, K, stride=2)
        source.update(Frame(k, 0.3 * k, K, image_rgb=image), points, depth)
    assert len(priors) == 2
    assert all((p is not None) == prior_given for p in priors)
