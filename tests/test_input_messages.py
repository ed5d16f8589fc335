"""What the command line and the Python API say about inputs an audit found misread: an unreadable config, a
Ctrl-C while a config is serialized, a scenario simulated into another command's results, a pose file given for
its sequence folder (and a folder named poses.txt), the eval caption with fewer than two robots placed, options
not named in their messages, and a --kitti-root nothing reads."""

from __future__ import annotations

import math
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest
from rich.console import Console
from typer.testing import CliRunner

import shgm_slam
from shgm_slam.cli import app
from shgm_slam.errors import ConfigError, DataError, SimulationError

runner = CliRunner()


def _invoke(args: list[str]) -> tuple[int, str]:
    """Exit code and output (whitespace folded) of one command line; no traceback."""
    res = runner.invoke(app, args, env={"COLUMNS": "250"})
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    return res.exit_code, " ".join(res.output.split())


# --- 1. config files that cannot be read -------------------------------------------------------------------


@pytest.mark.skipif(not Path("/proc/self/mem").exists(), reason="needs Linux's /proc/self/mem")
def test_a_config_file_that_cannot_be_read_names_the_file_and_the_os_error():
    """Reading /proc/self/mem fails with EIO: an OSError traceback from ``dump-config --config`` before."""
    with pytest.raises(ConfigError, match=r"config file /proc/self/mem cannot be read: Input/output error"):
        shgm_slam.load_config("/proc/self/mem")
    code, out = _invoke(["dump-config", "--config", "/proc/self/mem"])
    assert code == 2 and "error: config file /proc/self/mem cannot be read: Input/output error" in out


def test_a_config_file_without_permission_names_the_os_error(tmp_path, monkeypatch):
    path = tmp_path / "config.yaml"
    path.write_text("matching: {}\n")

    def denied(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_text", denied)  # (chmod 000 is no refusal for root)
    with pytest.raises(ConfigError, match=r"config\.yaml cannot be read: Permission denied"):
        shgm_slam.load_config(path)


# --- 2. Ctrl-C while the config digest is serialized -------------------------------------------------------


def test_a_ctrl_c_while_the_config_digest_is_serialized_is_a_keyboard_interrupt(monkeypatch, python_ctrl_c):
    """pydantic's JSON serializer wrapped the KeyboardInterrupt that a Ctrl-C raised in an enum's ``value``
    it read: ``PydanticSerializationError: ... KeyboardInterrupt`` (a traceback) instead of "interrupted"."""
    import enum

    from shgm_slam.config import DescriptorKind, ShgmConfig
    from shgm_slam.server.snapshot import config_digest

    cfg = ShgmConfig()
    expected = config_digest(cfg)
    value = enum.Enum.__dict__["value"]
    signalled = []

    def ctrl_c_then_value(member):
        if not signalled:  # the Ctrl-C lands once, as the serializer reads this value
            signalled.append(True)
            signal.raise_signal(signal.SIGINT)
        return value.fget(member)

    monkeypatch.setattr(DescriptorKind, "value", property(ctrl_c_then_value), raising=False)
    with pytest.raises(KeyboardInterrupt):
        config_digest(cfg)
    assert signalled
    monkeypatch.undo()
    assert config_digest(cfg) == expected  # the digest itself is as before (snapshots stay usable)


def test_the_config_digest_is_the_sha256_of_the_configs_json_without_the_server_stage():
    import hashlib

    from shgm_slam.config import ShgmConfig, config_from_mapping
    from shgm_slam.server.snapshot import config_digest

    cfg = config_from_mapping({"matching": {"min_inliers": 7}, "robots": {"uav": {"odometry": {
        "voxel_size_m": 0.3}}}}, "test")  # fmt: skip
    for c in (ShgmConfig(), cfg):
        text = c.model_dump_json(exclude={"server"})  # what snapshots written before were keyed by
        assert config_digest(c) == hashlib.sha256(text.encode()).hexdigest()


# --- 3. simulate into a folder of another command's results ------------------------------------------------


@pytest.fixture
def simulate_called(monkeypatch):
    """``sim.simulate.simulate`` replaced: it raises a SimulationError saying it was called (nothing rendered)."""
    import importlib

    simulate_module = importlib.import_module("shgm_slam.sim.simulate")  # (shgm_slam.sim.simulate: the function)

    def called(*_args, **_kwargs):
        raise SimulationError("simulate was called")

    monkeypatch.setattr(simulate_module, "simulate", called)


@pytest.mark.parametrize(("files", "says"), [
    (("sparse.json", "sparse.md"), "holds a benchmark's report (sparse.json, sparse.md)"),
    (("heldout.json", "heldout.md"), "holds a benchmark's report (heldout.json, heldout.md)"),
    (("metrics.json", "car1_fused_tum.txt"),
     "holds a run's or map server's results (car1_fused_tum.txt, metrics.json)"),
    (("calib.txt", "times.txt"), "holds a sequence (calib.txt, times.txt)"),
])  # fmt: skip
def test_simulate_refuses_a_folder_of_another_commands_results(tmp_path, simulate_called, files, says):
    """``simulate -o results/bench_sparse`` wrote a scenario among a benchmark's results, quietly."""
    out = tmp_path / "results"
    out.mkdir()
    for name in files:
        (out / name).write_text("{}\n")
    code, text = _invoke(["simulate", "-s", "synthia-like", "-o", str(out)])
    assert code == 2, text
    assert f"--out {out} {says}, not a scenario; give another folder for the scenario" in text
    assert "simulate was called" not in text and sorted(p.name for p in out.iterdir()) == sorted(files)


def test_simulate_still_judges_a_folder_of_a_scenario_or_of_other_files_itself(tmp_path, simulate_called):
    scenario = tmp_path / "scenario"
    scenario.mkdir()
    (scenario / "scenario.json").write_text("{}\n")
    (scenario / "world.json").write_text("{}\n")
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "README.md").write_text("my notes\n")
    (notes / "settings.json").write_text("{}\n")  # a JSON without its markdown is no benchmark report
    (notes / "config.yaml").write_text("matching: {}\n")  # a user's own config is no run's results
    for out in (scenario, notes, tmp_path / "new"):
        code, text = _invoke(["simulate", "-s", "synthia-like", "-o", str(out)])
        assert code == 2 and "simulate was called" in text, text


