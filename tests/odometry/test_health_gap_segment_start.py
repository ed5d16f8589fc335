"""The frame gap check at a new segment's first pose: the frames a re-initialisation waited through (no measured
pose) are not checked, so the time since the last checked frame is no gap of the new segment."""

from __future__ import annotations

import numpy as np

from shgm_slam.config import OdometryConfig
from shgm_slam.geometry.se3 import make_pose
from shgm_slam.odometry.health import FailureReason, HealthLimits, OdometryHealthMonitor

LIMITS = HealthLimits.from_config(OdometryConfig())


def test_a_new_segment_s_first_pose_after_a_long_wait_is_no_gap_and_its_first_step_is_checked() -> None:
    """After a divergence the front end waited 3 s for a measured pose (frames unchecked): the new segment's first
    pose was called a frame gap (the front end drops that result) before it was kept, so the segment's first step
    went unchecked: a 20 m jump passed."""
    mon = OdometryHealthMonitor(LIMITS)
    for i in range(10):  # 10 Hz, 8 m/s
        assert mon.check(i, 0.1 * i, make_pose(np.eye(3), [0.0, 0.0, 0.8 * i])) is None
    mon.reset()  # a new segment; frames 10-39 waited through, unchecked
    assert mon.check(40, 4.0, np.eye(4)) is None  # 3.1 s after frame 9: the segment's first pose
    failure = mon.check(41, 4.1, make_pose(np.eye(3), [0.0, 0.0, 20.0]))
    assert failure is not None and failure.reason is FailureReason.SPEED
    assert mon.check(60, 7.0, np.eye(4)) is not None  # inside a segment a gap is still one
