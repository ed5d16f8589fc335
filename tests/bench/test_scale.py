"""bench scale: steps binned by distance, the height split of an error, the report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.bench.scale import KM_M, ROBOT, _bin_row, _Recorder, height_split_m, scale_markdown
from shgm_slam.io.trajectories import write_tum
from shgm_slam.run_report import FrameStats
from shgm_slam.server.records import MatchRecord


def _match(nodes_a: int, nodes_b: int) -> MatchRecord:
    return MatchRecord(1, "a", "b", "submap", False, False, "", None, None, None, np.zeros((0, 2)), 0, nodes_a,
                       nodes_b, {})  # fmt: skip


def _stats(robot: str, frame: int, keyframe: bool, ms: float) -> FrameStats:
    matches = (_match(100, 20), _match(300, 40)) if frame % 10 == 0 else ()
    return FrameStats(robot, frame, keyframe, ms, 1.0, ms / 2, ms / 4, ms, 3 * ms, matches, 2 * ms)


def test_recorder_bins_the_long_robot_by_distance_and_keeps_others_apart():
    path_m = np.linspace(0.0, 2500.0, 251)  # 10 m per frame: frames 0-99 in km 0, 100-199 in km 1, 200-250 in km 2
    rec = _Recorder(path_m)
    for f in range(251):
        rec(_stats(ROBOT, f, f % 2 == 0, 10.0 if f < 100 else 20.0))
    rec(_stats("other", 0, True, 5.0))
    assert [b.frames for b in rec.bins] == [100, 100, 51]
    assert [b.keyframes for b in rec.bins] == [50, 50, 26]
    assert rec.other_robots.frames == 1
    first, second = _bin_row(rec.bins[0], 0.0, 1.0), _bin_row(rec.bins[1], 1.0, 2.0)
    assert second["front_end_ms_per_kf"] == pytest.approx(2 * first["front_end_ms_per_kf"])
    assert first["front_end_ms_per_kf"] == pytest.approx(10.0 * 100 / 50)
    assert first["runner_other_ms_per_kf"] == pytest.approx((30.0 - 10.0 - 1.0 - 10.0) * 100 / 50)
    assert second["cpu_ms_per_kf"] == pytest.approx(2 * first["cpu_ms_per_kf"])
    assert first["cpu_ms_per_frame"] == pytest.approx(20.0)
    assert first["matches"] == 20 and first["nodes_per_match"] == pytest.approx(230.0)
    assert first["ms_per_match"] == pytest.approx(5.0 * 100 / 20)  # 5 ms of matching in each of 100 frames
    assert rec.bins[0].rss_end_mb > 0 and np.isfinite(rec.rss_start_mb)
    assert len(rec.bins) == int(path_m[-1] // KM_M) + 1


def test_height_split_separates_vertical_from_horizontal_error(tmp_path: Path):
    t = np.arange(50) * 0.1
    gt = np.tile(np.eye(4), (50, 1, 1))
    gt[:, 2, 3] = np.arange(50.0)  # KITTI camera frame: driving along z, y down
    est = gt.copy()
    est[:, 1, 3] += 2.0  # 2 m low (y points down)
    est[:, 0, 3] += 1.0  # 1 m to the right
    write_tum(tmp_path / f"{ROBOT}_gt_tum.txt", t, gt)
    write_tum(tmp_path / f"{ROBOT}_fused_tum.txt", t, est)
    h, v = height_split_m(tmp_path, ROBOT)
    assert h == pytest.approx(1.0, abs=1e-6) and v == pytest.approx(2.0, abs=1e-6)
    assert all(np.isnan(height_split_m(tmp_path, "nobody")))


def test_markdown_shows_every_kilometre_and_the_ratio():
    row = {"from_km": 0.0, "to_km": 1.0, "keyframes": 10, "front_end_ms_per_kf": 1.0, "match_ms_per_kf": 2.0,
           "backend_ms_per_kf": 3.0, "results_files_ms_per_kf": 0.2, "corrections_ms_per_kf": 0.1,
           "server_other_ms_per_kf": 0.5, "runner_other_ms_per_kf": 0.1,
           "total_ms_per_kf": 6.6, "cpu_ms_per_kf": 5.0, "matches": 2, "ms_per_match": 10.0, "nodes_per_match": 100.0,
           "rss_end_mb": 300.0, "rss_growth_kb_per_kf": 12.0}  # fmt: skip
    results = {
        "robot": ROBOT, "path_km": 2.0, "per_km": [row, {**row, "from_km": 1.0, "to_km": 2.0}],
        "targets": {"time_per_kf_last_over_first": 1.0, "cpu_per_kf_last_over_first": 1.1,
                    "cpu_per_frame_last_over_first": 1.05,
                    "rss_growth_per_kf_last_over_first": 1.0},
        "rss_start_mb": 250.0, "height_split_m": {ROBOT: (0.5, 0.2)},
        "run": {"robots": [{"name": ROBOT, "ate_fused_m": 0.6, "ate_fused_aligned_m": 0.4, "localized": True}],
                "matches_tried": 5, "closures_accepted": 2, "wall_s": 10.0},
        "memory": {"1 km": {"peak_rss_mb": 300.0, "wall_s": 5.0}},
    }  # fmt: skip
    text = scale_markdown(results)
    assert "| 0-1.0 |" in text and "| 1-2.0 |" in text
    assert "time per keyframe 1.00" in text and "0.50 / 0.20" in text and "1 km" in text
