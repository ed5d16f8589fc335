"""KISS-ICP's step checked against the image's own motion, and replaced where ICP slipped.

Point-to-point ICP on a pseudo-LiDAR cloud that is mostly one plane (a UAV's view of flat ground) has
nothing that pulls it along the plane: started from a zero or too small velocity it stays there, and
its constant-velocity model keeps it there (measured on airsim-like tuning seeds 30 and 31: a UAV flying
7.3 m/s registered 0.4 m/s for 2.5 s from its first frame; another 2.7 of 7.2 m/s for 2 s). The
depth itself then cannot tell, but the images can: the previous frame's pixels, lifted to 3-D with its
depth and moved by a candidate step, must land where they are seen in this frame.

``FlowTracks`` tracks a grid of the previous frame's pixels with valid depth into the current image
(pyramidal Lucas-Kanade, kept when the backward track returns within ``FB_MAX_PX``). A step's
``flow_residual_rad`` is the median distance between where it puts them and where they were tracked,
as an angle (pixels / focal length: independent of the image size). ``pnp_step`` solves the step from
the same tracks (PnP + RANSAC). ``choose_step`` keeps ICP's step unless its residual is above
``SLIP_FLOOR_RAD`` and ``SLIP_RATIO`` times PnP's: then ICP slipped and PnP's step is kept (KISS-ICP's
map, velocity and pose follow it, so the next frame starts from the right velocity). PnP's step, not ICP
run again from it: against the truth at the replaced steps of a KITTI 00 car and two UAVs (tuning data),
PnP's translation was 0.03 / 0.01 / 0.02 m off (median), ICP's own 0.09 / 0.14 / 0.38 m and ICP run again
from PnP's step 0.06 / 0.11 / 0.25 m: it slides back toward its own. PnP runs only for
steps above the floor; the tracks cost ~2-3 ms per frame at 320x96 and 640x192 (two pyramidal
Lucas-Kanade passes over ~400 pixels).

On rendered depth a right step's residual is ~1e-4 rad (0.02 px at 320x96); a healthy KISS-ICP step's
~1e-3; the slips above 6-10e-3 per frame. Slips too small to show in one frame (far ground, a high UAV) are
checked over a second by ``window_check``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from shgm_slam.geometry.camera import backproject, project
from shgm_slam.geometry.se3 import inverse, make_pose
from shgm_slam.odometry.image_rotation import rot_y, yaw_of
from shgm_slam.types import Intrinsics

TARGET_TRACKS = 400
"""Grid pixels tracked per frame (about; the grid stride follows the image size)."""

FB_MAX_PX = 0.5
"""A track is kept when tracking it back lands within this many pixels of where it started."""

MIN_TRACKS = 30
"""Fewer kept tracks: no check (too little texture or depth)."""

SLIP_FLOOR_RAD = 3e-3
"""ICP's step is suspect only when its median residual exceeds this angle (0.5 px at a 160 px focal
length): ten times a healthy KISS-ICP step's on rendered depth."""

PNP_SEED = 0
"""OpenCV's RANSAC draws from a per-thread generator: it is seeded before each PnP so a step depends only on
its tracks (robots sharing a process in ``run`` and a robot process restarted mid-run solve the same steps)."""

SLIP_RATIO = 3.0
"""... and this many times the residual of the step PnP solves from the same tracks."""

SEED_MIN_PX = 10.0
"""A guessed step (``FlowTracks.update``'s ``guess_step``: the odometry's constant-velocity prediction turned to
the yaw the images suggest) that moves the tracked pixels by this many or more (median) is also tried as the
tracks' starting point, and the tracking with more PnP inliers wins (pixels Lucas-Kanade could not follow
tend to stay put, pass the forward-backward check and agree on no motion: counting tracks would pick them).
Lucas-Kanade from zero motion (11 px window, 3 levels) loses most pixels beyond ~20 px: in the turns of the
tuning drives (true yaw > 5 deg/frame; airsim-like 10-14 with the UAV, synthia-like and kitti-paths 10-11) PnP
had tracks for 203 of 279 frames at 10 Hz and 33 of 189 with every third frame; seeded by the
phase-correlation yaw 276 and 138, every one within 1 deg of the true turn. KISS-ICP alone on those 27 drives
(with disjoint 10-11) at 5 Hz (every second frame), SE(3)-aligned ATE: synthia-like 11 forward 53.1 -> 0.7 m,
airsim-like car2s 6.8 / 4.2 / 6.7 -> 0.7 / 0.5 / 0.4 m, the worst UAV 2.2 -> 1.1 m, no drive more than 0.04 m
worse; at 10 Hz the same to 0.02 m. From 3 px the UAVs' small image motion was seeded too and three UAVs
ended 0.1-0.3 m worse at 10 Hz; 10 px leaves them as they were."""

MISFIT_RATIO = 1.5
"""A step from the images replaces ICP's only if the frame's cloud fits the local map about as well under it: its
``KissOdometry.map_misfits`` (point to plane, judged on what the previous camera saw under both steps) at most this
many times ICP's, plus ``misfit_slack``. Where ICP slipped along a plane (a UAV over flat ground, a corridor) the
two fit alike, and where ICP missed a turn the image's step fits better; where the tracks agreed on a wrong
motion (pixels left behind that agree on none while a car drives 2.8 m per frame, at 3 frames/s) it fits worse.
Airsim-like and synthia-like tuning seeds 10-13 at 3.3 frames/s (every replacement the tracks proposed, against
the truth): the 33 nearer the truth than ICP's step fitted at most 0.56 times ICP's misfit, 15 of the 19 farther
(2.4-3.1 m off) 1.9-137 times and were refused, and 4 passed (1.58 times, or within the slack)."""

MISFIT_SLACK = 0.01
"""... plus at most this much (misfits are shares of the gate squared): on flat walls and ground the map's samples
make a step along them fit up to ~0.01 worse than ICP's own (the corridor of ``tests/odometry/test_hybrid.py``,
where ICP's own misfit is 0.003-0.03 and the true step's up to 3 times it). The slack a step gets is ICP's own
misfit times ``MISFIT_SLACK_SCALE``, between ``MISFIT_SLACK_FLOOR`` and this (``misfit_slack``)."""

