"""The held-out benchmark's runs: worlds cached by what they depend on, seeds, resuming, replays, stops."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from shgm_slam.bench.heldout import REPORT_SEEDS, TUNING_SEEDS, world_folder
from shgm_slam.bench.heldout_judge import InputMode
from shgm_slam.errors import DataError


def test_tuning_and_report_seeds_are_disjoint():
    assert not set(TUNING_SEEDS) & set(REPORT_SEEDS)
    assert len(REPORT_SEEDS) >= 10


def test_worlds_rendered_with_more_rays_per_pixel_are_cached_apart(tmp_path):
    plain = world_folder(tmp_path, "airsim-like", 10, (320, 96))
    assert plain.name == "airsim-like-s10-320x96"  # the caches rendered before the option stay valid
    assert world_folder(tmp_path, "airsim-like", 10, (320, 96), supersample=1) == plain
    assert world_folder(tmp_path, "airsim-like", 10, (320, 96), supersample=3).name == "airsim-like-s10-320x96-ss3"


def test_uavs_at_another_altitude_are_cached_apart_and_only_airsim_like_has_one(tmp_path):
    high = world_folder(tmp_path, "airsim-like", 15, (320, 96), uav_altitude_m=(85.0, 95.0))
    assert high.name == "airsim-like-s15-320x96-uav85-95"
    same = world_folder(tmp_path, "synthia-like", 15, (320, 96), uav_altitude_m=(85.0, 95.0))
    assert same == world_folder(tmp_path, "synthia-like", 15, (320, 96))  # no UAV there: the same world


def test_corrupted_worlds_are_cached_apart_and_rendered_corrupted(tmp_path, monkeypatch):
    from shgm_slam.bench import heldout
    from shgm_slam.sim.corruption import CorruptionLevels

    noisy = CorruptionLevels.from_levels(depth_noise=0.05, label_noise=0.1)
    folder = world_folder(tmp_path, "synthia-like", 12, (320, 96), corruption=noisy)
    assert folder.name == "synthia-like-s12-320x96-d0.05-l0.1"
    assert world_folder(tmp_path, "synthia-like", 12, (320, 96), corruption=CorruptionLevels()) == world_folder(
        tmp_path, "synthia-like", 12, (320, 96)
    )  # no corruption: the perfect renders' cache
    seen = {}

    def fake_simulate(scenario, out, **kwargs):
        seen.update(kwargs, out=out)
        (out.mkdir(parents=True), (out / "scenario.json").write_text("{}"))

    monkeypatch.setattr("shgm_slam.sim.cache.simulate", fake_simulate)
    assert heldout.ensure_world(tmp_path, "synthia-like", 12, (320, 96), print, corruption=noisy) == folder
    assert (folder / "scenario.json").is_file() and seen["corruption"] == noisy


def test_bench_heldout_refuses_a_uav_altitude_whose_ground_is_out_of_range(tmp_path):
    from typer.testing import CliRunner

    from shgm_slam.cli import app

    for alt, words in (("160", "raise --max-depth"), ("x", "LOW-HIGH")):
        bad = CliRunner().invoke(app, ["bench", "heldout", "--uav-altitude", alt, "-o", str(tmp_path / "o"),
                                       "--cache", str(tmp_path / "c")])  # fmt: skip
        assert bad.exit_code == 2 and words in bad.output, bad.output
    assert not (tmp_path / "c").exists()
    bad = CliRunner().invoke(app, ["bench", "heldout", "--resolution", "640", "-o", str(tmp_path / "o"),
                                   "--cache", str(tmp_path / "c")])  # fmt: skip
    assert bad.exit_code == 2 and "WIDTHxHEIGHT" in bad.output, bad.output
    assert not (tmp_path / "c").exists()


def test_a_resume_refuses_runs_made_with_other_options(tmp_path):
    """A results folder resumed with another render size, UAV altitude, corruption or frame cut would report its
    old runs as the new benchmark's: refused before anything runs, naming what differs."""
    from shgm_slam.bench.heldout import HeldoutOptions, check_resumable, run_options
    from shgm_slam.errors import ConfigError

    made = HeldoutOptions(scenarios=("airsim-like",), seeds=(1, 2), modes=(InputMode.FILES,), max_frames=30)
    run = tmp_path / "runs" / "airsim-like-s2-files"
    run.mkdir(parents=True)
    (run / "verdicts.json").write_text(json.dumps({"seed": 2, "asked": run_options(made)}))
    check_resumable(tmp_path, made)  # the same options: resumed
    check_resumable(tmp_path, HeldoutOptions(scenarios=("airsim-like",), seeds=(3,), modes=(InputMode.FILES,),
                                             resolution=(640, 192)))  # other worlds: none of its runs is reused
    for other, words in ((dict(resolution=(640, 192)), "resolution [320, 96] (asked: [640, 192])"),
                         (dict(max_frames=None), "max_frames 30 (asked: None)"),
                         (dict(uav_altitude_m=(85.0, 95.0)), "uav_altitude_m None (asked: [85.0, 95.0])")):
        asked = HeldoutOptions(scenarios=("airsim-like",), seeds=(1, 2), modes=(InputMode.FILES,),
                               **{"max_frames": 30, **other})  # fmt: skip
        with pytest.raises(ConfigError, match="another --out") as err:
            check_resumable(tmp_path, asked)
        assert "airsim-like-s2-files" in str(err.value) and words in str(err.value)
    (run / "verdicts.json").write_text(json.dumps({"seed": 2}))  # cached before the options were recorded
    check_resumable(tmp_path, HeldoutOptions(scenarios=("airsim-like",), seeds=(2,), modes=(InputMode.FILES,)))


