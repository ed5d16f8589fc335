"""The run report's warnings on degenerate data: a depth model far off its metric scale is reported."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from shgm_slam.config import ShgmConfig
from shgm_slam.run_report import RobotReport, report_degenerate
from shgm_slam.types import Intrinsics

TUNED_CAMERA = Intrinsics(184.0, 184.0, 160.0, 48.0, 320, 96)  # 82 degrees, as the simulator renders


def _front(camera_height_m: float, intrinsics: Intrinsics = TUNED_CAMERA) -> SimpleNamespace:
    cfg = ShgmConfig()
    cfg.perception.camera_height_m = camera_height_m
    return SimpleNamespace(cfg=cfg, stopped=False, failures=[], sequence=SimpleNamespace(intrinsics=intrinsics))


@pytest.mark.parametrize(("scale", "warned"), [(0.45, True), (2.2, True), (0.9, False), (1.3, False), (None, False)])
def test_a_depth_scale_far_from_one_is_a_warning(scale: float | None, warned: bool) -> None:
    """The demo models on real KITTI 07 needed x0.45: the run says so, naming the height it scaled to and what to
    check; a network's usual few percent, or no scaling at all, say nothing."""
    rep = RobotReport("k07", frames=0, frames_processed=0, frames_skipped=0, keyframes=0, nodes=0, localized=False)
    rep.depth_scale = scale
    report_degenerate([rep], {"k07": _front(1.2)}, {})
    said = [w for w in rep.warnings if "predicted depth scaled" in w]
    assert len(said) == int(warned)
    if warned:
        assert f"x{scale:.2f}" in said[0] and "1.2 m below the camera" in said[0]
        assert "perception.camera_height_m" in said[0]


def test_a_camera_far_smaller_or_narrower_than_the_tuned_ones_is_named():
    """At 80x24 or 64x48 pixels, or a 10-degree view, the demo world's robots ran and none but the first was placed,
    with nothing naming the camera as the reason."""
    from shgm_slam.run_report import camera_warning

    assert camera_warning(TUNED_CAMERA) is None
    assert camera_warning(Intrinsics(718.9, 718.9, 607.2, 185.2, 1241, 376)) is None  # KITTI
    assert "a 10-degree field of view" in camera_warning(Intrinsics(1829.0, 1829.0, 160.0, 48.0, 320, 96))
    rep = RobotReport("tiny", frames=0, frames_processed=0, frames_skipped=0, keyframes=0, nodes=0, localized=False)
    report_degenerate([rep], {"tiny": _front(1.6, Intrinsics(46.0, 46.0, 40.0, 12.0, 80, 24))}, {})
    assert len(rep.warnings) == 1 and rep.warnings[0].startswith("camera of 80x24 pixels: the defaults were chosen")