# --- 4. a pose file given for its sequence folder; a folder named poses.txt --------------------------------


def _kitti_sequence(root: Path, n: int = 3) -> Path:
    """A tiny KITTI sequence: image_2 (8x6), calib.txt, times.txt and poses.txt."""
    (root / "image_2").mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_2" / f"{i:06d}.png"), np.full((6, 8, 3), 50, np.uint8))
    P2 = [[5.0, 0, 4, 0], [0, 5.0, 3, 0], [0, 0, 1, 0]]
    (root / "calib.txt").write_text("P2: " + " ".join(str(v) for row in P2 for v in row) + "\n")
    (root / "times.txt").write_text("".join(f"{0.1 * i}\n" for i in range(n)))
    (root / "poses.txt").write_text("".join(f"1 0 0 {0.5 * i} 0 1 0 0 0 0 1 0\n" for i in range(n)))
    return root


def test_evaluate_given_a_pose_file_says_it_is_a_file_not_its_sequence_folder(tmp_path):
    """``evaluate(results, {"car1": ".../poses.txt"})`` said "sequence folder .../poses.txt does not exist"."""
    poses = _kitti_sequence(tmp_path / "car1") / "poses.txt"
    for spec in (str(poses), poses, f"{poses}:0-2"):
        with pytest.raises(DataError) as info:
            shgm_slam.evaluate(tmp_path, {"car1": spec})
        text = str(info.value)
        assert text.startswith(f"sequences['car1']: {poses} is a file; give the robot's sequence folder"), text
        assert "does not exist" not in text
    with pytest.raises(DataError, match=r"is a file; give the robot's sequence folder \(its images, times\.txt"):
        shgm_slam.open_sequence(poses)
    with pytest.raises(DataError, match=r"sequences\['car1'\]: sequence folder .*nowhere does not exist"):
        shgm_slam.evaluate(tmp_path, {"car1": tmp_path / "nowhere"})  # a missing folder: said as before


def test_a_sequence_path_the_os_cannot_look_at_is_a_data_error(tmp_path):
    """A name longer than the file system allows: ``open_sequence``, ``evaluate`` and ``run --robot`` raised Python's
    OSError (File name too long), a traceback, from the check of the sequence folder."""
    too_long = tmp_path / ("a" * 300)
    for spec in (too_long, f"{too_long}:0-5"):
        with pytest.raises(DataError, match=r"sequence folder .* cannot be looked at \(File name too long\)"):
            shgm_slam.open_sequence(spec)
    with pytest.raises(DataError, match=r"sequences\['car1'\]: sequence folder .* cannot be looked at"):
        shgm_slam.evaluate(tmp_path, {"car1": too_long})
    code, out = _invoke(["run", "--robot", f"car1={too_long}", "--out", str(tmp_path / "out")])
    assert code == 2 and "cannot be looked at (File name too long)" in out, out


