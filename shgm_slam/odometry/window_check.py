"""KISS-ICP's motion over the last second checked against the image's own motion, and corrected where
ICP slid.

``flow_check`` compares each frame's step with the image motion between two consecutive frames. A UAV
high above flat ground moves its image by a fraction of a pixel per frame there: at 85-95 m over
airsim-like worlds (tuning seeds 15-19, 320x96) a true step's residual is 1.4-1.6e-3 rad and the steps of
an ICP sliding along the plane-like ground 2-4e-3 rad, one pixel of tracking noise apart. Over one second
the slide adds up while tracking noise grows only slowly: pixels tracked from one frame through the next
ten (chained pyramidal Lucas-Kanade, each link checked forward-backward) land 0.6 px (median) from where
the true motion of the second puts them, the healthy windows of ICP's motion within 1.5-2.2 px (95th
percentile), the windows where ICP slid by more than 1.5 m at 3.3-4.2 px (median) - measured offline on
tuning seeds 17 and 18.

``WindowTracks`` keeps one anchor frame's grid of pixels with depth and tracks them frame by frame; once
``WINDOW_S`` has passed it hands over the tracks (``Window``) and the current frame becomes the next
anchor. ``window_correction`` solves the window's motion from them (PnP + RANSAC, ``flow_check.pnp_step``)
and returns it where ICP's window motion is off the image on three counts: its residual above
``WINDOW_FLOOR_RAD``, above ``WINDOW_SLIP_RATIO`` times PnP's, and its translation more than
``WINDOW_SLIP_FRACTION`` of the window's length away from PnP's; and where one frame could not have shown
such a slip (``WINDOW_SLIP_FRACTION`` of a step, seen from the tracks' median depth, under
``flow_check.SLIP_FLOOR_RAD``; the step as long as PnP's or ICP's window says, whichever is longer: the per-frame
check judged ICP's steps). The first two are the per-frame check's tests (a lower ratio); the third
keeps ICP wherever it is close in metres, the fourth leaves near scenes (where a few centimetres of healthy
drift are many pixels, and ICP holds) and fast motion to the per-frame check. Airsim-like tuning seed 10 at
3.3 frames/s: a UAV at 50 m moving 2.1 m per frame (~20 px) left the chained Lucas-Kanade tracks behind, and their
PnP motion over the window (1.6 m against the true 8.6 m, ICP's 8.2) would have put the UAV 10 m off, twice
(odometry ATE 12.3 m); judged by PnP's length alone such a slip looked invisible to one frame. The odometry then
keeps the window's motion from the tracks, restarts its local map and its motion model from it
(``kiss.Relocation``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shgm_slam.geometry.camera import backproject
from shgm_slam.geometry.se3 import make_pose
from shgm_slam.odometry.flow_check import (
    SLIP_FLOOR_RAD,
    TARGET_TRACKS,
    Tracks,
    flow_residual_rad,
    pnp_step,
    track,
)
from shgm_slam.types import Intrinsics

WINDOW_S = 1.0
"""Length of the checked window, seconds (ten frames at 10 Hz)."""

WINDOW_FLOOR_RAD = 6e-3
"""ICP's window motion is suspect only when its median residual exceeds this angle (1 px at a 160-185 px
focal length: above the 0.6 px of the true motion's residual over ten chained frames)."""

WINDOW_SLIP_RATIO = 1.5
"""... and this many times the residual of the window's motion PnP solves from the same tracks: over ten
chained frames the tracks' own noise (0.5-0.8 px) is most of PnP's residual, so a slide shows as a smaller
ratio than over one frame (``flow_check.SLIP_RATIO``). UAVs at 85-95 m, tuning seeds 15-19, odometry alone:
at 3 the check kept ICP's motion in 8-18 windows per UAV where it was more than 10 % off (ATE summed over the
five 22.4 m; 19.4 m at 1.5; 53.4 m without the check); windows of 0.5 s and 2 s did worse (24.6, 22.8 m)."""

WINDOW_SLIP_FRACTION = 0.1
"""... and its translation differs from PnP's by more than this fraction of PnP's (PnP over a window of a
UAV at 85-95 m: 0.38-0.40 m off per 7 m, median; ICP's slides 1.5-4 m)."""


WINDOW_MIN_TRACKS = 100
"""Fewer tracks through the whole window: no check (PnP from 48 tracks was 0.7 m off over 4.3 m, a car on
kitti-paths tuning seed 11; the UAVs' windows keep 140-250 of the ~400 grid pixels)."""


@dataclass(frozen=True)
class Window:
    """Pixels of an anchor frame tracked into the current frame ``WINDOW_S`` or more later.

    Attributes:
        tracks: the anchor's 3-D points (anchor camera frame) and where they are seen now.
        frames: frames from the anchor to the current one (>= 1).
    """

    tracks: Tracks
    frames: int


