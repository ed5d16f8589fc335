"""ICP run again from the image's turn where PnP cannot decide (``choose_step``'s second chance) and
``KissOdometry.realign``, the ICP it runs: a sharp turn at a low frame rate leaves too few tracks for PnP,
ICP from the constant-velocity prediction misses the turn, and ICP from the image's guess finds it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from shgm_slam.geometry.se3 import inverse, make_pose
from shgm_slam.odometry.flow_check import (
    MIN_TRACKS,
    MISFIT_RATIO,
    MISFIT_SLACK,
    MISFIT_SLACK_FLOOR,
    SIDEWAYS_SEARCH,
    SLIP_RATIO,
    TURN_SEARCH_DEG,
    Tracks,
    choose_step,
    flow_residual_rad,
    pnp_step,
    speed_search,
    turn_search,
)
from shgm_slam.odometry.image_rotation import rot_y, yaw_of
from shgm_slam.odometry.kiss import KissOdometry
from shgm_slam.types import Intrinsics

K = Intrinsics(fx=184.0, fy=184.0, cx=159.5, cy=47.5, width=320, height=96)
TURN_DEG = 16.8  # one frame of a car's turn at an intersection, seen at 3 frames/s


def _true_step() -> np.ndarray:
    return make_pose(rot_y(np.radians(TURN_DEG)), np.array([0.3, 0.0, 3.0]))


def _tracks(step: np.ndarray, count: int) -> Tracks:
    """``count`` points 8-30 m ahead of the previous camera, seen where ``step`` (this camera in the previous
    one) puts them: right tracks, too few for PnP when ``count`` < ``MIN_TRACKS``."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-6, 6, count), rng.uniform(-2, 1, count), rng.uniform(8, 30, count)])
    T_cur_prev = inverse(step)
    cur = points @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3]
    uv = np.column_stack([K.fx * cur[:, 0] / cur[:, 2] + K.cx, K.fy * cur[:, 1] / cur[:, 2] + K.cy])
    return Tracks(points, uv, K)


class _Realign:
    """A stand-in for ``KissOdometry.realign``: returns ``answer`` and records the guesses it was given."""

    def __init__(self, answer: np.ndarray) -> None:
        self.answer = answer
        self.guesses: list[np.ndarray] = []

    def __call__(self, guess_step: np.ndarray) -> np.ndarray:
        self.guesses.append(guess_step)
        return self.answer


def test_without_pnp_icp_from_the_images_turn_replaces_a_missed_turn() -> None:
    truth = _true_step()
    tracks = _tracks(truth, MIN_TRACKS - 10)
    assert pnp_step(tracks) is None  # too few tracks: PnP cannot decide
    missed = make_pose(rot_y(np.radians(1.7)), np.array([0.0, 0.0, 3.0]))  # ICP from constant velocity
    guess = make_pose(rot_y(np.radians(TURN_DEG - 0.2)), np.array([0.0, 0.0, 3.0]))  # the image's turn
    assert flow_residual_rad(tracks, missed) > 10 * flow_residual_rad(tracks, guess)
    found = _Realign(truth)
    step, replaced = choose_step(missed, tracks, guess, found)
    assert replaced and step is truth
    assert len(found.guesses) == 1 and found.guesses[0] is guess
    # without the second chance (no guess or no ICP to run again) ICP's step stays, as before
    assert choose_step(missed, tracks) == (missed, False)
    assert choose_step(missed, tracks, guess, None) == (missed, False)


def test_icp_from_the_turn_must_agree_with_the_images_too() -> None:
    truth = _true_step()
    tracks = _tracks(truth, MIN_TRACKS - 10)
    missed = make_pose(rot_y(np.radians(1.7)), np.array([0.0, 0.0, 3.0]))
    guess = make_pose(rot_y(np.radians(TURN_DEG)), np.array([0.0, 0.0, 3.0]))
    back = _Realign(missed)  # the depth pulls ICP back to its own step: the images alone do not decide
    step, replaced = choose_step(missed, tracks, guess, back)
    assert not replaced and step is missed and len(back.guesses) == 1


def test_a_guess_no_better_than_icp_is_not_tried() -> None:
    truth = _true_step()
    tracks = _tracks(truth, MIN_TRACKS - 10)
    missed = make_pose(rot_y(np.radians(1.7)), np.array([0.0, 0.0, 3.0]))
    wrong_guess = make_pose(rot_y(np.radians(-12.0)), np.array([0.0, 0.0, 3.0]))  # the other way
    never = _Realign(truth)
    step, replaced = choose_step(missed, tracks, wrong_guess, never)
    assert not replaced and step is missed and never.guesses == []
    right = make_pose(rot_y(np.radians(TURN_DEG)), np.array([0.3, 0.0, 3.0]))
    assert choose_step(right, tracks, right, never) == (right, False)  # ICP right: nothing to try
    assert never.guesses == []