def test_a_world_that_cannot_be_built_is_skipped_and_reported_not_fatal(tmp_path, monkeypatch):
    """A UAV altitude below one city's roofs refuses that world only: the benchmark still writes its report,
    and the report says which world was skipped and why."""
    import shgm_slam.bench.heldout as heldout
    from shgm_slam.errors import SimulationError

    def refuse(cache, scenario, seed, *args, **kwargs):
        raise SimulationError(f"the UAV flies through buildings (seed {seed})")

    monkeypatch.setattr(heldout, "ensure_world", refuse)
    options = heldout.HeldoutOptions(scenarios=("airsim-like",), seeds=(15, 19), modes=(InputMode.FILES,),
                                     cache=tmp_path / "cache", uav_altitude_m=(30.0, 40.0))  # fmt: skip
    results = heldout.run_heldout_benchmark(tmp_path / "out", options)
    assert [w["seed"] for w in results["skipped_worlds"]] == [15, 19] and results["robots"] == []
    report = (tmp_path / "out" / "heldout.md").read_text()
    assert "Worlds skipped" in report and "airsim-like seed 19: the UAV flies through buildings (seed 19)" in report
    assert json.loads((tmp_path / "out" / "heldout.json").read_text())["skipped_worlds"][0]["seed"] == 15


def test_a_replay_reports_its_own_placements_not_the_recorded_ones(tiny_scenario: Path, tmp_path: Path) -> None:
    """``bench heldout --replay-from`` runs the map server again on a recorded run's keyframes: the robots'
    provisional flags, waiting lines, stretches on their own odometry and last looks in its ``metrics.json`` are the
    replayed server's (the judge reads the flag). Recorded trusting single matches (car2 provisional after 30
    frames), replayed with the default (two independent matches): car2 waits, and says so."""
    from shgm_slam.bench.heldout import replay_one
    from shgm_slam.config import OdometryKind, ShgmConfig
    from shgm_slam.runner import open_robots, run_slam

    cfg = ShgmConfig()
    cfg.odometry.kind = OdometryKind.GT
    cfg.backend.min_closures_to_anchor = 1
    recorded = tmp_path / "recorded"
    robots = open_robots([f"car1={tiny_scenario / 'car1'}", f"car2={tiny_scenario / 'car2'}:0-30"])
    run_slam(robots, cfg, recorded, journal=True)
    before = {r["name"]: r for r in json.loads((recorded / "metrics.json").read_text())["robots"]}
    assert before["car2"]["provisional"] and before["car2"]["path_from_closures_m"] is not None
    assert any(w.startswith("car2 is placed provisionally") for w in before["car2"]["warnings"])

    metrics = replay_one(recorded, InputMode.FILES, tmp_path / "replayed", ["car1", "car2"])
    car2 = next(r for r in metrics["robots"] if r["name"] == "car2")
    assert not car2["provisional"] and car2["path_from_closures_m"] is None  # no longer placed: nothing rests on it
    assert not any("provisionally" in w for w in car2["warnings"])
    waiting = [w for w in car2["warnings"] if w.startswith("car2 is not placed in the shared frame")]
    assert len(waiting) == 1 and "(here: matches that found the same objects" in waiting[0]
    assert json.loads((tmp_path / "replayed" / "metrics.json").read_text())["robots"][1] == car2
    assert metrics["last_looks"] and all(line.startswith("car2: ") for line in metrics["last_looks"])