MISFIT_SLACK_SCALE = 4.0
"""How many times ICP's own misfit a step along a surface may fit worse by the map's sampling: ICP's misfit measures
how coarsely the map samples the surfaces in view, so where ICP's cloud fits closely, a step that fits many times
worse is a wrong step, not a slide along a plane. Synthia-like tuning seeds 12-13 at 3.3 frames/s: Lucas-Kanade
tracks left behind on a straight road (a car driving 2.8 m per frame) agreed on 0.4-0.7 m, and their PnP step fitted
the map 9-22 times worse than ICP's right one (0.0003 -> 0.0065, 0.0012 -> 0.0107), yet within the fixed slack; the
replacements nearer the truth (67 at 10 Hz, 92 at 3.3 frames/s, every robot of tuning worlds 10-13) fitted at most
1.7 times ICP's where they differed by more than ``MISFIT_SLACK_FLOOR`` (0.0051 -> 0.0087), the corridor's 3.2."""

MISFIT_SLACK_FLOOR = 1e-3
"""... but never less than this: a healthy step's misfit (~1e-3 and below) is the map's sampling noise itself (the
replacements nearer the truth on kitti-paths tuning worlds fitted 1e-4 -> 4e-4)."""

PREDICTION_SHARE = 0.5
"""A step PnP solves from image tracks does not replace ICP's where it is shorter than both ICP's step and the step
expected before ICP (the constant-velocity prediction turned to the images' yaw) by more than this share of the
predicted step's length, and the frame's cloud also fits the map worse under it (``_left_behind``): tracks of
pixels Lucas-Kanade left behind agree on a fraction of the motion. Every replacement of ICP's step on the tuning
drives at 3.3 frames/s (seeds 10-29, KISS-ICP alone, 309 replacements) that fitted the map worse than ICP's step
(52; 51 with a prediction of motion): the 2 that were wrong (disjoint 19 and airsim-like 20, a car at 2.8-3.1 m per
frame: ICP's step 0.04 / 0.17 m off, the tracks' 0.16 / 0.25 m long, 3.3 / 2.8 m off) fell short by 0.95 / 0.91 of
the predicted length; the other 49 (nearer the truth than ICP's, or at most 0.14 m farther) by at most 0.41
(kitti-paths 15, stopping: 0.10 m predicted, 0.06 m kept). Where ICP's step and its prediction are both wrong (the
corridor of ``tests/odometry/test_hybrid.py``, where ICP slid backwards and the prediction with it), the tracks' step
is as long as theirs and still replaces them."""

TURN_SEARCH_DEG = (10.0, 20.0, 30.0)
"""Where no image tracks judge a step and the frame's cloud fits the map badly under ICP's (``turn_search``), ICP runs
again from its own step turned by each of these angles, either way about the camera's vertical axis: at 3.3
frames/s a car turns up to ~32 deg in one frame, ICP from the constant-velocity prediction stopped 7-21 deg short
(synthia-like tuning seeds 10-13), and from 10 or 20 deg further it reached the true turn within 0.5 deg. ICP's
basin is narrower than that spacing: airsim-like tuning seed 27's car2 turned 25.9 deg in one frame, ICP registered
-0.5 deg, and from 19.5 deg it stalled at 19.8 (misfit 0.52 against ICP's 0.72: not clearly better), from anywhere
between 21.5 and 29.5 deg it reached 26.0 (misfit 0.055); from 30 deg further, KISS-ICP alone ended 1.09 m off
instead of 3.66 with its break gone. Where ICP
also stalled short of the step's length, each turned start is tried once more at the predicted translation carried
round the turn (``_on_arc``): airsim-like tuning seed 15's car2, a 30.3 deg turn at 3 m per frame, ICP at 6.7 deg
and 1.0 m ahead; from its own step turned 20 deg further it reached 31.9 deg but 2.8 m off, from that start at the
predicted 3.07 m on the arc 30.2 deg and 0.03 m off (misfit 0.11 against ICP's 0.69)."""

ALONG_AXIS_SAMPLES = 64
"""Distances along the camera's optical axis ``_along_axis`` tries (evenly spaced between the nearest tracked
point's depth either way)."""

SIDEWAYS_SEARCH = (0.5, 1.0)
"""Where ICP ran again from a turn (the images' guess or ``turn_search``), it runs once more from the step it reached
moved sideways by these fractions of its length, either way, and a start that ends where the cloud fits the map
clearly better wins (``_best_start``): in a turn of ~30 deg in one frame at 3.3 frames/s ICP finds the turn but can
stop 3-4 m to the side of the truth (synthia-like tuning seed 13: from the images' guess 30.8 deg, 3.5 m to the side,
a misfit of 0.023; from 3 m to the right of it 31.4 deg, 0.1 m off, 0.003)."""

SPEED_SEARCH_M = (1.5, 3.0, 6.0, 12.0)
"""Where the first step of an odometry started from rest fits the map badly (``speed_search``), ICP runs again from
steps of these lengths, metres, along each of the camera's axes either way: at 3.3 frames/s a car already driving
3 m per frame at its first frame is out of reach of ICP from rest, which registered no motion and, predicting on
at that, none for the next 8-12 frames (report worlds 725 and 729 at 3.3 frames/s, airsim-like car1: 4.3 and 7.1 m
odometry ATE, undetected). Airsim-like 725's car1 at its first step: ICP from rest 0.01 m (misfit 0.076), from
1.5, 3 or 6 m ahead 2.91-2.95 m (0.019; the truth 2.99), from behind the camera stuck behind it (0.16-0.32). Spaced
at ICP's initial gate (3 x KISS-ICP's initial threshold, 2 m) or closer; 12 m per frame is 40 m/s at 3.3 frames/s."""

MIN_JUDGED_SHARE = 0.5
"""``turn_search`` judges a step against ICP's only on points both put where the previous camera saw (``_seen_before``
in ``kiss``): at least this share of those ICP's step alone puts there (a step turned 45 deg the wrong way shares a
sliver of the view, on which it may fit better by chance)."""

ORB_FEATURES = 1000
"""Features detected per image for ``feature_step``."""

