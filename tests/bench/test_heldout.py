"""The held-out benchmark's judge: odometry breaks from ground truth, robot verdicts, summaries."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.bench.heldout import (
    REPORT_SEEDS,
    TUNING_SEEDS,
    InputMode,
    Outcome,
    heldout_markdown,
    judge_run,
    odometry_breaks,
    summarize,
    world_folder,
)
from shgm_slam.data import open_sequence
from shgm_slam.geometry import se3
from shgm_slam.io.trajectories import read_tum, write_tum


def _drive(n: int = 100, speed_mps: float = 10.0, fps: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) times and (N, 4, 4) poses of a car driving a gentle curve."""
    t = np.arange(n) / fps
    yaw = 0.002 * np.arange(n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = np.stack([se3.rot_y(a) for a in yaw])
    poses[:, 2, 3] = speed_mps * t
    poses[:, 0, 3] = 0.5 * np.sin(t)
    return t, poses


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


def test_perfect_odometry_has_no_breaks():
    t, gt = _drive()
    # the odometry frame differs from the world frame by a rigid transform: relative motion is what counts
    T = se3.make_pose(se3.rot_y(0.7), np.array([5.0, 1.0, -3.0]))
    assert odometry_breaks(t, T @ gt, gt) == 0


def test_a_jump_is_one_break_and_a_reported_segment_start_excuses_it():
    t, gt = _drive()
    est = gt.copy()
    est[60:, 2, 3] += 40.0  # a 40 m jump between frames 59 and 60
    assert odometry_breaks(t, est, gt) == 1
    assert odometry_breaks(t, est, gt, boundaries={60}) == 0


def test_a_wrong_turn_is_a_break():
    t, gt = _drive()
    est = gt.copy()
    R = se3.make_pose(se3.rot_y(np.radians(30.0)), np.zeros(3))
    est[40:] = gt[40] @ R @ se3.inverse(gt[40]) @ gt[40:]
    assert odometry_breaks(t, est, gt) >= 1


def test_missing_frames_are_not_breaks():
    t, gt = _drive()
    est = gt.copy()
    est[30:45] = np.nan
    assert odometry_breaks(t, est, gt) == 0


def _fake_run(world: Path, run_dir: Path, offsets_m: dict[str, float | None]) -> dict:
    """Write fused/odometry TUM files as a run would: GT in the shared frame shifted by an offset."""
    run_dir.mkdir(parents=True, exist_ok=True)
    robots = json.loads((world / "scenario.json").read_text())["robots"]
    ref = open_sequence(str(world / robots[0]["name"])).gt_poses[0]
    reports = []
    for r in robots:
        seq = open_sequence(str(world / r["name"]))
        t = np.asarray(seq.timestamps_s)
        gt = se3.inverse(ref) @ seq.gt_poses
        write_tum(run_dir / f"{r['name']}_odometry_tum.txt", t, se3.inverse(gt[0]) @ gt)
        off = offsets_m.get(r["name"])
        if off is not None:
            fused = gt.copy()
            fused[:, 0, 3] += off
            write_tum(run_dir / f"{r['name']}_fused_tum.txt", t, fused)
        reports.append({"name": r["name"], "odometry_failures": 0, "path_length_m": 100.0})
    return {"robots": reports}


def test_judge_places_right_wrong_and_not_placed(tiny_scenario, tmp_path):
    metrics = _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": 30.0, "uav": None})
    v = {x.robot: x for x in judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES,
                                       "airsim-like", 0, metrics)}
    assert v["car1"].reference and v["car1"].outcome == Outcome.RIGHT.value
    assert v["car1"].ate_fused_m == pytest.approx(0.0, abs=1e-3)
    assert v["car2"].outcome == Outcome.WRONG.value
    assert v["car2"].ate_fused_m == pytest.approx(30.0, abs=0.01)
    assert v["uav"].outcome == Outcome.NOT_PLACED.value and v["uav"].placed_fraction == 0.0
    assert all(x.odometry_breaks == 0 for x in v.values())
    # RGB tolerates 5 m: 3 m off is right there, wrong from files
    metrics = _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": 3.0, "uav": 3.0})
    files = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES, "airsim-like", 0, metrics)
    rgb = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.RGB, "airsim-like", 0, metrics)
    assert [x.outcome for x in files] == ["right", "wrong", "wrong"]
    assert [x.outcome for x in rgb] == ["right", "right", "right"]


