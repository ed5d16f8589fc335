"""A live run whose first camera never sends: the frames held for it are bounded (``FIRST_CAMERA_WAIT_FRAMES``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from shgm_slam import open_sequence
from shgm_slam.live import LiveRun, fleet


def give(live: LiveRun, robot: str, sequence, i: int) -> list:
    f = sequence[i]
    return live.add_frame(robot, f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                          T_world_cam=f.T_world_cam)  # fmt: skip


def test_a_first_camera_that_never_sends_holds_the_others_only_up_to_the_bound(
    tiny_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """car1 (the first camera, the shared frame's) is unplugged: car2's frames were held, every one of them, until
    ``finish`` (an hour of four cameras at 10 fps ran out of memory). Now the run starts without car1 once warm car2
    holds the bound (30 here, ~half the tiny world's frames), car2's first frame is the shared frame, every frame
    since runs (and is dropped) at its call, and car1 joins when it is plugged in."""
    monkeypatch.setattr(fleet, "FIRST_CAMERA_WAIT_FRAMES", 30)
    sequences = {n: open_sequence(tiny_scenario / n) for n in ("car1", "car2")}
    live = LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp_path / "out")
    car2 = sequences["car2"]
    assert len(car2) > 40
    poses, most_held = [], 0
    with caplog.at_level("WARNING"):
        for i in range(len(car2)):
            poses += give(live, "car2", car2, i)
            most_held = max(most_held, len(live._held))
    assert live.started and live.warming == ("car1",)
    assert most_held < 30 and live._held == []
    assert [(p.robot, p.index) for p in poses] == [("car2", i) for i in range(len(car2))]
    assert poses[0].T_shared_cam is not None  # car2 took the shared frame
    assert all(image is None for image in live.streams["car2"]._images)  # run and dropped
    assert "the first camera, car1, has sent no frame while car2 holds 30 frames" in caplog.text
    assert caplog.text.count("the run starts without it, with car2") == 1
    car1 = sequences["car1"]
    joined = [p for i in range(len(car1)) for p in give(live, "car1", car1, i)]  # plugged in at last: it joins
    assert [p.index for p in joined] == list(range(len(car1))) and not live.warming
    summary = live.finish()
    assert [r.name for r in summary.robots] == ["car2", "car1"] and summary.robots[0].localized
    assert (summary.out_dir / "car1_odometry_tum.txt").is_file()