def test_matched_features_too_few_for_pnp_judge_icp_from_a_rough_guess() -> None:
    # Lucas-Kanade lost the turn (no tracks), the matched features are too few for PnP, and the images' guess
    # is rough (half the turn, only ~2.5 times better than ICP's step): ICP runs again from it anyway, and what it
    # reaches is kept where the matched features agree with it (and the map does not fit it worse).
    truth = make_pose(rot_y(np.radians(26.0)), np.array([0.6, 0.0, 2.7]))
    matched = _tracks(truth, MIN_TRACKS - 4)
    assert pnp_step(matched) is None
    missed = make_pose(rot_y(np.radians(1.2)), np.array([0.0, 0.0, 1.3]))
    rough = make_pose(rot_y(np.radians(17.0)), np.array([0.0, 0.0, 2.7]))
    assert flow_residual_rad(matched, missed) < 3 * flow_residual_rad(matched, rough)  # LK's gate would not try it
    found = _Realign(truth)
    step, replaced = choose_step(missed, None, rough, found, lambda: matched)
    assert replaced and step is truth and found.guesses == [rough]
    # the map vetoes it like any replacement
    vetoed = choose_step(missed, None, rough, _Realign(truth), lambda: matched, lambda icp, step: (0.001, 0.05))
    assert vetoed == (missed, False)
    # what ICP reaches must explain the matched features: pulled back to its own step, nothing is replaced
    assert choose_step(missed, None, rough, _Realign(missed), lambda: matched) == (missed, False)
    # matched features that agree with ICP's step: nothing is run again
    never = _Realign(truth)
    assert choose_step(truth, None, rough, never, lambda: matched) == (truth, False) and never.guesses == []


def _scene() -> np.ndarray:
    """(N, 3) points of a street corner in the first camera's frame: two facades, a wall ahead and the
    ground (x right, y down, z forward), ~0.25 m apart."""
    s = np.arange(-20.0, 40.0, 0.25)
    h = np.arange(-6.0, 1.5, 0.25)
    S, H = np.meshgrid(s, h)
    left = np.column_stack([np.full(S.size, -8.0), H.ravel(), S.ravel()])
    right = np.column_stack([np.full(S.size, 9.0), H.ravel(), S.ravel()])
    X, Hw = np.meshgrid(np.arange(-8.0, 9.0, 0.25), h)
    ahead = np.column_stack([X.ravel(), Hw.ravel(), np.full(X.size, 40.0)])
    Xg, Zg = np.meshgrid(np.arange(-8.0, 9.0, 0.5), np.arange(-20.0, 40.0, 0.5))
    ground = np.column_stack([Xg.ravel(), np.full(Xg.size, 1.5), Zg.ravel()])
    bumps = np.column_stack([np.full(40, -7.5), np.linspace(-5, 1, 40), np.linspace(2, 35, 40)])  # a row of posts
    return np.vstack([left, right, ahead, ground, bumps])