def test_a_folder_named_poses_txt_is_said_to_be_where_the_pose_file_should_be(tmp_path):
    """It read as a sequence without ground truth ("has no ground truth (poses.txt ...)")."""
    root = _kitti_sequence(tmp_path / "car1")
    assert shgm_slam.open_sequence(root).gt_poses is not None  # the file: read as before
    (root / "poses.txt").unlink()
    assert shgm_slam.open_sequence(root).gt_poses is None  # none at all: a sequence without ground truth
    (root / "poses.txt").mkdir()
    with pytest.raises(DataError, match=r"car1/poses\.txt is a folder where the sequence's pose file should be"):
        shgm_slam.open_sequence(root)
    with pytest.raises(DataError, match=r"poses\.txt is a folder where the sequence's pose file should be"):
        shgm_slam.evaluate(tmp_path, {"car1": root})


# --- 5. the eval caption with fewer than two robots placed -------------------------------------------------


def _caption(placed: int) -> str:
    """The ``eval`` table's text for a result with ``placed`` of two robots placed (in the joint fit)."""
    from shgm_slam.cli.render import eval_table
    from shgm_slam.evaluation import EvaluationResult, RobotEvaluation

    robots = [RobotEvaluation(f"car{k}", 10 if k <= placed else 0, 10 if k <= placed else 0, 0.5, 0.2, 0.9,
                              ate_fused_joint_m=0.2 if placed == 1 else 0.3)
              for k in (1, 2)]  # fmt: skip
    result = EvaluationResult(Path("results"), "car1", "results folder", robots, joint_robots=placed,
                              ate_joint_m=0.3 if placed > 1 else (0.2 if placed else math.nan))  # fmt: skip
    console = Console(width=200, record=True)
    console.print(eval_table(result))
    return " ".join(console.export_text().split())


def test_the_eval_caption_leaves_the_joint_fit_out_without_two_placed_robots():
    """With none placed it read "joint = one SE(3) fit of all 0 placed robots together (- m over all their poses)";
    with one, "all 1 placed robots together"."""
    none, one, two = _caption(0), _caption(1), _caption(2)
    assert "ground truth from the results folder; aligned = SE(3)-aligned per robot" in none
    assert "joint =" not in none and "0 placed robots" not in none
    assert ("joint = aligned (one placed robot has ground truth in the shared frame: one SE(3) fit of it alone is "
            "its own alignment)") in one  # fmt: skip
    assert "1 placed robots" not in one
    assert ("joint = one SE(3) fit of the 2 placed robots with ground truth in the shared frame together (0.30 m over "
            "all their poses)") in two  # fmt: skip


def test_the_eval_caption_does_not_count_placed_robots_without_ground_truth_out():
    """Both robots placed, car2 without ground truth (its sequence has none, or the run's ground truths share no
    frame): the joint fit holds car1 alone, and the caption said "one robot placed"."""
    from shgm_slam.cli.render import eval_table
    from shgm_slam.evaluation import EvaluationResult, RobotEvaluation

    robots = [RobotEvaluation("car1", 10, 10, 0.5, 0.2, 0.9, ate_fused_joint_m=0.2),
              RobotEvaluation("car2", 10, 0, note="no ground truth given")]  # fmt: skip
    result = EvaluationResult(Path("results"), "car1", "results folder", robots, joint_robots=1, ate_joint_m=0.2)
    console = Console(width=200, record=True)
    console.print(eval_table(result))
    text = " ".join(console.export_text().split())
    assert "robot placed" not in text and "one placed robot has ground truth in the shared frame" in text


def test_the_joint_fit_of_one_robot_is_its_own_se3_aligned_ate():
    """What the caption says of one placed robot."""
    from shgm_slam.geometry import se3
    from shgm_slam.metrics import AlignMode, ate, joint_ate

    rng = np.random.default_rng(3)
    gt = np.tile(np.eye(4), (30, 1, 1))
    gt[:, :3, 3] = np.cumsum(rng.normal(size=(30, 3)), axis=0)
    est = gt.copy()
    est[:, :3, 3] += rng.normal(scale=0.3, size=(30, 3))
    est = se3.make_pose(se3.so3_exp(np.array([0.05, 0.1, -0.3])), np.array([0.1, -0.2, 0.3])) @ est
    per_robot, together = joint_ate([gt], [est])
    aligned = ate(gt, est, align=AlignMode.SE3)
    assert per_robot[0].rmse == pytest.approx(aligned.rmse, rel=1e-6)
    assert together.rmse == pytest.approx(aligned.rmse, rel=1e-6)


