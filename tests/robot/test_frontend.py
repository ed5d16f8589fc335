"""The robot front end: thin objects of predicted depth are placed at their near part; a restarted odometry
continues the vehicle's last trusted motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import shgm_slam.robot.frontend as frontend_module
from shgm_slam.config import ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.geometry import se3
from shgm_slam.labels import THIN_OBJECT_DEPTH_PERCENTILES, Label
from shgm_slam.runner import make_frontend
from tests.perception.test_ground_scale import _perceived_copy
from tests.robot.jumps import jumping_odometry
from tests.spies import record_depth_percentiles


def _percentiles_used(front, monkeypatch: pytest.MonkeyPatch, frames: int = 6) -> list:
    seen = record_depth_percentiles(monkeypatch, frontend_module)
    for i in range(frames):
        front.process(i)
    return seen


def test_thin_objects_take_the_near_percentile_only_with_predicted_depth(
    tiny_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = '{"format": "shgm-perceive/1", "depth_model": {"path": "/m/depth.onnx"}, "seg_model": null}'
    cfg = ShgmConfig()
    assert cfg.extraction.predicted_depth_percentiles == THIN_OBJECT_DEPTH_PERCENTILES
    assert set(THIN_OBJECT_DEPTH_PERCENTILES) == {Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN}
    perceived = _perceived_copy(tiny_scenario / "car1", tmp_path / "p", model)
    predicted = make_frontend("car1", open_sequence(perceived), cfg)
    used = _percentiles_used(predicted, monkeypatch)
    assert used and all(u == THIN_OBJECT_DEPTH_PERCENTILES for u in used)
    measured = make_frontend("car1", open_sequence(tiny_scenario / "car1"), cfg)
    used = _percentiles_used(measured, monkeypatch)
    assert used and all(u is None for u in used)  # rendered (measured) depth keeps the mean
    mine = cfg.model_copy(update={"extraction": cfg.extraction.model_copy(
        update={"predicted_depth_percentiles": {Label.VEGETATION: 40.0}})})  # fmt: skip
    own = make_frontend("car1", open_sequence(tmp_path / "p"), mine)
    used = _percentiles_used(own, monkeypatch)
    assert used and all(u == {Label.VEGETATION: 40.0} for u in used)  # a configured mapping replaces the default


class _RecordingResets:
    """Wraps an odometry source and records the motion of every ``reset``."""

    def __init__(self, inner) -> None:
        self.inner, self.motions = inner, []

    def update(self, *args, **kwargs):
        return self.inner.update(*args, **kwargs)

    def reset(self, motion=None) -> None:
        self.motions.append(None if motion is None else motion.copy())
        self.inner.reset(motion)


@pytest.mark.parametrize("memory_s", [frontend_module.MOTION_MEMORY_S, 0.1])
def test_a_restarted_odometry_continues_the_last_trusted_motion(
    tiny_scenario: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, memory_s: float
) -> None:
    """car1's odometry jumps 30 m at frame 25 (4 Hz): the new segment's odometry is re-initialised with the
    step into frame 24 (the last one before the onset), the vehicle's velocity; a restart more than
    ``MOTION_MEMORY_S`` after that step (here 0.25 s against 0.1 s) starts at rest."""
    monkeypatch.setattr(frontend_module, "MOTION_MEMORY_S", memory_s)
    seq, cfg, gt = jumping_odometry(tiny_scenario / "car1", tmp_path, 25)
    front = make_frontend("car1", seq, cfg)
    front.odometry = _RecordingResets(front.odometry)
    for i in range(30):
        front.process(i)
    assert [f.onset_frame for f in front.failures] == [25] and front.segments[1].first_frame == 25
    assert len(front.odometry.motions) == 1
    if memory_s >= 0.25:
        np.testing.assert_allclose(front.odometry.motions[0], se3.inverse(gt[23]) @ gt[24], atol=1e-6)
        assert np.linalg.norm(front.odometry.motions[0][:3, 3]) > 1.0  # the car was moving
    else:
        assert front.odometry.motions == [None]


def test_a_gap_in_the_frame_times_starts_a_new_segment(tiny_scenario: Path, tmp_path: Path) -> None:
    """car1's frames 20 on come 5 s later (a paused camera): its odometry, which registers across the gap as if
    no time had passed, is not trusted across it; frame 20 begins a new trajectory segment."""
    import shutil

    folder = shutil.copytree(tiny_scenario / "car1", tmp_path / "car1")
    times = np.loadtxt(folder / "times.txt")
    times[20:] += 5.0
    np.savetxt(folder / "times.txt", times, fmt="%.6f")
    front = make_frontend("car1", open_sequence(str(folder)), ShgmConfig())
    for i in range(30):
        front.process(i)
    assert [(f.reason.value, f.onset_frame) for f in front.failures] == [("frame-gap", 20)]
    assert len(front.segments) == 2 and front.segments[1].first_frame == 20