def test_a_false_merge_the_run_flagged_as_provisional_is_counted_and_marked(tiny_scenario, tmp_path):
    metrics = _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": 300.0, "uav": 250.0})
    metrics["robots"][1]["provisional"] = True  # the run said car2's place was unconfirmed
    v = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES, "airsim-like", 0, metrics)
    assert [x.outcome for x in v] == ["right", "wrong", "wrong"]
    assert [x.provisional for x in v] == [False, True, False]
    assert any("provisional" in n for n in v[1].notes) and not any("provisional" in n for n in v[2].notes)
    s = summarize([vars(x) for x in v])["files"]["all"]
    assert (s["wrong"], s["wrong_gross"], s["wrong_gross_provisional"]) == (2, 2, 1)
    md = heldout_markdown({"options": {"seeds": [0], "resolution": [320, 96], "tuning_seeds": [10, 19],
                                       "placed_right_m": {"files": 2.0}}, "summary": summarize([vars(x) for x in v])})
    assert "| 2 | 2 (1 provisional) |" in md


def test_a_robot_left_out_for_too_few_independent_matches_is_counted_as_waiting(tiny_scenario, tmp_path):
    metrics = _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": None, "uav": None})
    (tmp_path / "server.json").write_text(json.dumps({"robots": {
        "car1": {"waiting": []}, "car2": {"waiting": ["car2 is not placed in the shared frame: ..."]},
        "uav": {"waiting": []}}}))  # fmt: skip
    v = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES, "airsim-like", 0, metrics)
    assert [x.outcome for x in v] == ["right", "not placed", "not placed"]
    assert [x.waiting for x in v] == [False, True, False]
    assert any("independent" in n for n in v[1].notes) and not v[2].notes
    s = summarize([vars(x) for x in v])["files"]["all"]
    assert (s["not_placed"], s["not_placed_waiting"]) == (2, 1)
    md = heldout_markdown({"options": {"seeds": [0], "resolution": [320, 96], "tuning_seeds": [10, 19],
                                       "placed_right_m": {"files": 2.0}}, "summary": summarize([vars(x) for x in v])})
    assert "| 2 (1 waiting) |" in md


def test_a_gauge_error_of_the_shared_frame_is_not_a_placement_error(tiny_scenario, tmp_path):
    _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": 0.0, "uav": 0.0})
    up = se3.inverse(open_sequence(str(tiny_scenario / "car1")).gt_poses[0])[:3, :3] @ np.array([0.0, 0.0, 1.0])
    T = se3.make_pose(se3.so3_exp(up * np.radians(3.0)), np.array([1.0, -2.0, 0.5]))  # the whole fleet turned
    for name in ("car1", "car2", "uav"):
        t, poses = read_tum(tmp_path / f"{name}_fused_tum.txt")
        write_tum(tmp_path / f"{name}_fused_tum.txt", t, T @ poses)
    metrics = {"robots": [{"name": n} for n in ("car1", "car2", "uav")]}
    v = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES, "airsim-like", 0, metrics)
    assert [x.outcome for x in v] == ["right"] * 3
    assert all(x.ate_fused_m < 1e-3 for x in v)
    assert max(x.ate_fused_raw_m for x in v) > 2.0  # the unaligned error sees the turn
    rows = [vars(x) for x in v]
    s = summarize(rows)["files"]["all"]
    assert s["placed_right"] == 2 and s["fused_within"] == 2 and s["fused_within_unaligned"] < 2


def test_own_drift_is_not_misplacement(tiny_scenario, tmp_path):
    """A wobble no rigid transform removes (odometry drift) leaves the placement right, the fused ATE not."""
    _fake_run(tiny_scenario, tmp_path, {"car1": 0.0, "car2": 0.0, "uav": 0.0})
    t, poses = read_tum(tmp_path / "car2_fused_tum.txt")
    wobble = 4.0 * np.sin(np.linspace(0.0, 6.0 * np.pi, len(t)))
    poses[:, 0, 3] += wobble
    poses[:, 2, 3] -= wobble
    write_tum(tmp_path / "car2_fused_tum.txt", t, poses)
    metrics = {"robots": [{"name": n} for n in ("car1", "car2", "uav")]}
    v = judge_run(tmp_path, tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES, "airsim-like", 0, metrics)
    assert v[1].outcome == Outcome.RIGHT.value
    assert v[1].placement_error_m < 1.0 < 2.0 < v[1].ate_fused_m