# --- 6. messages that name their option --------------------------------------------------------------------


@pytest.mark.parametrize(("value", "says"), [
    ("abc", "--resolution 'abc': write the image size as WIDTHxHEIGHT pixels, e.g. 640x192"),
    ("4x4", "--resolution 4x4 is out of range: give WIDTHxHEIGHT with 8..8192 pixels per side, e.g. 640x192"),
])  # fmt: skip
def test_a_bad_resolution_names_the_option(tmp_path, simulate_called, value, says):
    code, text = _invoke(["simulate", "-s", "synthia-like", "-o", str(tmp_path / "w"), "--resolution", value])
    assert code == 2 and says in text, text


def test_fleet_sizes_out_of_range_name_the_option():
    from shgm_slam.bench.robots import run_robots_benchmark

    with pytest.raises(ConfigError, match=r"--fleets 0,9,2: 0, 9 outside 1\.\.8 .*give comma-separated fleet sizes"):
        run_robots_benchmark(Path("unused"), fleets=(0, 9, 2))
    with pytest.raises(ConfigError, match=r"--fleets names no size in 1\.\.8"):
        run_robots_benchmark(Path("unused"), fleets=())


@pytest.mark.parametrize("under", [False, True])
def test_a_localization_cache_that_is_a_file_says_so(tmp_path, under):
    """``bench localization --cache afile`` rendered a scene, then said "[Errno 20] Not a directory"."""
    from shgm_slam.bench.localization import BenchOptions, run_localization_benchmark

    (tmp_path / "afile").write_text("")
    cache = tmp_path / "afile" / "sub" if under else tmp_path / "afile"
    says = f"lies under {tmp_path / 'afile'}, a file" if under else "is a file"
    with pytest.raises(SimulationError, match=rf"--cache .* {says}; give a folder for the rendered keyframes"):
        run_localization_benchmark(None, BenchOptions.quick_options(cache_dir=cache))


# --- 7. a --kitti-root nothing reads -----------------------------------------------------------------------


@pytest.fixture
def heldout_called(monkeypatch):
    """``bench heldout``'s benchmark replaced by one that stops the command with a ConfigError."""
    from shgm_slam.bench import heldout

    def called(*_args, **_kwargs):
        raise ConfigError("the benchmark was called")

    monkeypatch.setattr(heldout, "run_heldout_benchmark", called)


@pytest.mark.parametrize(("scenarios", "unused"), [(["airsim-like", "disjoint"], True),
                                                   (["airsim-like", "kitti-paths"], False), ([], False)])
def test_heldout_warns_once_of_a_kitti_root_no_selected_world_reads(tmp_path, heldout_called, scenarios, unused):
    """``--kitti-root`` was ignored without a word when no kitti-paths world was selected."""
    args = ["bench", "heldout", "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"), "--seeds", "1",
            "--kitti-root", str(tmp_path / "kitti")] + [a for s in scenarios for a in ("--scenario", s)]
    code, text = _invoke(args)
    assert code == 2 and "the benchmark was called" in text, text  # a warning, not an error
    warning = f"warning: --kitti-root {tmp_path / 'kitti'} is not used: no kitti-paths world is selected (--scenario)"
    assert text.count(warning) == (1 if unused else 0), text


def test_simulate_warns_of_a_kitti_root_its_scenario_does_not_read(tmp_path, simulate_called):
    kitti = str(tmp_path / "kitti")
    code, text = _invoke(["simulate", "-s", "airsim-like", "-o", str(tmp_path / "w"), "--kitti-root", kitti])
    assert code == 2 and "simulate was called" in text, text
    assert text.count(f"warning: --kitti-root {kitti} is not used: only the kitti-paths scenario reads KITTI "
                      "poses, not airsim-like") == 1  # fmt: skip
    code, text = _invoke(["simulate", "-s", "kitti-paths", "-o", str(tmp_path / "k"), "--kitti-root", kitti])
    assert "simulate was called" in text and "warning" not in text, text