def test_a_stopped_run_ends_the_benchmark_is_not_cached_and_the_same_command_resumes_it(tiny_scenario, tmp_path,
                                                                                       monkeypatch):
    """Ctrl-C lands in the second world's run: ``run_slam`` keeps that run's results and returns normally, but the
    benchmark must not judge and cache it as finished, nor go on to the next world. It writes the first world,
    marked interrupted; run again, it runs only the stopped world and the report is whole."""
    import shgm_slam.bench.heldout as heldout
    import shgm_slam.bench.stopping as stopping

    monkeypatch.setattr(heldout, "ensure_world", lambda *args, **kwargs: tiny_scenario)
    real_run, runs = stopping.run_slam, []

    def stopped_in_second_run(robots, cfg, out, **kwargs):
        summary = real_run(robots, cfg, out, **kwargs)
        runs.append(Path(out).name)
        summary.interrupted = summary.interrupted or len(runs) == 2  # as if the stop landed in that run
        return summary

    monkeypatch.setattr(stopping, "run_slam", stopped_in_second_run)
    options = heldout.HeldoutOptions(scenarios=("airsim-like",), seeds=(1, 2, 3), modes=(InputMode.FILES,),
                                     max_frames=12, cache=tmp_path / "cache")  # fmt: skip
    out = tmp_path / "out"
    first = heldout.run_heldout_benchmark(out, options)
    assert first["interrupted"] and [r["seed"] for r in first["runs"]] == [1]
    assert runs == ["airsim-like-s1-files", "airsim-like-s2-files"]  # seed 3 never started
    assert not (out / "runs" / "airsim-like-s2-files" / "verdicts.json").exists()
    cached = json.loads((out / "runs" / "airsim-like-s1-files" / "verdicts.json").read_text())
    assert cached["asked"] == heldout.run_options(options)  # what a resume checks
    assert (out / "heldout.md").read_text().startswith("**Interrupted**")
    assert json.loads((out / "heldout.json").read_text())["interrupted"] is True

    again = heldout.run_heldout_benchmark(out, options)
    assert not again["interrupted"] and [r["seed"] for r in again["runs"]] == [1, 2, 3]
    assert runs[2:] == ["airsim-like-s2-files", "airsim-like-s3-files"]  # seed 1 was not run again
    assert not (out / "heldout.md").read_text().startswith("**Interrupted**")


