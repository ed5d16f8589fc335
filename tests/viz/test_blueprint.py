"""The default blueprint builds for 1-3 robots and shows each robot's camera and the shared world."""

from __future__ import annotations

import pytest
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from shgm_slam.viz.blueprint import camera_path, default_blueprint, matches_path, robot_path, timings_path


def _views(item) -> list:
    """All views in a blueprint container tree, depth first."""
    if isinstance(item, rrb.Container):
        return [v for child in item.contents for v in _views(child)]
    return [item]


@pytest.mark.parametrize("robots", [["robot_a"], ["robot_a", "robot_b"], ["r0", "r1", "r2"]])
def test_blueprint_has_world_cameras_series_and_log(robots):
    bp = default_blueprint(robots)
    views = _views(bp.root_container)
    spatial3d = [v for v in views if isinstance(v, rrb.Spatial3DView)]
    assert len(spatial3d) == 1 and str(spatial3d[0].origin) == "/world"
    excluded = {c for c in spatial3d[0].contents if c.startswith("-")}
    for r in robots:
        assert f"- {camera_path(r)}/rgb" in excluded and f"- {camera_path(r)}/depth" in excluded
        cams = [v for v in views if isinstance(v, rrb.Spatial2DView) and str(v.origin) == camera_path(r)]
        shown = {c for v in cams for c in v.contents}
        assert shown == {f"{camera_path(r)}/rgb", f"{camera_path(r)}/seg", f"{camera_path(r)}/depth"}
    assert any(isinstance(v, rrb.TimeSeriesView) and str(v.origin) == "/timings" for v in views)
    assert any(isinstance(v, rrb.TextLogView) and str(v.origin) == "/log" for v in views)
    assert len(views) == 2 * len(robots) + 4


def test_blueprint_is_sent_with_a_recording(tmp_path):
    path = tmp_path / "bp.rrd"
    rec = rr.RecordingStream("shgm_slam_test")
    rec.save(path, default_blueprint=default_blueprint(["robot_a", "robot_b", "robot_c"]))
    rec.log("/world", rr.ViewCoordinates.RDF, static=True)
    rec.flush()
    rec.disconnect()
    app_ids = {r.application_id for r in RrdReader(path).recordings()}
    assert app_ids == {"shgm_slam_test"}
    assert path.stat().st_size > 0


def test_paths_escape_odd_robot_names():
    assert robot_path("robot_a") == "/world/robot_a"
    assert camera_path("a b") == "/world/a\\ b/cam"
    assert timings_path("r/1", "icp") == "/timings/r\\/1/icp"
    assert matches_path("a", "b") == "/world/matches/a__b"