def test_a_robot_that_shares_no_view_is_right_only_when_left_apart(tiny_scenario, tmp_path):
    world = tmp_path / "world"
    world.mkdir()
    for name in ("car1", "car2", "uav"):
        (world / name).symlink_to(tiny_scenario / name)
    scen = json.loads((tiny_scenario / "scenario.json").read_text())
    scen["overlap"]["shared_view_m"] = {"car1": {"car2": 0.0}, "car2": {"car1": 0.0}, "uav": {}}
    (world / "scenario.json").write_text(json.dumps(scen))
    metrics = _fake_run(world, tmp_path / "a", {"car1": 0.0, "car2": None, "uav": 0.5})
    v = judge_run(tmp_path / "a", world, ["car1", "car2", "uav"], InputMode.FILES, "disjoint", 0, metrics)
    assert [x.outcome for x in v[1:]] == ["right", "wrong"]  # car2 kept apart; the uav merged with no overlap
    rows = [vars(x) for x in v]
    s = summarize(rows)["files"]["all"]
    assert s["apart"] == 2 and s["apart_kept_apart"] == 1 and s["wrong"] == 1
    assert s["references"] == 1 and s["references_within"] == 1 and s["overlapping"] == 0
    assert "disjoint" in heldout_markdown({"options": {
        "seeds": [0], "resolution": [320, 96], "tuning_seeds": [10, 19], "placed_right_m": {"files": 2.0}},
        "summary": summarize(rows)})


def test_summary_adds_up_the_runs_judged_matches_per_scenario(tiny_scenario, tmp_path):
    metrics = _fake_run(tiny_scenario, tmp_path / "a", {"car1": 0.0, "car2": 0.5, "uav": 0.5})
    rows = [vars(x) for x in judge_run(tmp_path / "a", tiny_scenario, ["car1", "car2", "uav"], InputMode.FILES,
                                       "airsim-like", 0, metrics)]  # fmt: skip
    runs = [
        {"scenario": "airsim-like", "mode": "files", "matches": {"accepted": 7, "off": 2, "gross": 1, "worst_m": 31.0,
                                                                 "anchorings": 3, "anchorings_gross": 1,
                                                                 "anchorings_gross_confirmed": 1}},
        {"scenario": "synthia-like", "mode": "files", "matches": {"accepted": 5, "off": 0, "gross": 0, "worst_m": 1.0,
                                                                  "anchorings": 1, "anchorings_gross": 0}},
        {"scenario": "airsim-like", "mode": "rgb", "matches": {"accepted": 9, "off": 9, "gross": 9, "worst_m": 99.0}},
    ]
    s = summarize(rows, runs)["files"]
    assert (s["all"]["matches_accepted"], s["all"]["matches_off"], s["all"]["matches_gross"]) == (12, 2, 1)
    assert (s["airsim-like"]["matches_accepted"], s["airsim-like"]["matches_off"]) == (7, 2)
    options = {"seeds": [0], "resolution": [320, 96], "tuning_seeds": [10, 19], "placed_right_m": {"files": 2.0}}
    md = heldout_markdown({"options": options, "summary": summarize(rows, runs)})
    assert "| 2/12 (1) | 1/4 (1) |" in md
    runs[1]["matches"]["anchorings"] = None  # a run from before anchorings were recorded
    md = heldout_markdown({"options": options, "summary": summarize(rows, runs)})
    assert "| 2/12 (1) | ? |" in md


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
    provisional flags, waiting lines and last looks in its ``metrics.json`` are the replayed server's (the
    judge reads the flag). Recorded trusting single matches (car2 provisional after 30 frames), replayed with
    the default (two independent matches): car2 waits, and says so."""
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
    assert before["car2"]["provisional"]
    assert any(w.startswith("car2 is placed provisionally") for w in before["car2"]["warnings"])

    metrics = replay_one(recorded, InputMode.FILES, tmp_path / "replayed", ["car1", "car2"])
    car2 = next(r for r in metrics["robots"] if r["name"] == "car2")
    assert not car2["provisional"]
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