def test_a_benchmark_stopped_before_any_world_finished_says_so(tiny_scenario, tmp_path, monkeypatch):
    import shgm_slam.bench.heldout as heldout
    import shgm_slam.bench.stopping as stopping

    monkeypatch.setattr(heldout, "ensure_world", lambda *args, **kwargs: tiny_scenario)

    def stopped(robots, cfg, out, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(stopping, "run_slam", stopped)
    options = heldout.HeldoutOptions(scenarios=("airsim-like",), seeds=(1,), modes=(InputMode.FILES,),
                                     max_frames=12, cache=tmp_path / "cache")  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        heldout.run_heldout_benchmark(tmp_path / "out", options)


def test_a_replay_of_runs_the_recorded_benchmark_does_not_hold_says_what_it_holds(tiny_scenario, tmp_path, monkeypatch):
    """``--replay-from`` with other seeds than the recorded benchmark's said "<folder> holds no journal.bin" of a
    folder that does not exist."""
    import shgm_slam.bench.heldout as heldout

    monkeypatch.setattr(heldout, "ensure_world", lambda *args, **kwargs: tiny_scenario)
    recorded = tmp_path / "recorded"
    for name in ("airsim-like-s10-files", "airsim-like-s11-files"):
        (recorded / "runs" / name).mkdir(parents=True)
    options = heldout.HeldoutOptions(scenarios=("airsim-like",), seeds=(12,), modes=(InputMode.FILES,),
                                     cache=tmp_path / "cache", replay_from=recorded)  # fmt: skip
    with pytest.raises(DataError, match=r"has no run airsim-like-s12-files \(its runs/ holds 2: airsim-like-s10-files, "
                                        r"airsim-like-s11-files\); give the recorded benchmark's --seeds"):
        heldout.run_heldout_benchmark(tmp_path / "out", options)


def test_kitti_paths_worlds_without_kitti_poses_are_refused_before_any_world_runs(tmp_path, monkeypatch):
    """Without KITTI ground truth the benchmark ran every other world (30 runs, 40 minutes) and then stopped at the
    first kitti-paths world with an error that named a ``--kitti-root`` option the command did not have."""
    import shgm_slam.bench.heldout as heldout

    ran = []
    monkeypatch.setattr(heldout, "ensure_world", lambda *args, **kwargs: ran.append(args) or tmp_path)
    options = heldout.HeldoutOptions(scenarios=("airsim-like", "kitti-paths"), seeds=(1,), modes=(InputMode.FILES,),
                                     cache=tmp_path / "cache", kitti_root=tmp_path / "no-kitti")  # fmt: skip
    with pytest.raises(DataError, match=r"needs KITTI ground truth .*no-kitti/poses.*--kitti-root"):
        heldout.run_heldout_benchmark(tmp_path / "out", options)
    assert ran == []
    (tmp_path / "kitti" / "poses").mkdir(parents=True)
    for seq in heldout.KITTI_DRIVE_PAIRS[1]:
        (tmp_path / "kitti" / "poses" / f"{seq.split(':')[0]}.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    heldout.check_kitti_poses(replace(options, kitti_root=tmp_path / "kitti"))  # seed 1's drives are there


def test_a_run_that_lost_a_robot_s_front_end_is_refused_not_judged(tiny_scenario, tmp_path, monkeypatch):
    """A front end that failed in its worker process (a bug, or code changed under a running benchmark) skipped all
    of its robot's frames, and the benchmark judged the run: 10 robot-worlds "not placed", the reference "not
    within", a table that measured the fault instead of the system. Now the benchmark stops naming it, caches
    nothing for that run, and the same command resumes once the fault is fixed."""
    import shgm_slam.bench.heldout as heldout
    import shgm_slam.bench.stopping as stopping
    from shgm_slam.errors import RunError

    monkeypatch.setattr(heldout, "ensure_world", lambda *args, **kwargs: tiny_scenario)
    real_run = stopping.run_slam

    def lost_car2(robots, cfg, out, **kwargs):
        summary = real_run(robots, cfg, out, **kwargs)
        summary.robots[1].front_end_lost = "at frame 0: car2: its front end failed in its worker process (a bug)"
        return summary

    monkeypatch.setattr(stopping, "run_slam", lost_car2)
    options = heldout.HeldoutOptions(scenarios=("airsim-like",), seeds=(1,), modes=(InputMode.FILES,),
                                     max_frames=12, cache=tmp_path / "cache")  # fmt: skip
    with pytest.raises(RunError, match=r"airsim-like-s1-files: a robot's front end was lost at frame 0: car2: .*"
                                       r"not judged.*resume"):  # fmt: skip
        heldout.run_heldout_benchmark(tmp_path / "out", options)
    assert not (tmp_path / "out" / "runs" / "airsim-like-s1-files" / "verdicts.json").exists()
