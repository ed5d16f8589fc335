"""KISS-ICP's motion over one second against the image's own motion: chained tracks from an anchor frame, the
residual of right and slid motions, the correction, and KISS-ICP kept moving over far flat ground where one
frame's image motion is about a pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shgm_slam.geometry.se3 import make_pose
from shgm_slam.odometry.flow_check import flow_residual_rad
from shgm_slam.odometry.kiss import KissOdometry
from shgm_slam.odometry.sources import KissIcpSource
from shgm_slam.odometry.window_check import (
    WINDOW_FLOOR_RAD,
    WINDOW_SLIP_FRACTION,
    WindowTracks,
    mean_step,
    window_correction,
)
from shgm_slam.types import Frame, Intrinsics

K = Intrinsics(fx=160.0, fy=160.0, cx=159.5, cy=47.5, width=320, height=96)
HEIGHT_M = 100.0  # camera straight above flat ground, looking down (its z axis)
STEP_M = 0.7  # along the camera's x axis per frame (7 m/s at 10 Hz): the ground moves 1.12 px per frame
DT_S = 0.1


@pytest.fixture(scope="module")
def ground_texture() -> np.ndarray:
    """(H + 8, long) float32 smooth random texture of the ground strip the camera flies along."""
    rng = np.random.default_rng(0)
    noise = rng.uniform(0, 255, (K.height + 8, 1200)).astype(np.float32)
    grey = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX)


def _view(texture: np.ndarray, k: int) -> np.ndarray:
    """(H, W, 3) uint8 image of frame k: the strip shifted by k * 1.12 px (bilinear resampling)."""
    shift = k * STEP_M * K.fx / HEIGHT_M
    M = np.float32([[1, 0, shift + 4], [0, 1, 4]])
    grey = cv2.warpAffine(texture, M, (K.width, K.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def _depth() -> np.ndarray:
    return np.full((K.height, K.width), HEIGHT_M, dtype=np.float32)


def _motion(frames: int, fraction: float = 1.0) -> np.ndarray:
    return make_pose(np.eye(3), np.array([fraction * frames * STEP_M, 0.0, 0.0]))


def _window(texture: np.ndarray, window: WindowTracks | None = None, start: int = 0):
    window = window or WindowTracks()
    got = [window.update(_view(texture, k), _depth(), K, k * DT_S) for k in range(start, start + 11)]
    return window, got


def test_a_window_is_handed_over_once_a_second_has_passed(ground_texture) -> None:
    window, got = _window(ground_texture)
    assert all(w is None for w in got[:10])  # the anchor, then nine frames within the second
    w = got[10]
    assert w is not None and w.frames == 10 and len(w.tracks.uv_cur) > 200
    assert window.anchored_now  # the frame that closed the window anchors the next one
    assert flow_residual_rad(w.tracks, _motion(10)) < 0.3 / K.fx  # the true motion: within 0.3 px
    assert flow_residual_rad(w.tracks, np.eye(4)) == pytest.approx(11.2 / K.fx, rel=0.05)  # 11.2 px unexplained
    assert window.update(_view(ground_texture, 11), _depth(), K, 1.1) is None and not window.anchored_now


def test_a_slid_motion_is_corrected_and_a_right_one_kept(ground_texture) -> None:
    _, got = _window(ground_texture)
    w = got[10]
    stalled = _motion(10, 0.4)  # ICP slid: 4.2 of 7 m
    fix = window_correction(w, stalled)
    assert fix is not None
    np.testing.assert_allclose(fix[:3, 3], [7.0, 0.0, 0.0], atol=0.2)
    assert window_correction(w, _motion(10)) is None
    near = _motion(10, 1.0 - WINDOW_SLIP_FRACTION / 2)  # 0.35 m off: metres-close, kept even above the floor
    assert flow_residual_rad(w.tracks, near) > WINDOW_FLOOR_RAD / 2
    assert window_correction(w, near) is None


def test_a_window_leaves_motion_one_frame_shows_to_the_per_frame_check(ground_texture) -> None:
    # ICP claims 4 m per frame over ground 100 m away: a tenth of such a step is 4 mrad in one frame, above the
    # per-frame floor, so the per-frame check judged those steps (at a low frame rate the chained tracks are what
    # fails: pixels left behind agree on a short motion); a stall (ICP's step short) is still the window's
    _, got = _window(ground_texture)
    w = got[10]
    assert window_correction(w, _motion(10, 40.0 / 7.0)) is None
    assert window_correction(w, _motion(10, 0.4)) is not None


def test_the_window_restarts_after_a_break(ground_texture) -> None:
    window, _ = _window(ground_texture)
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 255, (K.height, K.width, 3), dtype=np.uint8)  # an unrelated image: tracks lost
    for k in range(11, 30):
        frame = noise if k == 15 else _view(ground_texture, k)
        w = window.update(frame, _depth(), K, k * DT_S)
        assert w is None or k >= 25  # lost at 15 (anchored there), the next window closes a second later
        if k == 15:
            assert window.anchored_now
    window.reset()
    wrong_size = np.zeros((K.height // 2, K.width // 2), np.float32)  # depth of another size: no anchor
    assert all(window.update(_view(ground_texture, k), wrong_size, K, k * DT_S) is None for k in range(40, 60))


def test_mean_step_continues_the_window_per_frame() -> None:
    step = mean_step(_motion(10), 10, make_pose(np.eye(3), [0.0, 0.0, 0.0]))
    np.testing.assert_allclose(step[:3, 3], [STEP_M, 0.0, 0.0])


def _fly(texture: np.ndarray, window: WindowTracks | None, frames: int = 40) -> tuple[np.ndarray, int]:
    """(frames, 3) positions KISS-ICP (with or without the window check; no per-frame check) gives the
    camera flying 100 m over flat ground, and the frames it corrected."""
    source = KissIcpSource(KissOdometry(voxel_size_m=2.0, max_range_m=200.0), window=window)
    rng = np.random.default_rng(2)
    out, corrected = [], 0
    for k in range(frames):
        # the ground at random image positions: a pixel grid is a lattice on the ground that ICP snaps to
        uv = rng.uniform([0, 0], [K.width, K.height], (1500, 2))
        points = np.c_[(uv - [K.cx, K.cy]) / [K.fx, K.fy], np.ones(len(uv))] * HEIGHT_M
        est = source.update(Frame(k, DT_S * k, K, image_rgb=_view(texture, k)), points, _depth())
        out.append(est.T_odom_cam[:3, 3])
        corrected += est.image_window
    return np.array(out), corrected


def test_kiss_icp_over_far_flat_ground_is_kept_moving_by_the_window_check(ground_texture) -> None:
    """The cloud is one plane patch: ICP pulls it back toward the map it overlaps most, so it stays near its
    zero-velocity start. Each second the tracks show the ground moved 11 px: the window's motion from the
    tracks is kept, so the pose is right at every window's end."""
    truth = np.arange(40)[:, None] * np.array([STEP_M, 0.0, 0.0])
    alone, _ = _fly(ground_texture, None)
    assert np.linalg.norm(alone[-1] - truth[-1]) > 20.0  # stalled: most of the 27 m missing
    checked, corrected = _fly(ground_texture, WindowTracks())
    assert corrected == 3  # every window's end (frames 10, 20, 30)
    ends = np.arange(10, 40, 10)
    assert np.linalg.norm(checked[ends] - truth[ends], axis=1).max() < 0.3
    assert np.linalg.norm(checked - truth, axis=1).max() < 15 * STEP_M  # ICP slides (back) between ends
