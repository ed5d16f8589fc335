"""A live run that waits for a camera that never sends, or stops before it is warm: the frames held meanwhile are
bounded (``START_WAIT_FRAMES``)."""

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
    monkeypatch.setattr(fleet, "START_WAIT_FRAMES", 30)
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
    assert "car1 has sent no frame, while car2 holds 30 frames (live.fleet.START_WAIT_FRAMES)" in caplog.text
    assert caplog.text.count("the run starts with car2, and car2's first camera frame is the shared frame") == 1
    car1 = sequences["car1"]
    joined = [p for i in range(len(car1)) for p in give(live, "car1", car1, i)]  # plugged in at last: it joins
    assert [p.index for p in joined] == list(range(len(car1))) and not live.warming
    summary = live.finish()
    assert [r.name for r in summary.robots] == ["car2", "car1"] and summary.robots[0].localized
    assert (summary.out_dir / "car1_odometry_tum.txt").is_file()


@pytest.mark.parametrize("stalled", ["car1", "car2"])
def test_a_camera_that_stops_after_its_first_frames_holds_the_others_only_up_to_the_bound(
    stalled: str, tiny_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A camera that sent two frames and stopped never warmed up, and the run waited for it holding every frame of
    the others (the bound covered only a first camera that sent nothing). Now the run starts with the warm robot at
    the bound; the shared frame stays the first camera's when it is the warm one, and the stalled camera joins when
    its frames come again."""
    monkeypatch.setattr(fleet, "START_WAIT_FRAMES", 30)
    sequences = {n: open_sequence(tiny_scenario / n) for n in ("car1", "car2")}
    live = LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp_path / "out")
    warm = "car2" if stalled == "car1" else "car1"
    poses = give(live, stalled, sequences[stalled], 0) + give(live, stalled, sequences[stalled], 1)
    most_held = 0
    with caplog.at_level("WARNING"):
        for i in range(len(sequences[warm])):
            poses += give(live, warm, sequences[warm], i)
            most_held = max(most_held, sum(r == warm for r, _ in live._held))
    assert live.started and most_held < 30
    assert f"{stalled} has sent 2 frames and is not warm" in caplog.text
    assert f"{warm}'s first camera frame is the shared frame" in caplog.text
    assert [p.index for p in poses if p.robot == warm] == list(range(len(sequences[warm])))
    for i in range(2, len(sequences[stalled])):  # plugged in again: it joins with its held frames
        poses += give(live, stalled, sequences[stalled], i)
    assert [p.index for p in poses if p.robot == stalled] == list(range(len(sequences[stalled])))
    summary = live.finish()
    assert [r.name for r in summary.robots] == [warm, stalled] and summary.robots[0].localized