_LK = {"winSize": (11, 11), "maxLevel": 2, "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}


@dataclass(frozen=True)
class Tracks:
    """Pixels of the previous frame tracked into the current one.

    Attributes:
        points_prev_cam: (N, 3) their 3-D points in the previous camera frame, metres.
        uv_cur: (N, 2) where they were seen in the current image, pixels.
        intrinsics: the images' intrinsics.
    """

    points_prev_cam: np.ndarray
    uv_cur: np.ndarray
    intrinsics: Intrinsics

    @cached_property
    def pnp(self) -> tuple[np.ndarray | None, np.ndarray]:
        """``solve_pnp``'s answer, solved once per set of tracks (the slip check, the choice between trackings,
        the rival's backing and the noisy-depth blend all ask for it; RANSAC is seeded, so asking again would
        give the same answer). Read-only arrays."""
        step, inliers = _solve_pnp(self)
        for a in (step, inliers):
            if a is not None:
                a.flags.writeable = False
        return step, inliers


class FlowTracks:
    """Tracks of consecutive frames (frames in order; ``reset`` after a break in the sequence).

    Args:
        max_depth_m: pixels with depth beyond this are not tracked (far depth is least certain).
    """

    def __init__(self, max_depth_m: float = 80.0) -> None:
        self.max_depth_m = max_depth_m
        self._prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # grey, points, uv
        self._prev_depth: np.ndarray | None = None
        self._pair: tuple[np.ndarray, np.ndarray, np.ndarray, Intrinsics] | None = None  # ``matched``'s frames
        self._matched: Tracks | None = None
        self._matched_done = False
        self.rival: Tracks | None = None
        """The Lucas-Kanade tracking of the last ``update`` that was not chosen (from rest where the one from the
        guess had more PnP inliers, or the other way round; ``SEED_MIN_PX``), or None: ``choose_step`` keeps ICP's
        step where the rival agrees with it (its ``rival``)."""

    def reset(self) -> None:
        self._prev = None
        self._prev_depth = None
        self._pair, self._matched, self._matched_done = None, None, False
        self.rival = None

    @property
    def pairable(self) -> bool:
        """Whether the last ``update`` had a previous frame of the same size with depth (``matched`` can try)."""
        return self._pair is not None

    def matched(self) -> Tracks | None:
        """Tracks of matched ORB features (``matched_tracks``) between the last two frames ``update`` saw, or
        None (no such pair, or too few agree). Computed on the first call for a pair (~30 ms at 320x96), so only
        where Lucas-Kanade's tracks cannot decide a step: a turn of ~30 deg in one frame (a car at an intersection
        at 3 frames/s) moves the image by a third of its width, beyond Lucas-Kanade even from a guess."""
        if not self._matched_done and self._pair is not None:
            self._matched = matched_tracks(*self._pair, self.max_depth_m)
        self._matched_done = True
        return self._matched

    def update(
        self,
        image_rgb: np.ndarray,
        depth_m: np.ndarray,
        intrinsics: Intrinsics,
        guess_step: np.ndarray | None = None,
        *,
        motion_unknown: bool = False,
    ) -> Tracks | None:
        """Track the previous frame's grid into this (H, W, 3) uint8 image; remember this frame's grid
        (``depth_m`` (H, W) metres, 0 invalid) for the next. None for the first frame, a changed image
        size or fewer than ``MIN_TRACKS`` kept tracks.

        ``guess_step``: (4, 4) a guess of this camera's pose in the previous camera's frame; where it moves
        the pixels by ``SEED_MIN_PX`` or more (median), tracking also starts from where it puts them, and the
        tracking whose tracks agree with more of one rigid motion (PnP's inliers) is used: pixels that
        Lucas-Kanade could not follow tend to stay where they were, pass the forward-backward check and
        agree with each other on no motion.

        ``motion_unknown``: nothing predicts this step (the first one after a start or a reset, where the
        odometry assumes rest): matched features (``matched_tracks``) are a further option, and the step
        they give is the guess.
        """
        grey = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
        prev, self._prev = self._prev, self._grid(grey, depth_m, intrinsics)
        depth_prev, self._prev_depth = self._prev_depth, np.asarray(depth_m)
        pairable = prev is not None and depth_prev is not None and prev[0].shape == grey.shape == depth_prev.shape
        self._pair = (prev[0], depth_prev, grey, intrinsics) if pairable else None
        self._matched, self._matched_done = None, False
        self.rival = None
        if prev is None or prev[0].shape != grey.shape or len(prev[2]) < MIN_TRACKS:
            return None
        grey_prev, points, uv = prev
        options: list[Tracks] = []  # the tracks to choose from (by PnP inliers)
        seed_min_px = SEED_MIN_PX
        if motion_unknown and depth_prev is not None and depth_prev.shape == grey.shape:
            matched = self.matched()
            if matched is not None:  # a measured guess: always worth a try
                options.append(matched)
                guess_step, seed_min_px = pnp_step(matched), 0.0
        fwd, ok = track(grey_prev, grey, uv)
        if ok.sum() >= MIN_TRACKS:
            options.append(Tracks(points[ok], fwd[ok].astype(np.float64), intrinsics))
        guess = None if guess_step is None else moved_pixels(points, uv, guess_step, intrinsics)
        if guess is not None and np.median(np.linalg.norm(guess - uv, axis=1)) >= seed_min_px:
            fwd, ok = track(grey_prev, grey, uv, guess)
            if ok.sum() >= MIN_TRACKS:
                options.append(Tracks(points[ok], fwd[ok].astype(np.float64), intrinsics))
        if len(options) <= 1:
            return options[0] if options else None
        chosen = max(reversed(options), key=lambda t: len(solve_pnp(t)[1]))  # ties: the later (LK) option
        rivals = [t for t in options if t is not chosen and t is not self._matched]
        self.rival = rivals[-1] if rivals else None
        return chosen

    def _grid(
        self, grey: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h, w = grey.shape
        stride = max(1, round(float(np.sqrt(h * w / TARGET_TRACKS))))
        depth = np.asarray(depth_m)
        if depth.shape != grey.shape:  # depth of another size: no grid (the check is skipped)
            return grey, np.zeros((0, 3)), np.zeros((0, 2), np.float32)
        points, pix = backproject(depth, intrinsics, stride=stride, max_depth_m=self.max_depth_m)
        uv = np.stack([pix % w, pix // w], axis=1).astype(np.float32)
        return grey, points, uv


def moved_pixels(points_prev_cam: np.ndarray, uv: np.ndarray, step: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(N, 2) float32 where ``step`` (4, 4: the current camera's pose in the previous camera's frame) puts the
    previous frame's points ``points_prev_cam`` (N, 3, metres) seen at ``uv`` (N, 2 pixels); points it takes
    behind the camera stay at ``uv``."""
    T_cur_prev = inverse(step)
    uv_moved, front = project(points_prev_cam @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3], intrinsics)
    return np.where(front[:, None], uv_moved, uv).astype(np.float32)


def track(
    grey_prev: np.ndarray, grey: np.ndarray, uv: np.ndarray, uv_guess: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``uv`` (N, 2) float32 of ``grey_prev`` tracked into ``grey`` (both (H, W) uint8; pyramidal
    Lucas-Kanade, starting from ``uv_guess`` (N, 2) float32 when given, else from ``uv``): ((N, 2) float32
    where they were found, (N,) bool kept: found both ways and the backward track lands within
    ``FB_MAX_PX`` of the start)."""
    if uv_guess is None:
        fwd, st_f, _ = cv2.calcOpticalFlowPyrLK(grey_prev, grey, uv, None, **_LK)
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(grey, grey_prev, fwd, None, **_LK)
    else:
        seeded = {**_LK, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}
        fwd, st_f, _ = cv2.calcOpticalFlowPyrLK(grey_prev, grey, uv, uv_guess.copy(), **seeded)
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(grey, grey_prev, fwd, uv.copy(), **seeded)
    ok = (st_f[:, 0] == 1) & (st_b[:, 0] == 1) & (np.linalg.norm(back - uv, axis=1) < FB_MAX_PX)
    return fwd, ok


def flow_residual_rad(tracks: Tracks, step: np.ndarray) -> float:
    """Median distance between where ``step`` (4, 4: the current camera's pose in the previous camera's
    frame) puts the tracked points and where they were seen, as an angle (pixels / fx)."""
    T_cur_prev = inverse(step)
    uv, front = project(tracks.points_prev_cam @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3], tracks.intrinsics)
    if not front.any():
        return float("inf")
    return float(np.median(np.linalg.norm(uv[front] - tracks.uv_cur[front], axis=1)) / tracks.intrinsics.fx)


def matched_tracks(
    grey_prev: np.ndarray, depth_prev_m: np.ndarray, grey: np.ndarray, intrinsics: Intrinsics, max_depth_m: float
) -> Tracks | None:
    """Tracks from matched ORB features, for where Lucas-Kanade has no starting point: the previous frame's
    features lifted with its depth (``depth_prev_m`` (H, W) metres, up to ``max_depth_m``) and where their
    cross-checked matches are seen now, kept where they agree with one rigid motion (PnP + RANSAC, 1 px); None
    with fewer than ``MIN_TRACKS`` of those. A robot that starts moving fast (4 frames/s: 2.7 m per frame) is
    registered by KISS-ICP as at rest, and Lucas-Kanade from rest follows few pixels and keeps many that did
    not move, which agree on no motion. ~30 ms at 320x96, so only for the first step of a trajectory
    (airsim-like tuning seeds 10 and 25: the step solved from them 0.05-0.41 m from the true 1.1-3.2 m)."""
    orb = cv2.ORB_create(nfeatures=ORB_FEATURES, nlevels=4, edgeThreshold=8, patchSize=15, fastThreshold=10)
    kp_prev, desc_prev = orb.detectAndCompute(grey_prev, None)
    kp, desc = orb.detectAndCompute(grey, None)
    if desc_prev is None or desc is None:
        return None
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(desc_prev, desc)
    if len(matches) < MIN_TRACKS:
        return None
    uv_prev = np.array([kp_prev[m.queryIdx].pt for m in matches])
    uv_cur = np.array([kp[m.trainIdx].pt for m in matches])
    h, w = depth_prev_m.shape
    col = np.clip(np.round(uv_prev[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.round(uv_prev[:, 1]).astype(np.int64), 0, h - 1)
    z = depth_prev_m[row, col].astype(np.float64)
    ok = np.isfinite(z) & (z > 0) & (z <= max_depth_m)
    if ok.sum() < MIN_TRACKS:
        return None
    rays = np.stack([(uv_prev[:, 0] - intrinsics.cx) / intrinsics.fx, (uv_prev[:, 1] - intrinsics.cy) / intrinsics.fy,
                     np.ones(len(z))], axis=1)  # fmt: skip
    candidates = Tracks(rays[ok] * z[ok, None], uv_cur[ok], intrinsics)
    step, inliers = solve_pnp(candidates)
    if step is None:
        return None
    return Tracks(candidates.points_prev_cam[inliers], candidates.uv_cur[inliers], intrinsics)


def pnp_step(tracks: Tracks) -> np.ndarray | None:
    """(4, 4) the current camera's pose in the previous camera's frame solved from the tracks (PnP +
    RANSAC, 1 px), or None when it fails or keeps fewer than ``MIN_TRACKS`` inliers."""
    return solve_pnp(tracks)[0]


def solve_pnp(tracks: Tracks) -> tuple[np.ndarray | None, np.ndarray]:
    """(``pnp_step``'s pose or None, (K,) indices of its RANSAC inliers: empty when PnP failed); fresh arrays
    (``Tracks.pnp`` holds the answer)."""
    step, inliers = tracks.pnp
    return (None if step is None else step.copy()), inliers.copy()


def _solve_pnp(tracks: Tracks) -> tuple[np.ndarray | None, np.ndarray]:
    cv2.setRNGSeed(PNP_SEED)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        tracks.points_prev_cam.astype(np.float64), tracks.uv_cur.astype(np.float64), tracks.intrinsics.K, None,
        reprojectionError=1.0, iterationsCount=100, flags=cv2.SOLVEPNP_ITERATIVE,
    )  # fmt: skip
    if not ok or inliers is None:
        return None, np.zeros(0, np.int64)
    inliers = inliers.reshape(-1)
    T_cur_prev = make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    if len(inliers) < MIN_TRACKS or not np.isfinite(T_cur_prev).all():
        return None, inliers
    return inverse(T_cur_prev), inliers


def choose_step(
    icp_step: np.ndarray,
    tracks: Tracks | None,
    guess_step: np.ndarray | None = None,
    realign: Callable[[np.ndarray], np.ndarray] | None = None,
    matched: Callable[[], Tracks | None] | None = None,
    misfits: Callable[..., tuple[float, ...]] | None = None,
    judged: Callable[..., int] | None = None,
    rival: Tracks | None = None,
    distinct: Callable[[np.ndarray, np.ndarray], bool] | None = None,
    motion_prior: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """(step to keep, whether ICP's step was replaced): PnP's (``pnp_step``, solved only when ICP's residual is
    above ``SLIP_FLOOR_RAD``) where ICP's residual is also above ``SLIP_RATIO`` times PnP's (module docstring), or,
    where the tracks cannot decide between the two (below that ratio), where the depth does: the cloud fits the map
    so much better under PnP's step than under ICP's own that the rule which refuses an image step that fits worse
    (``MISFIT_RATIO`` and ``misfit_slack``) refuses ICP's (``_fits_far_worse``; ICP then stopped short of its own
    best fit; asked only where ``distinct``, e.g. ``KissOdometry.beyond_threshold``, says the two steps differ by
    more than ICP's own threshold: building the map's search tree costs ~10 ms, and at 10 Hz the tracks are above
    the floor in most frames while PnP's step and ICP's are one motion). Airsim-like tuning seed 25 at 3.3 frames/s:
    a car already driving 3.2 m per frame at its first frame; ICP from rest registered no motion for seven frames,
    the tracks from rest, mostly pixels left behind, explained no motion nearly as well as any (0.014-0.025 rad
    against PnP's 0.009-0.018), and PnP's step, right in three of those frames, fitted the map 7-10 times better
    (0.015-0.035 against 0.15-0.28); kept from the first of them, KISS-ICP alone ended 0.64 m off instead of 3.28.
    ICP's very array otherwise, without tracks or when PnP fails, and where ``rival``, the other tracking of the
    same pixels (``FlowTracks.rival``), agrees with ICP's step by that rule but not with PnP's, and PnP's step does
    not fit the map better than ICP's (``misfits``): the two trackings then contradict each other, and the depth's
    own step is kept. (Where the rival agrees with both, ICP's step was a few centimetres off and PnP's correction
    stands: the demo world at 640x192, 10 Hz, cars' steps 4-6 cm off, the rival backing both.) Synthia-like tuning
    seed 13 at 3.3 frames/s, a straight road at 2.8 m per frame: Lucas-Kanade from rest kept 105 tracks, 53 of them
    agreeing on 0.55 m (pixels left behind), from the guess 100, 32 agreeing on 2.89 m (the truth 2.88, ICP's 2.83,
    fitting the map 25 times better than PnP's). The other way round at a start from rest (airsim-like tuning seed
    11): ICP stalled at 0.10 m, the tracks from rest agreed with it, and PnP's step from the tracks chosen (2.95 m,
    the truth 2.99) fitted the map 5 times better and was kept.

    Where the tracks cannot decide (none, or too few agreeing on one motion for PnP: a turn so sharp that
    Lucas-Kanade loses most pixels, measured at 3 frames/s, below), more chances, in turn:

    - ``matched`` (``FlowTracks.matched``: matched ORB features, which follow a turn of ~30 deg in one frame) is
      asked for other tracks, and they are judged as above: ICP's step kept when they agree with it, PnP's step
      from them where ICP slipped by the same rule;
    - ``guess_step`` (4, 4: the step the images suggest, ``FlowTracks.update``'s guess) and ``realign`` (ICP
      again from a given step, e.g. ``KissOdometry.realign``): when the guess explains the tracks (Lucas-Kanade's,
      else the matched ones too few for PnP) ``SLIP_RATIO`` times better than ICP's step, ICP runs again from the
      guess, and its step is kept if it explains them ``SLIP_RATIO`` times better too (the depth, not only the
      images, agrees with the turn). Judged by matched features, ICP runs again from the guess however well the
      guess itself explains them: Lucas-Kanade lost the turn, and the images' global shift is then rough;
    - with no tracks at all, the depth alone: ``turn_search`` (with ``realign``, ``misfits`` and ``judged``, the
      points two steps are judged on, e.g. ``KissOdometry.map_judged``; ``guess_step``'s translation is the
      predicted one, ``_on_arc``);
    - where tracks (or matched features) exist but could not decide and ICP from the guess did not explain them,
      the same search, its step kept only where they explain it ``SLIP_RATIO`` times better than ICP's
      (``_judged_search``). Synthia-like tuning seed 15 at 3.3 frames/s: a backward camera's car turned 31.9 deg in
      one frame, Lucas-Kanade kept no tracks, 32 matched features (24 PnP inliers, fewer than ``MIN_TRACKS``)
      agreed with the truth, the images' guess turned -6.8 deg, and ICP registered 18.4 deg (misfit 0.36 against
      the truth's 0.001); ICP from its own step turned 10 deg further reached 32.0 deg, and the drive's ATE fell
      from 14.0 to 1.2 m.

    ``misfits`` (steps -> how badly the frame's cloud then fits the map, e.g. ``KissOdometry.map_misfits``) vetoes
    any replacement that fits more than ``MISFIT_RATIO`` times worse than ICP's step, and, given ``motion_prior``
    (4, 4: the step expected before ICP, e.g. ``guess_step``; leave it out where the depth is noisy and misfits
    differ by the noise), a PnP step far shorter than both ICP's step and the prior that fits worse at all
    (``_left_behind``).

    Airsim-like tuning seed 21 at 3 frames/s: a car turned 16.8 deg in one frame, ICP from the constant-velocity
    prediction registered 1.7 deg (a residual of 0.35 rad), the seeded tracks kept 44 pixels of which PnP
    found 17 inliers (fewer than ``MIN_TRACKS``), and the bent trajectory ended 34 m off. Synthia-like seed 681
    at 3.3 frames/s: a car turned 25.9 and 27.4 deg in two frames; Lucas-Kanade kept no tracks, the 30 matched
    features were 26 for PnP, and ICP registered 1.2 deg (residual 0.46 rad on the matched features); the images'
    guess, 16.9 deg, explained them 2.5 times better (0.18 rad) and ICP again from it reached 25.6 deg (0.007 rad;
    its cloud's misfit against the map 0.001, ICP's 0.047)."""
    r_icp = None if tracks is None else flow_residual_rad(tracks, icp_step)
    verdict = None if tracks is None else _pnp_verdict(icp_step, tracks, r_icp, misfits, distinct, motion_prior)
    if verdict is not None:
        if verdict[1] and rival is not None and _backing(rival, icp_step, verdict[0]) == (True, False):
            if not _fits_better(icp_step, verdict[0], misfits):
                return icp_step, False
        return verdict
    other = None if matched is None else matched()
    r_other = None if other is None else flow_residual_rad(other, icp_step)
    verdict = None if other is None else _pnp_verdict(icp_step, other, r_other, misfits, distinct, motion_prior)
    if verdict is not None:
        return verdict
    rough_guess = tracks is None and other is not None  # judged by matched features too few for PnP
    judge, r_judge = (other, r_other) if rough_guess else (tracks, r_icp)
    if judge is None:
        return turn_search(icp_step, realign, misfits, judged, guess_step)
    if guess_step is None or realign is None:
        return icp_step, False
    if not rough_guess and r_judge <= SLIP_RATIO * flow_residual_rad(judge, guess_step):
        return _judged_search(icp_step, judge, r_judge, realign, misfits, judged, guess_step)
    again = realign(guess_step)
    if r_judge <= SLIP_RATIO * flow_residual_rad(judge, again):
        return _judged_search(icp_step, judge, r_judge, realign, misfits, judged, guess_step)
    step, replaced = _unless_worse_fit(icp_step, again, misfits)
    if replaced and misfits is not None and judged is not None:
        step = _best_start(step, _sideways(step), realign, misfits, judged)
    return step, replaced


def _pnp_verdict(
    icp_step: np.ndarray,
    tracks: Tracks,
    r_icp: float,
    misfits: Callable[..., tuple[float, ...]] | None,
    distinct: Callable[[np.ndarray, np.ndarray], bool] | None = None,
    prediction: np.ndarray | None = None,
) -> tuple[np.ndarray, bool] | None:
    """``choose_step``'s first rule on one set of tracks (``r_icp``: ICP's residual on them): ICP's step where its
    residual is within ``SLIP_FLOOR_RAD`` or ``SLIP_RATIO`` times PnP's (unless the depth refuses ICP's step:
    ``_fits_far_worse``, asked where ``distinct``), PnP's where ICP slipped (unless it fits the map worse, or fits
    it worse at all while far shorter than both ICP's step and ``prediction``: ``_left_behind``), None where PnP
    cannot decide."""
    if r_icp <= SLIP_FLOOR_RAD:
        return icp_step, False
    pnp = pnp_step(tracks)
    if pnp is None:
        return None
    r_pnp = flow_residual_rad(tracks, pnp)
    if r_icp <= SLIP_RATIO * r_pnp:
        if (distinct is None or distinct(icp_step, pnp)) and _fits_far_worse(icp_step, pnp, misfits):
            return pnp, True  # the depth refuses ICP's step for the images' own
        return icp_step, False
    if _left_behind(icp_step, pnp, prediction, misfits):
        return icp_step, False
    return _unless_worse_fit(icp_step, pnp, misfits)


def _left_behind(
    icp_step: np.ndarray,
    step: np.ndarray,
    prediction: np.ndarray | None,
    misfits: Callable[..., tuple[float, ...]] | None,
) -> bool:
    """Whether ``step`` (4, 4), the images' replacement for ICP's step (4, 4), is shorter than both ICP's step and
    ``prediction`` (4, 4: the step expected before ICP, ``choose_step``'s ``guess_step``) by more than
    ``PREDICTION_SHARE`` of the predicted step's length, and the frame's cloud fits the map worse under it than under
    ICP's (``misfits``): the motion prior and the depth then agree against the images' tracks (pixels left behind,
    which agree on a fraction of the motion). False without a prediction of motion (at rest) or ``misfits``.

    Only on noise-free depth (``choose_step``'s ``motion_prior``): on 2 %-noisy depth the misfits of two steps differ
    by the noise, and where ICP slid along the ground and the prediction with it (a UAV, noisy tuning seed 75), the
    tracks' right step, 0.6 m shorter, fitted 1.03 times worse and was refused (the drive ended 47 m off instead of
    30)."""
    if prediction is None or misfits is None:
        return False
    predicted_m = float(np.linalg.norm(prediction[:3, 3]))
    kept_pace_m = min(float(np.linalg.norm(icp_step[:3, 3])), predicted_m)
    if predicted_m <= 0.0 or kept_pace_m - float(np.linalg.norm(step[:3, 3])) <= PREDICTION_SHARE * predicted_m:
        return False
    return _fits_better(step, icp_step, misfits)  # ICP's step fits better than the tracks' (roles swapped)


def _backing(tracks: Tracks, *steps: np.ndarray) -> tuple[bool, ...]:
    """Whether ``tracks`` agree with each of ``steps`` (4, 4) by ``choose_step``'s first rule, as if it were ICP's
    (its residual within ``SLIP_FLOOR_RAD``, or within ``SLIP_RATIO`` times that of the step PnP solves from them,
    solved once)."""
    residuals = [flow_residual_rad(tracks, step) for step in steps]
    if all(r <= SLIP_FLOOR_RAD for r in residuals):
        return tuple(True for _ in steps)
    pnp = pnp_step(tracks)
    r_pnp = None if pnp is None else flow_residual_rad(tracks, pnp)
    return tuple(r <= SLIP_FLOOR_RAD or (r_pnp is not None and r <= SLIP_RATIO * r_pnp) for r in residuals)


def _fits_better(icp_step: np.ndarray, step: np.ndarray, misfits: Callable[..., tuple[float, ...]] | None) -> bool:
    """Whether the frame's cloud fits the map better under ``step`` than under ICP's (which ICP's own minimum then
    is not); False without ``misfits``."""
    if misfits is None:
        return False
    of_icp, of_step = misfits(icp_step, step)
    return of_step < of_icp


def _judged_search(
    icp_step: np.ndarray,
    tracks: Tracks,
    r_icp: float,
    realign: Callable[[np.ndarray], np.ndarray] | None,
    misfits: Callable[..., tuple[float, ...]] | None,
    judged: Callable[..., int] | None,
    prediction: np.ndarray | None,
) -> tuple[np.ndarray, bool]:
    """``turn_search`` where image tracks exist but could not decide (too few agreeing for PnP, and the images' guess
    did not explain them): its step is kept only where ``tracks`` explain it ``SLIP_RATIO`` times better than ICP's
    (``r_icp``: ICP's residual on them), so the depth and the images agree on the turn. Where no turn is kept, ICP
    runs again from ICP's step moved along the camera's axis by the distance that explains the tracks best
    (``_along_axis``; like the turns, only where the cloud fits the map badly under ICP's step, ``misfits`` above
    ``MISFIT_SLACK``), kept by the same rule and unless the cloud fits the map worse under it (``_unless_worse_fit``):
    airsim-like tuning seed 22 at 3.3 frames/s, a car already driving 3.2 m per frame at its first frame, held still
    by ICP for six frames while 42-74 Lucas-Kanade tracks explained the truth 4-5 times better than the standstill
    (0.007 against 0.033 rad) but PnP kept fewer than ``MIN_TRACKS`` within 1 px and ORB matched none; KISS-ICP alone
    2.70 -> 0.51 m."""
    step, replaced = turn_search(icp_step, realign, misfits, judged, prediction)
    if replaced and r_icp <= SLIP_RATIO * flow_residual_rad(tracks, step):
        return icp_step, False
    if replaced or realign is None or misfits is None or judged is None or misfits(icp_step)[0] <= MISFIT_SLACK:
        return step, replaced
    start = _along_axis(icp_step, tracks)
    if start is None:
        return icp_step, False
    again = realign(start)
    if r_icp <= SLIP_RATIO * flow_residual_rad(tracks, again):
        return icp_step, False
    return _unless_worse_fit(icp_step, again, misfits)


def _along_axis(step: np.ndarray, tracks: Tracks, samples: int = ALONG_AXIS_SAMPLES) -> np.ndarray | None:
    """(4, 4) ``step`` moved along its camera's optical axis by the distance whose step explains ``tracks`` best
    (``flow_residual_rad``), searched over every distance that leaves the nearest tracked point in front of the
    camera, either way (``samples`` evenly spaced); None where no distance explains them better than ``step``.
    A robot already moving at its first frame, which ICP from its prediction of rest holds still, with tracks PnP
    cannot solve."""
    depth = tracks.points_prev_cam[:, 2]
    if len(depth) == 0 or not np.isfinite(depth).all() or depth.min() <= 0.0:
        return None
    axis = np.asarray(step[:3, :3], dtype=np.float64) @ np.array([0.0, 0.0, 1.0])
    best, best_r = None, flow_residual_rad(tracks, step)
    for d in np.linspace(-depth.min(), depth.min(), samples + 2)[1:-1]:
        start = np.array(step, dtype=np.float64, copy=True)
        start[:3, 3] += d * axis
        r = flow_residual_rad(tracks, start)
        if r < best_r:
            best, best_r = start, r
    return best


def turn_search(
    icp_step: np.ndarray,
    realign: Callable[[np.ndarray], np.ndarray] | None,
    misfits: Callable[..., tuple[float, ...]] | None,
    judged: Callable[..., int] | None,
    prediction: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """(step to keep, whether ICP's step was replaced) where no image tracks judge ``icp_step`` (4, 4: this camera
    in the previous one): only where the frame's cloud could fit the map clearly better than under it (``misfits``
    above ``MISFIT_SLACK_FLOOR``, the least a clearly better fit must gain), ICP runs again (``realign``) from ICP's
    step turned by each of ``TURN_SEARCH_DEG`` either way (and, given ``prediction`` (4, 4: the constant-velocity
    step), from each turned start at the predicted translation carried round the turn, ``_on_arc``), and the step it
    reaches replaces ICP's where the cloud fits the map clearly better under it, by the rule that vetoes image steps
    the other way round (ICP's misfit above ``MISFIT_RATIO`` times the new step's plus ``misfit_slack`` of it: a
    step that fits the map as closely as sampling allows may beat a misfit below ``MISFIT_SLACK``), both judged on at
    least ``MIN_JUDGED_SHARE`` of the points ICP's step alone is judged on; of several, the one with the lowest
    misfit relative to ICP's (``_best_start``). Then the same from that step (ICP's own where no turn won) moved
    sideways (``SIDEWAYS_SEARCH``). ICP's very array without ``realign``, ``misfits`` or ``judged``.

    The images' own guess is not among the starts (only its translation, the prediction's): at the sharp turns where
    Lucas-Kanade and matched features both failed (synthia-like tuning seeds 10-13 at 3.3 frames/s), the global
    shift pointed the wrong way in 4 of 5. Synthia-like tuning seed 10 at 3.3 frames/s: the backward camera's car
    turned 31.9 deg in one frame, ICP registered 21-23 deg, 3.0 m off, with a misfit of 0.0096-0.0104 (the truth's
    0.0000), at the edge of the ``MISFIT_SLACK`` this search once asked for, both to search and to replace; now
    searched and replaced (31.9 deg, 0.19 m off), the drive (945 m, KISS-ICP alone) ended 19 m from the truth instead
    of 102."""
    if realign is None or misfits is None or judged is None or misfits(icp_step)[0] <= MISFIT_SLACK_FLOOR:
        return icp_step, False
    turned = []
    for deg in TURN_SEARCH_DEG:
        for sign in (-1.0, 1.0):
            start = np.array(icp_step, dtype=np.float64, copy=True)
            start[:3, :3] = rot_y(np.radians(sign * deg)) @ start[:3, :3]
            turned.append(start)
            if prediction is not None and np.linalg.norm(prediction[:3, 3]) > 0.0:
                turned.append(_on_arc(start, prediction))
    best = _best_start(icp_step, turned, realign, misfits, judged, misfit_slack)
    best = _best_start(best, _sideways(best), realign, misfits, judged, misfit_slack)
    return best, best is not icp_step


def speed_search(
    icp_step: np.ndarray,
    realign: Callable[[np.ndarray], np.ndarray],
    misfits: Callable[..., tuple[float, ...]],
    judged: Callable[..., int],
    distinct: Callable[[np.ndarray, np.ndarray], bool],
) -> tuple[np.ndarray, bool]:
    """(step to keep, whether ICP's step was replaced) for the first step of an odometry started from rest (nothing
    predicts it): only where the frame's cloud fits the map badly under ICP's step (``misfits`` above
    ``MISFIT_SLACK``), ICP runs again (``realign``) from ICP's step moved by each of ``SPEED_SEARCH_M`` along each of
    the camera's axes either way. The step reached that fits the map best, by ``turn_search``'s rule
    (``_best_start``: clearly better than ICP's, judged on enough of the view), replaces ICP's only where it is a
    motion of its own, ``distinct`` from ICP's (e.g. ``KissOdometry.beyond_threshold``: a step within ICP's threshold
    of it is ICP's to refine; on the 180 tuning drives at 3.3 frames/s such replacements moved first steps 0.02-0.3 m
    off by as much, both ways, and nothing after 12 frames), and only where it is unrivalled: every other step
    reached that is distinct from it and judged on enough of the view fits clearly worse by the same rule (where two
    places along a regular street fit alike, neither is taken). A robot at rest fits the map under ICP's step
    (misfit ~1e-3): nothing is searched."""
    if misfits(icp_step)[0] <= MISFIT_SLACK:
        return icp_step, False
    starts = []
    for axis in np.eye(3):
        for length_m in SPEED_SEARCH_M:
            for sign in (-1.0, 1.0):
                start = np.array(icp_step, dtype=np.float64, copy=True)
                start[:3, 3] += sign * length_m * axis
                starts.append(start)
    reached = [realign(start) for start in starts]
    best = _best_start(icp_step, reached, lambda step: step, misfits, judged)
    if best is icp_step or not distinct(best, icp_step):  # within ICP's threshold: one motion to ICP, its own kept
        return icp_step, False
    own = judged(icp_step)
    for other in reached:
        if other is best or not distinct(best, other) or judged(icp_step, other) < MIN_JUDGED_SHARE * own:
            continue
        of_best, of_other = misfits(best, other)
        if not of_other > MISFIT_RATIO * of_best + MISFIT_SLACK:
            return icp_step, False  # another place fits about as well
    return best, True


def _on_arc(start: np.ndarray, prediction: np.ndarray) -> np.ndarray:
    """(4, 4) ``start``'s rotation with ``prediction``'s translation turned by half of ``start``'s yaw (about the
    camera's vertical axis): where the robot goes on at the predicted speed through a turn of that yaw (the chord of
    the arc), not where ICP stalled."""
    on_arc = np.array(start, dtype=np.float64, copy=True)
    on_arc[:3, 3] = rot_y(0.5 * yaw_of(start)) @ prediction[:3, 3]
    return on_arc


def _sideways(step: np.ndarray) -> list[np.ndarray]:
    """(4, 4) copies of ``step`` moved along its camera's x axis (sideways) by each of ``SIDEWAYS_SEARCH`` times its
    length, either way."""
    length = float(np.linalg.norm(step[:3, 3]))
    starts = []
    for fraction in SIDEWAYS_SEARCH:
        for sign in (-1.0, 1.0):
            start = np.array(step, dtype=np.float64, copy=True)
            start[:3, 3] += start[:3, :3] @ np.array([sign * fraction * length, 0.0, 0.0])
            starts.append(start)
    return starts


def _best_start(
    step: np.ndarray,
    starts: list[np.ndarray],
    realign: Callable[[np.ndarray], np.ndarray],
    misfits: Callable[..., tuple[float, ...]],
    judged: Callable[..., int],
    slack: Callable[[float], float] = lambda _: MISFIT_SLACK,
) -> np.ndarray:
    """Of the steps ICP reaches from ``starts`` (``realign``), the one under which the frame's cloud fits the map
    clearly better than under ``step`` (its misfit above ``MISFIT_RATIO`` times theirs plus ``slack`` of theirs,
    ``MISFIT_SLACK`` unless given), the lowest relative misfit; judged on at least ``MIN_JUDGED_SHARE`` of the points
    ``step`` alone is judged on. ``step`` itself (the very array) where none does."""
    own = judged(step)
    best, best_ratio = step, 1.0
    for start in starts:
        again = realign(start)
        if judged(step, again) < MIN_JUDGED_SHARE * own:
            continue
        of_step, of_again = misfits(step, again)
        if of_step > MISFIT_RATIO * of_again + slack(of_again) and of_again / of_step < best_ratio:
            best, best_ratio = again, of_again / of_step
    return best


def _unless_worse_fit(
    icp_step: np.ndarray, step: np.ndarray, misfits: Callable[..., tuple[float, ...]] | None
) -> tuple[np.ndarray, bool]:
    """(``step``, True), or (``icp_step``, False) where the cloud fits the map ``MISFIT_RATIO`` times worse under it
    (and ``misfit_slack`` more: ``_fits_far_worse``)."""
    if _fits_far_worse(step, icp_step, misfits):
        return icp_step, False
    return step, True


def _fits_far_worse(step: np.ndarray, than: np.ndarray, misfits: Callable[..., tuple[float, ...]] | None) -> bool:
    """Whether the cloud fits the map more than ``MISFIT_RATIO`` times worse under ``step`` than under ``than``, and
    ``misfit_slack`` more (False without ``misfits``). With ``than`` an image step and ``step`` ICP's own: ICP stopped
    short of the depth's own best fit, as it does from a constant-velocity prediction of rest while the robot
    already drives."""
    if misfits is None:
        return False
    of_than, of_step = misfits(than, step)
    return of_step > MISFIT_RATIO * of_than + misfit_slack(of_than)


def misfit_slack(of_icp: float) -> float:
    """How much worse than ICP's step (misfit ``of_icp``, a share of the gate squared) another step may fit the map,
    beyond ``MISFIT_RATIO`` times it, and still replace it: ``MISFIT_SLACK_SCALE`` times ICP's own misfit, between
    ``MISFIT_SLACK_FLOOR`` and ``MISFIT_SLACK``."""
    return float(np.clip(MISFIT_SLACK_SCALE * of_icp, MISFIT_SLACK_FLOOR, MISFIT_SLACK))
