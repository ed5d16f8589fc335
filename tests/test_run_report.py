"""The run report's warnings on degenerate data: a depth model far off its metric scale is reported."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from shgm_slam.config import ShgmConfig
from shgm_slam.run_report import RobotReport, report_degenerate


def _front(camera_height_m: float) -> SimpleNamespace:
    cfg = ShgmConfig()
    cfg.perception.camera_height_m = camera_height_m
    return SimpleNamespace(cfg=cfg, stopped=False, failures=[])


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