class WindowTracks:
    """Chained tracks from an anchor frame (frames in order; ``reset`` after a break in the sequence).

    Args:
        max_depth_m: pixels with depth beyond this are not tracked (None: no limit).
        window_s: window length, seconds.
    """

    def __init__(self, max_depth_m: float | None = None, window_s: float = WINDOW_S) -> None:
        self.max_depth_m = np.inf if max_depth_m is None else float(max_depth_m)
        self.window_s = window_s
        self.reset()

    def reset(self) -> None:
        self._anchor: tuple[float, np.ndarray] | None = None  # timestamp, (N, 3) points in the anchor camera
        self._grey: np.ndarray | None = None  # the previous frame's grey image
        self._uv: np.ndarray = np.zeros((0, 2), np.float32)  # where the live points were seen last
        self._live: np.ndarray = np.zeros(0, bool)
        self._frames = 0

    @property
    def anchored_now(self) -> bool:
        """Whether the frame just given to ``update`` became the anchor of the next window."""
        return self._frames == 0

    def update(
        self, image_rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, timestamp_s: float
    ) -> Window | None:
        """Track the live points into this (H, W, 3) uint8 image (``depth_m`` (H, W) metres, 0 invalid).

        Returns the window when ``window_s`` has passed since the anchor (this frame then anchors the next
        one), else None. Fewer than ``WINDOW_MIN_TRACKS`` live points, a changed image size or a
        timestamp not after the anchor's: this frame becomes the anchor, None.
        """
        grey = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY)
        window = None
        if self._anchor is not None and self._grey is not None and self._grey.shape == grey.shape:
            t_anchor, points = self._anchor
            self._track(grey)
            self._frames += 1
            elapsed = timestamp_s - t_anchor
            if self._live.sum() >= WINDOW_MIN_TRACKS and elapsed > 0:
                if elapsed < self.window_s - 1e-6:
                    self._grey = grey
                    return None
                live = self._live
                window = Window(Tracks(points[live], self._uv[live].astype(np.float64), intrinsics), self._frames)
        self._anchor_at(grey, depth_m, intrinsics, timestamp_s)
        return window

    def _track(self, grey: np.ndarray) -> None:
        live = np.flatnonzero(self._live)
        if len(live) == 0:
            return
        fwd, ok = track(self._grey, grey, self._uv[live])
        self._uv[live[ok]] = fwd[ok]
        self._live[live[~ok]] = False

    def _anchor_at(self, grey: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, timestamp_s: float) -> None:
        h, w = grey.shape
        depth = np.asarray(depth_m)
        self._grey, self._frames = grey, 0
        if depth.shape != grey.shape:  # depth of another size: no anchor (no check)
            self._anchor, self._uv, self._live = None, np.zeros((0, 2), np.float32), np.zeros(0, bool)
            return
        stride = max(1, round(float(np.sqrt(h * w / TARGET_TRACKS))))
        points, pix = backproject(depth, intrinsics, stride=stride, max_depth_m=self.max_depth_m)
        self._anchor = (float(timestamp_s), points)
        self._uv = np.stack([pix % w, pix // w], axis=1).astype(np.float32)
        self._live = np.ones(len(points), bool)


def window_correction(window: Window, icp_motion: np.ndarray) -> np.ndarray | None:
    """The window's motion from the image tracks where ICP's is off them (module docstring), else None.

    Args:
        window: the tracks of the window.
        icp_motion: (4, 4) the current camera's pose in the anchor camera's frame from the odometry.

    Returns:
        (4, 4) the current camera's pose in the anchor camera's frame solved from the tracks, or None.
    """
    tracks = window.tracks
    r_icp = flow_residual_rad(tracks, icp_motion)
    if r_icp <= WINDOW_FLOOR_RAD:
        return None
    pnp = pnp_step(tracks)
    if pnp is None or r_icp <= WINDOW_SLIP_RATIO * flow_residual_rad(tracks, pnp):
        return None
    length = float(np.linalg.norm(pnp[:3, 3]))
    if float(np.linalg.norm(icp_motion[:3, 3] - pnp[:3, 3])) <= WINDOW_SLIP_FRACTION * length:
        return None
    depth_m = float(np.median(tracks.points_prev_cam[:, 2]))
    either = max(length, float(np.linalg.norm(icp_motion[:3, 3])))  # the per-frame check judged ICP's steps
    if WINDOW_SLIP_FRACTION * either / window.frames >= SLIP_FLOOR_RAD * depth_m:
        return None  # one frame resolves such a slip: the per-frame check's (a near scene, where ICP holds)
    return pnp


def mean_step(motion: np.ndarray, frames: int, last_step: np.ndarray) -> np.ndarray:
    """(4, 4) a constant-velocity step for the frames after a corrected window: ``last_step``'s rotation
    and the window's translation per frame, expressed in the window's last camera frame.

    Args:
        motion: (4, 4) the current camera's pose in the anchor camera's frame.
        frames: frames the window spans (>= 1).
        last_step: (4, 4) the last frame's step (its rotation is kept).
    """
    t_cur = motion[:3, :3].T @ motion[:3, 3] / max(frames, 1)
    return make_pose(last_step[:3, :3], t_cur)
