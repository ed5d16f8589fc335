"""``bench heldout --fps``: worlds rendered at another frame rate, cached apart, refused where they do not match."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import shgm_slam.bench.heldout as heldout
from shgm_slam.bench.heldout import HeldoutOptions, check_replayable, check_resumable, run_options, world_folder
from shgm_slam.bench.heldout_judge import InputMode
from shgm_slam.cli import app
from shgm_slam.errors import ConfigError, SimulationError


def _options(**kwargs) -> HeldoutOptions:
    return HeldoutOptions(scenarios=("airsim-like",), seeds=(2,), modes=(InputMode.FILES,), **kwargs)


def _record_run(folder: Path, asked: dict | None) -> Path:
    """A cached run of airsim-like seed 2 (files) under ``folder/runs`` whose ``verdicts.json`` records ``asked``."""
    run = folder / "runs" / "airsim-like-s2-files"
    run.mkdir(parents=True)
    (run / "verdicts.json").write_text(json.dumps({"seed": 2, **({} if asked is None else {"asked": asked})}))
    return run


def test_worlds_at_10_fps_keep_their_cache_folder_and_other_rates_are_cached_apart(tmp_path):
    plain = world_folder(tmp_path, "airsim-like", 10, (320, 96))
    assert plain.name == "airsim-like-s10-320x96"  # caches rendered before --fps still hit
    assert world_folder(tmp_path, "airsim-like", 10, (320, 96), fps=10) == plain
    names = {fps: world_folder(tmp_path, "airsim-like", 10, (320, 96), fps=fps).name for fps in (3, 5.0, 3.3)}
    assert names == {3: "airsim-like-s10-320x96-fps3", 5.0: "airsim-like-s10-320x96-fps5",
                     3.3: "airsim-like-s10-320x96-fps3.3"}  # fmt: skip
    close = {world_folder(tmp_path, "synthia-like", 1, (320, 96), fps=f) for f in (3.333333, 3.3333333, 10 / 3)}
    assert len(close) == 3  # rates that print alike at six digits are not one world
    both = world_folder(tmp_path, "airsim-like", 10, (320, 96), supersample=2, uav_altitude_m=(85.0, 95.0), fps=5)
    assert both.name == "airsim-like-s10-320x96-ss2-uav85-95-fps5"


@pytest.mark.parametrize(("fps", "words"), [("0", "0 is out of range 0.1..100"), ("-5", "-5 is out of range"),
                                           ("nan", "nan is not a finite number"), ("inf", "inf is not a finite"),
                                           ("101", "101 is out of range"), ("x", "'x' is not a number")])  # fmt: skip
def test_bench_heldout_refuses_a_frame_rate_that_is_not_a_positive_finite_rate_up_to_100(tmp_path, fps, words):
    result = CliRunner().invoke(app, ["bench", "heldout", f"--fps={fps}", "-o", str(tmp_path / "o"),
                                      "--cache", str(tmp_path / "c")])  # fmt: skip
    assert result.exit_code == 2 and "Invalid value for '--fps'" in result.output, result.output
    assert words in result.output, result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


@pytest.mark.parametrize("fps", [0.0, -5.0, float("nan"), float("inf"), 101.0])
def test_the_library_refuses_such_a_frame_rate_too_instead_of_skipping_every_world(fps):
    with pytest.raises(ConfigError, match="at most 100"):
        _options(fps=fps)


def test_the_frame_rate_reaches_the_simulator_and_the_results(tmp_path, monkeypatch):
    """``--fps 5`` renders the worlds at 5 Hz into their own cache folder; heldout.json records it and heldout.md
    names it. (The simulator is stopped at once: the world is then skipped, nothing is rendered or run.)"""
    asked = []

    def simulate_cached(scenario, folder, **kwargs):
        asked.append((Path(folder).name, kwargs["fps"]))
        raise SimulationError("not rendered in this test")

    monkeypatch.setattr(heldout, "simulate_cached", simulate_cached)
    out = tmp_path / "o"
    result = CliRunner().invoke(app, ["bench", "heldout", "--fps", "5", "--scenario", "airsim-like", "--mode", "files",
                                      "--seeds", "3", "-o", str(out), "--cache", str(tmp_path / "c")])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert asked == [("airsim-like-s3-320x96-fps5", 5.0)]
    assert json.loads((out / "heldout.json").read_text())["options"]["fps"] == 5.0
    assert "320x96 at 5 Hz" in (out / "heldout.md").read_text()
    with pytest.raises(SimulationError):
        heldout.ensure_world(tmp_path / "c", "synthia-like", 4, (320, 96), print)  # the default rate, as before
    assert asked[-1] == ("synthia-like-s4-320x96", 10.0)


def test_a_replay_of_runs_made_at_another_frame_rate_is_refused_before_any_world_is_built(tmp_path, monkeypatch):
    """Recorded keyframes at 10 Hz judged against worlds rendered at 5 Hz (other poses at other times) would be
    reported as the 5 Hz benchmark's; a run recorded before the frame rate was recorded counts as 10 Hz."""
    monkeypatch.setattr(heldout, "ensure_world", lambda *a, **k: pytest.fail("a world was built before the refusal"))
    recorded = tmp_path / "recorded"
    run = _record_run(recorded, {k: v for k, v in run_options(_options()).items() if k != "fps"})  # an older record
    for asked in (_options(fps=5.0, replay_from=recorded), _options(fps=3.3, max_frames=50, replay_from=recorded)):
        with pytest.raises(ConfigError, match=r"holds runs made with other options \(airsim-like-s2-files: fps 10.0 "
                                              rf"\(asked: {asked.fps}\)\).*give the recorded benchmark's --fps$"):
            heldout.run_heldout_benchmark(tmp_path / "out", asked)
    check_replayable(_options(replay_from=recorded))  # recorded at 10 Hz, replayed at 10 Hz
    check_replayable(_options(max_frames=50, replay_from=recorded))  # a replay runs the frames recorded
    (run / "verdicts.json").write_text(json.dumps({"seed": 2, "asked": run_options(_options(fps=5.0))}))
    check_replayable(_options(fps=5.0, replay_from=recorded))
    with pytest.raises(ConfigError, match=r"fps 5.0 \(asked: 10.0\)"):
        check_replayable(_options(replay_from=recorded))
    with pytest.raises(ConfigError, match=r"resolution \[320, 96\] \(asked: \[640, 192\]\).*benchmark's --resolution$"):
        check_replayable(_options(fps=5.0, resolution=(640, 192), replay_from=recorded))  # the other renderings too


def test_a_resume_keeps_runs_cached_before_the_frame_rate_was_recorded_and_refuses_them_at_another_rate(tmp_path):
    _record_run(tmp_path, {k: v for k, v in run_options(_options()).items() if k != "fps"})
    check_resumable(tmp_path, _options())  # made at 10 Hz, resumed at 10 Hz
    with pytest.raises(ConfigError, match=r"fps 10.0 \(asked: 5.0\).*another --out"):
        check_resumable(tmp_path, _options(fps=5.0))