def _seen_from(points_world: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """The scene's points within 30 m in the camera ``T_world_cam``'s frame (every direction: a clean cloud)."""
    T = inverse(T_world_cam)
    cam = points_world @ T[:3, :3].T + T[:3, 3]
    return cam[np.linalg.norm(cam, axis=1) < 30.0]


def test_kiss_realign_runs_icp_again_without_touching_the_map() -> None:
    scene = _scene()
    small_turn = make_pose(rot_y(np.radians(3.0)), np.array([0.0, 0.0, 1.0]))

    def odometry_after_two() -> KissOdometry:
        odo = KissOdometry(voxel_size_m=0.5, max_range_m=30.0)
        odo.register(_seen_from(scene, np.eye(4)))
        odo.register(_seen_from(scene, small_turn))
        return odo

    with pytest.raises(RuntimeError, match="only valid inside"):
        odometry_after_two().realign(np.eye(4))
    T_world_2 = small_turn @ make_pose(rot_y(np.radians(8.0)), np.array([0.2, 0.0, 1.5]))
    cloud = _seen_from(scene, T_world_2)
    plain, probed = odometry_after_two(), odometry_after_two()
    plain.register(cloud, fuse_step=lambda icp_step: icp_step)
    true_step = inverse(small_turn) @ T_world_2
    realigned: list[np.ndarray] = []

    def probe(icp_step: np.ndarray) -> np.ndarray:
        realigned.append(probed.realign(true_step))
        realigned.append(probed.realign(probed.predicted_delta))  # KISS-ICP's own start again
        return icp_step

    T_odom_prev = probed.T_odom_cam
    probed.register(cloud, fuse_step=probe)
    np.testing.assert_array_equal(probed.T_odom_cam, plain.T_odom_cam)  # nothing of it was kept
    np.testing.assert_allclose(plain.local_map_points(), probed.local_map_points())
    from_truth, own = realigned
    np.testing.assert_allclose(from_truth[:3, 3], true_step[:3, 3], atol=0.05)
    assert np.degrees(yaw_of(from_truth)) == pytest.approx(np.degrees(yaw_of(true_step)), abs=0.2)
    np.testing.assert_allclose(probed.T_odom_cam, T_odom_prev @ own, atol=1e-9)  # the same ICP, the same step


def test_a_replacement_that_fits_the_map_worse_is_vetoed() -> None:
    # The tracks agree on a wrong motion (pixels left behind agree on none while the car drove 2.8 m): ICP's
    # cloud fits the map, the image's step does not, and ICP's step stays.
    truth = _true_step()
    tracks = _tracks(truth, MIN_TRACKS + 40)  # enough for PnP, which here finds the truth
    missed = make_pose(np.eye(3), np.zeros(3))
    worse = MISFIT_RATIO * 0.10 + MISFIT_SLACK + 0.01
    assert choose_step(missed, tracks, misfits=lambda icp, step: (0.10, worse)) == (missed, False)
    alike = MISFIT_RATIO * 0.10 + MISFIT_SLACK - 0.01  # a plane: every step along it fits alike
    step, replaced = choose_step(missed, tracks, misfits=lambda icp, step: (0.10, alike))
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(TURN_DEG, abs=0.5)
    # ICP on the samples themselves: a step along the plane fits to their spacing
    assert choose_step(missed, tracks, misfits=lambda icp, step: (0.0, 2e-4))[1]


def test_where_icp_fits_the_map_closely_a_step_many_times_worse_is_vetoed() -> None:
    # The map's sampling lets a slide along a surface fit worse by a few times ICP's own misfit: where ICP's cloud
    # fits to 3e-4, a step fitting 0.0065 (within the fixed slack) is a wrong one; at the level of the map's
    # sampling noise (below MISFIT_SLACK_FLOOR) steps still fit alike.
    truth = _true_step()
    tracks = _tracks(truth, MIN_TRACKS + 40)
    missed = make_pose(np.eye(3), np.zeros(3))
    assert 0.0065 < MISFIT_RATIO * 3e-4 + MISFIT_SLACK
    assert choose_step(missed, tracks, misfits=lambda icp, step: (3e-4, 0.0065)) == (missed, False)
    assert choose_step(missed, tracks, misfits=lambda icp, step: (1e-4, 4e-4))[1]
    assert choose_step(missed, tracks, misfits=lambda icp, step: (0.0058, 0.0178))[1]  # the corridor's walls
    assert choose_step(missed, tracks, misfits=lambda icp, step: (0.0, MISFIT_SLACK_FLOOR * 1.01)) == (missed, False)


def test_a_rival_tracking_that_backs_icp_keeps_its_step() -> None:
    # Lucas-Kanade from rest: pixels left behind agree on a short step; from the guess: the truth, which ICP found.
    truth = make_pose(np.eye(3), np.array([0.0, 0.0, 2.8]))
    left_behind = _tracks(make_pose(np.eye(3), np.array([0.0, 0.0, 0.5])), MIN_TRACKS + 40)
    from_guess = _tracks(truth, MIN_TRACKS + 10)
    step, replaced = choose_step(truth, left_behind)
    assert replaced and step[2, 3] == pytest.approx(0.5, abs=0.05)  # alone, the short step would win
    assert choose_step(truth, left_behind, rival=from_guess) == (truth, False)
    fits = lambda icp_fit, step_fit: lambda icp, step: (icp_fit, step_fit)  # noqa: E731
    assert choose_step(truth, left_behind, misfits=fits(2e-4, 3e-4), rival=from_guess) == (truth, False)
    # ICP stalled where the pixels stayed put (a start from rest): the rival agrees with ICP's stall, the map
    # prefers the tracks' step
    stalled = make_pose(np.eye(3), np.array([0.0, 0.0, 0.1]))
    at_rest = _tracks(stalled, MIN_TRACKS + 10)
    moving = _tracks(truth, MIN_TRACKS + 40)
    step, replaced = choose_step(stalled, moving, misfits=fits(0.05, 0.01), rival=at_rest)
    assert replaced and step[2, 3] == pytest.approx(2.8, abs=0.05)
    assert choose_step(stalled, moving, misfits=fits(0.01, 0.012), rival=at_rest) == (stalled, False)
    # a rival that backs neither ICP's step nor the tracks' does not stop a replacement of a slipped step
    slipped = make_pose(np.eye(3), np.array([0.0, 0.0, 1.5]))
    elsewhere = _tracks(make_pose(rot_y(np.radians(5.0)), np.array([0.5, 0.0, 2.0])), MIN_TRACKS + 10)
    step, replaced = choose_step(slipped, left_behind, rival=elsewhere)
    assert replaced and step[2, 3] == pytest.approx(0.5, abs=0.05)


def _walled_street() -> np.ndarray:
    """(N, 3) a street (x right, y down, z forward) between garden walls that run across it from the curbs
    outwards at uneven gaps (0.2 m apart on each wall), over the ground: the walls tell positions along it apart."""
    rng = np.random.default_rng(5)
    W, H = np.meshgrid(np.arange(0.0, 5.0, 0.2), np.arange(-2.5, 1.5, 0.2))
    walls = [np.column_stack([side * (3.0 + W.ravel()), H.ravel(), np.full(W.size, z)])
             for side in (-1.0, 1.0) for z in np.cumsum(rng.uniform(5.0, 9.0, 9)) - 15.0]  # fmt: skip
    Xg, Zg = np.meshgrid(np.arange(-8.0, 9.0, 0.5), np.arange(-20.0, 60.0, 0.5))
    ground = np.column_stack([Xg.ravel(), np.full(Xg.size, 1.5), Zg.ravel()])
    return np.vstack([*walls, ground])


def test_kiss_map_misfit_tells_a_right_step_from_a_wrong_one() -> None:
    scene = _walled_street()
    odo = KissOdometry(voxel_size_m=0.5, max_range_m=30.0)
    odo.reset(make_pose(np.eye(3), np.array([0.0, 0.0, 2.8])))  # started at its speed (from rest ICP stalls here)
    for k in range(8):  # driving 2.8 m per frame (a car at 3 frames/s)
        odo.register(_seen_from(scene, make_pose(np.eye(3), np.array([0.0, 0.0, 2.8 * k]))))
    with pytest.raises(RuntimeError, match="only valid inside"):
        odo.map_misfits(np.eye(4))
    seen: dict[str, float] = {}

    def probe(icp_step: np.ndarray) -> np.ndarray:
        seen["icp"], seen["stalled"] = odo.map_misfits(icp_step, np.eye(4))  # stalled: as tracks left behind say
        return icp_step

    odo.register(_seen_from(scene, make_pose(np.eye(3), np.array([0.0, 0.0, 2.8 * 8]))), fuse_step=probe)
    np.testing.assert_allclose(odo.T_odom_cam[:3, 3], [0.0, 0.0, 2.8 * 8], atol=0.1)
    assert 0.0 <= seen["icp"] < 0.05
    assert seen["stalled"] > MISFIT_RATIO * seen["icp"] + MISFIT_SLACK


def _in_view(points_world: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """The scene's points a camera ``T_world_cam`` with a 90 deg field of view sees within 30 m (its frame)."""
    T = inverse(T_world_cam)
    cam = points_world @ T[:3, :3].T + T[:3, 3]
    ahead = (cam[:, 2] > 0.5) & (np.abs(np.arctan2(cam[:, 0], cam[:, 2])) < np.radians(45.0))
    return cam[ahead & (np.linalg.norm(cam, axis=1) < 30.0)]


def test_without_tracks_icp_from_further_round_the_turn_finds_a_missed_turn() -> None:
    # A car at 3.3 frames/s turns 26 deg in one frame; nothing in the images judges the step (no tracks, no
    # matched features). ICP from the constant-velocity prediction stays straight, its cloud fits the map
    # badly, and ICP again from its own step turned further finds the turn.
    scene = _walled_street()
    poses = [make_pose(np.eye(3), np.array([0.0, 0.0, 2.8 * k])) for k in range(6)]
    turn = make_pose(rot_y(np.radians(26.0)), np.array([0.6, 0.0, 2.7]))
    odo = KissOdometry(voxel_size_m=0.5, max_range_m=30.0)
    odo.reset(make_pose(np.eye(3), np.array([0.0, 0.0, 2.8])))
    for T in poses:
        odo.register(_in_view(scene, T))
    seen: dict[str, object] = {}

    def check(icp_step: np.ndarray) -> np.ndarray:
        seen["icp"] = icp_step
        with pytest.raises(RuntimeError, match="only valid inside"):
            KissOdometry().map_judged(icp_step)
        step, seen["replaced"] = choose_step(icp_step, None, None, odo.realign, lambda: None, odo.map_misfits,
                                             odo.map_judged)  # fmt: skip
        return step

    odo.register(_in_view(scene, poses[-1] @ turn), fuse_step=check)
    assert abs(np.degrees(yaw_of(seen["icp"]))) < 5.0  # ICP missed the turn
    assert seen["replaced"]
    kept = inverse(poses[-1]) @ odo.T_odom_cam
    assert np.degrees(yaw_of(kept)) == pytest.approx(26.0, abs=1.0)


class _Fits:
    """Stand-ins for ``KissOdometry.map_misfits`` and ``map_judged``: a step's misfit and judged points follow its
    yaw (``misfit_of`` and ``judged_of``: degrees -> value); the pair's judged points are the fewer of the two."""

    def __init__(
        self, misfit_of: Callable[[float], float], judged_of: Callable[[float], int] = lambda deg: 1000
    ) -> None:
        self.misfit_of, self.judged_of = misfit_of, judged_of

    def misfits(self, *steps: np.ndarray) -> tuple[float, ...]:
        return tuple(self.misfit_of(np.degrees(yaw_of(s))) for s in steps)

    def judged(self, *steps: np.ndarray) -> int:
        return min(self.judged_of(np.degrees(yaw_of(s))) for s in steps)


def _snap_to(deg: float, basin_deg: float = 8.0) -> Callable[[np.ndarray], np.ndarray]:
    """A stand-in ICP: from a start within ``basin_deg`` of ``deg`` it reaches the turn ``deg``; else it stays."""

    def realign(start: np.ndarray) -> np.ndarray:
        if abs(np.degrees(yaw_of(start)) - deg) <= basin_deg:
            return make_pose(rot_y(np.radians(deg)), start[:3, 3])
        return start

    return realign


def test_turn_search_runs_only_where_icp_fits_badly_and_keeps_the_best_fit() -> None:
    icp = make_pose(rot_y(np.radians(2.0)), np.array([0.0, 0.0, 3.0]))
    calls: list[np.ndarray] = []

    def counted(start: np.ndarray) -> np.ndarray:
        calls.append(start)
        return _snap_to(24.0)(start)

    healthy = _Fits(lambda deg: 0.001 if abs(deg - 2.0) < 0.5 else 0.2)  # ICP's step fits: nothing runs again
    assert turn_search(icp, counted, healthy.misfits, healthy.judged) == (icp, False) and calls == []
    bad = _Fits(lambda deg: 0.002 if abs(deg - 24.0) < 0.5 else 0.3)
    step, replaced = turn_search(icp, counted, bad.misfits, bad.judged)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(24.0)
    assert len(calls) == 2 * len(TURN_SEARCH_DEG) + 2 * len(SIDEWAYS_SEARCH)  # the turns, then sideways
    # nothing fits clearly better (a plane: every step alike): ICP's step stays
    flat = _Fits(lambda deg: 0.05 if abs(deg - 24.0) < 0.5 else 0.06)
    assert turn_search(icp, _snap_to(24.0), flat.misfits, flat.judged) == (icp, False)
    # without the map's judgement nothing is replaced
    assert turn_search(icp, _snap_to(24.0), None, None) == (icp, False)


def test_turn_search_replaces_a_missed_turn_that_fits_the_map_only_slightly_badly() -> None:
    """A backward camera's missed turn (synthia-like tuning seed 10): ICP's step fits the map with a misfit below
    ``MISFIT_SLACK`` yet far above a step that fits as closely as the map's sampling allows; the search runs and the
    turn wins. Where the turn fits no clearly better, or ICP's own misfit is the sampling's floor, ICP's stays."""
    icp = make_pose(rot_y(np.radians(22.0)), np.array([0.0, 0.0, 3.0]))
    slight = _Fits(lambda deg: 0.0001 if abs(deg - 32.0) < 0.5 else 0.008)
    step, replaced = turn_search(icp, _snap_to(32.0), slight.misfits, slight.judged)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(32.0)
    alike = _Fits(lambda deg: 0.004 if abs(deg - 32.0) < 0.5 else 0.008)  # within MISFIT_RATIO plus the slack
    assert turn_search(icp, _snap_to(32.0), alike.misfits, alike.judged) == (icp, False)
    calls: list[np.ndarray] = []
    floor = _Fits(lambda deg: 0.0 if abs(deg - 32.0) < 0.5 else MISFIT_SLACK_FLOOR)
    assert turn_search(icp, lambda start: calls.append(start) or start, floor.misfits, floor.judged) == (icp, False)
    assert calls == []  # nothing can fit clearly better than the floor: nothing runs again


def test_icp_that_found_the_turn_but_stopped_to_the_side_is_moved_by_the_sideways_search() -> None:
    # A 31 deg turn in one frame (3.3 frames/s): ICP again from the images' guess reaches the turn but stops 3.5 m
    # to the left of the truth, where the map fits 8 times worse than at the truth; from 3 m to the right (one
    # step's length) it reaches the truth.
    truth = make_pose(rot_y(np.radians(31.0)), np.array([0.85, 0.0, 3.05]))
    aside = make_pose(rot_y(np.radians(31.0)), np.array([-2.7, 0.0, 2.7]))

    def icp(start: np.ndarray) -> np.ndarray:  # the truth's basin: within 2.5 m of it, else the side minimum
        return truth if np.linalg.norm(start[:3, 3] - truth[:3, 3]) < 2.5 else aside

    def misfits(*steps: np.ndarray) -> tuple[float, ...]:
        return tuple(0.003 if np.allclose(s, truth) else 0.023 if np.allclose(s, aside) else 0.2 for s in steps)

    def judged(*steps: np.ndarray) -> int:
        return 500

    tracks = _tracks(truth, MIN_TRACKS - 10)  # too few for PnP: ICP runs again from the guess
    guess = make_pose(rot_y(np.radians(29.0)), np.array([-2.0, 0.0, 3.0]))  # ICP from it stops aside
    missed = make_pose(rot_y(np.radians(-10.0)), np.array([-0.4, 0.0, 1.35]))
    for step in (guess, aside):
        assert flow_residual_rad(tracks, missed) > SLIP_RATIO * flow_residual_rad(tracks, step)
    step, replaced = choose_step(missed, tracks, guess, icp, misfits=misfits, judged=judged)
    assert replaced and step is truth
    # the same where no tracks judge the step: the turn search, then sideways
    step, replaced = turn_search(make_pose(rot_y(np.radians(25.0)), np.array([-0.4, 0.0, 1.35])), icp, misfits, judged)
    assert replaced and step is truth
    # where the side minimum fits as well, nothing moves
    alike = lambda *steps: tuple(0.01 for _ in steps)  # noqa: E731
    assert choose_step(missed, tracks, guess, icp, misfits=alike, judged=judged) == (aside, True)


def test_turn_search_reaches_a_turn_beyond_twenty_degrees_from_icps_step() -> None:
    # Airsim-like tuning seed 27's car2 at 3.3 frames/s: a 25.9 deg turn in one frame, ICP registered -0.5 deg, and
    # ICP reached the turn only from starts 21.5-29.5 deg (from 19.5 it stalled at 19.8): a basin narrower than the
    # search's spacing. From ICP's step turned 30 deg further the turn is found.
    icp = make_pose(rot_y(np.radians(-0.5)), np.array([0.2, -0.2, 2.9]))
    fits = _Fits(lambda deg: 0.055 if abs(deg - 26.0) < 0.5 else 0.72)
    step, replaced = turn_search(icp, _snap_to(26.0, basin_deg=5.0), fits.misfits, fits.judged)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(26.0)


def test_turn_search_refuses_a_step_judged_on_a_sliver_of_the_view() -> None:
    # ICP again reaches a turn 40 deg the other way, which fits better only on the few points both steps put
    # where the previous camera saw: refused.
    icp = make_pose(rot_y(np.radians(-6.0)), np.array([0.0, 0.0, 3.0]))
    sliver = _Fits(lambda deg: 0.002 if deg < -30.0 else 0.3, lambda deg: 200 if deg < -30.0 else 1000)
    assert turn_search(icp, _snap_to(-45.0, basin_deg=20.0), sliver.misfits, sliver.judged) == (icp, False)
    shared = _Fits(sliver.misfit_of)  # the same fit on most of the view: kept
    step, replaced = turn_search(icp, _snap_to(-45.0, basin_deg=20.0), shared.misfits, shared.judged)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(-45.0)


def test_turn_search_from_the_predicted_speed_on_the_arc_finds_a_turn_icp_stalled_in() -> None:
    # A car at 3.3 frames/s turns 30 deg in one frame at 3 m per frame; ICP registered 7 deg and stalled 1 m ahead
    # (no tracks, the map fits badly). ICP finds the truth only from a start near it in both yaw and place: its own
    # step turned further is 2 m short; the predicted step (3 m) on the arc of the turned heading is near.
    truth = make_pose(rot_y(np.radians(30.0)), np.array([0.78, 0.0, 2.9]))
    stalled = make_pose(rot_y(np.radians(7.0)), np.array([-0.37, 0.0, 1.03]))
    prediction = make_pose(rot_y(np.radians(5.0)), np.array([0.0, 0.0, 3.0]))  # the last step, at constant velocity

    def icp(start: np.ndarray) -> np.ndarray:  # the truth's basin: within 8 deg and 1 m of it
        near = abs(np.degrees(yaw_of(start)) - 30.0) <= 8.0 and np.linalg.norm(start[:3, 3] - truth[:3, 3]) < 1.0
        return truth if near else start

    fits = _Fits(lambda deg: 0.1 if abs(deg - 30.0) < 0.5 else 0.7)
    assert turn_search(stalled, icp, fits.misfits, fits.judged) == (stalled, False)  # its own step turned: short
    step, replaced = turn_search(stalled, icp, fits.misfits, fits.judged, prediction)
    assert replaced and step is truth
    # a backward-looking camera (moving along -z): the arc turns its own direction of travel
    back_truth = make_pose(rot_y(np.radians(30.0)), np.array([-0.78, 0.0, -2.9]))
    back_stalled = make_pose(rot_y(np.radians(7.0)), np.array([0.37, 0.0, -1.03]))
    back_prediction = make_pose(np.eye(3), np.array([0.0, 0.0, -3.0]))

    def back_icp(start: np.ndarray) -> np.ndarray:
        near = abs(np.degrees(yaw_of(start)) - 30.0) <= 8.0 and np.linalg.norm(start[:3, 3] - back_truth[:3, 3]) < 1.0
        return back_truth if near else start

    step, replaced = turn_search(back_stalled, back_icp, fits.misfits, fits.judged, back_prediction)
    assert replaced and step is back_truth


def test_where_matched_features_cannot_decide_and_the_guess_is_wrong_the_turn_search_runs_judged_by_them() -> None:
    # Lucas-Kanade lost a 32 deg turn, the matched features are too few for PnP and the images' guess turns the
    # wrong way (ICP from it explains them worse than ICP's own step): the depth's turn search runs, and its step is
    # kept where the matched features explain it SLIP_RATIO times better than ICP's.
    truth = make_pose(rot_y(np.radians(32.0)), np.array([0.9, 0.0, 3.1]))
    missed = make_pose(rot_y(np.radians(18.0)), np.array([0.5, 0.0, 3.2]))
    wrong_guess = make_pose(rot_y(np.radians(-7.0)), np.array([0.0, 0.0, 3.2]))
    matched = _tracks(truth, MIN_TRACKS - 6)
    assert pnp_step(matched) is None
    fits = _Fits(lambda deg: 0.001 if abs(deg - 32.0) < 0.5 else 0.37)
    step, replaced = choose_step(missed, None, wrong_guess, _snap_to(32.0), lambda: matched, fits.misfits, fits.judged)
    assert replaced and np.degrees(yaw_of(step)) == pytest.approx(32.0)
    # matched features of a motion between the two (no better explained by the search's step than by ICP's): the
    # map's preference alone does not replace ICP's step
    between = _tracks(make_pose(rot_y(np.radians(25.0)), np.array([0.7, 0.0, 3.15])), MIN_TRACKS - 6)
    r_icp, r_found = flow_residual_rad(between, missed), flow_residual_rad(between, step)
    assert r_icp > 3e-3 and r_icp < SLIP_RATIO * r_found
    kept = choose_step(missed, None, wrong_guess, _snap_to(32.0), lambda: between, fits.misfits, fits.judged)
    assert kept == (missed, False)


class _Along:
    """Stand-ins for ICP (``realign``), ``map_misfits``, ``map_judged`` and ``beyond_threshold`` along the camera's
    axis: ICP from a start within 2 m of one of ``places`` (z, metres) reaches it, else stays; a step's misfit is
    ``places``' value there (0.3 elsewhere); two steps are distinct more than 2 m apart."""

    def __init__(self, places: dict[float, float]) -> None:
        self.places, self.tried = places, 0

    def realign(self, start: np.ndarray) -> np.ndarray:
        self.tried += 1
        near = [z for z in self.places if abs(start[2, 3] - z) <= 2.0 and np.allclose(start[:2, 3], 0.0)]
        return make_pose(np.eye(3), [0.0, 0.0, min(near, key=lambda z: abs(start[2, 3] - z))]) if near else start

    def misfits(self, *steps: np.ndarray) -> tuple[float, ...]:
        return tuple(self.places.get(round(float(s[2, 3]), 6), 0.3) if np.allclose(s[:2, 3], 0.0) else 0.3
                     for s in steps)  # fmt: skip

    def judged(self, *steps: np.ndarray) -> int:
        return 1000

    def distinct(self, a: np.ndarray, b: np.ndarray) -> bool:
        return bool(np.linalg.norm(a[:3, 3] - b[:3, 3]) > 2.0)

    def search(self, icp_z: float) -> tuple[np.ndarray, bool]:
        return speed_search(make_pose(np.eye(3), [0.0, 0.0, icp_z]), self.realign, self.misfits, self.judged,
                            self.distinct)  # fmt: skip


def test_speed_search_keeps_the_one_place_that_fits_clearly_best() -> None:
    # airsim-like report world 725's car1 at its first step: ICP from rest 0.01 m (misfit 0.076), from ahead 2.95 m
    # (0.019), from behind stuck behind (0.16-0.32)
    along = _Along({0.0: 0.076, 2.95: 0.019, -1.5: 0.16, -3.0: 0.27, -6.0: 0.32})
    step, replaced = along.search(0.0)
    assert replaced and step[2, 3] == pytest.approx(2.95)


def test_speed_search_takes_neither_of_two_places_that_fit_alike() -> None:
    along = _Along({0.0: 0.076, 2.95: 0.019, -6.0: 0.022})  # a regular street: 9 m back fits about as well
    step, replaced = along.search(0.0)
    assert not replaced and step[2, 3] == 0.0
    along = _Along({0.0: 0.076, 2.95: 0.019, -6.0: 1.5 * 0.019 + MISFIT_SLACK + 1e-3})  # clearly worse: no rival
    assert along.search(0.0)[1]


def test_speed_search_runs_only_where_icps_first_step_fits_badly() -> None:
    along = _Along({0.0: MISFIT_SLACK, 2.95: 0.0})
    assert along.search(0.0)[1] is False and along.tried == 0


@pytest.mark.parametrize("step_m", [-2.8])
def test_a_first_step_icp_registered_at_rest_is_found_again_from_further_along(step_m: float) -> None:
    """A camera looking back from a car already driving at its first frame (3.3 frames/s), with KISS-ICP: ICP from rest
    stalls, its cloud fits the map badly, and from further along the camera's axis it reaches the step. (Looking
    ahead on this street of lattice walls, other places fit about as well as the true one, and nothing is taken.)"""
    scene = _walled_street()
    odo = KissOdometry(voxel_size_m=0.5, max_range_m=30.0)
    odo.register(_seen_from(scene, np.eye(4)))
    seen: dict[str, object] = {}

    def search(icp_step: np.ndarray) -> np.ndarray:
        seen["icp"] = icp_step
        step, seen["replaced"] = speed_search(icp_step, odo.realign, odo.map_misfits, odo.map_judged,
                                              odo.beyond_threshold)  # fmt: skip
        return step

    odo.register(_seen_from(scene, make_pose(np.eye(3), [0.0, 0.0, step_m])), fuse_step=search)
    assert abs(seen["icp"][2, 3]) < 0.5 * abs(step_m)  # ICP from rest stalled
    assert seen["replaced"]
    np.testing.assert_allclose(odo.T_odom_cam[:3, 3], [0.0, 0.0, step_m], atol=0.15)


def test_a_robot_at_rest_is_not_searched() -> None:
    scene = _walled_street()
    odo = KissOdometry(voxel_size_m=0.5, max_range_m=30.0)
    odo.register(_seen_from(scene, np.eye(4)))
    tried: list[np.ndarray] = []

    def realign(start: np.ndarray) -> np.ndarray:
        tried.append(start)
        return odo.realign(start)

    def search(icp_step: np.ndarray) -> np.ndarray:
        step, replaced = speed_search(icp_step, realign, odo.map_misfits, odo.map_judged, odo.beyond_threshold)
        assert not replaced and step is icp_step
        return step

    odo.register(_seen_from(scene, np.eye(4)), fuse_step=search)
    assert not tried
