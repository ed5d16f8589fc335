"""``bench live``: a world run recorded and fed frame by frame, side by side."""

from __future__ import annotations

import json
from pathlib import Path

from shgm_slam import open_sequence
from shgm_slam.bench.live import live_markdown, run_live_benchmark


def test_the_live_benchmark_compares_both_runs_and_times_every_call(tiny_scenario: Path, tmp_path: Path) -> None:
    robots = {n: open_sequence(tiny_scenario / n) for n in ("car1", "car2")}
    results = run_live_benchmark(robots, tmp_path / "bench")
    frames = sum(len(s) for s in robots.values())
    assert results["frames"] == frames and results["identical"] and len(results["files"]) >= 4
    assert 0 < results["held_frames"] < frames
    assert sum(results["held_per_robot"].values()) == results["held_frames"]
    assert results["placed"]["live"] == results["placed"]["recorded"]
    call = results["live_call_ms"]
    assert 0 < call["median"] <= call["p95"] <= call["max"]
    saved = json.loads((tmp_path / "bench" / "live.json").read_text())
    assert saved["identical"] is True and "environment" in saved
    text = live_markdown(results)
    assert "the same, byte for byte" in text and "| live, per add_frame call |" in text
    results["files"]["car1_fused_tum.txt"] = False
    assert "NOT the same: car1_fused_tum.txt" in live_markdown({**results, "identical": False})
