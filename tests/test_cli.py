"""The CLI's error boundary prints user text literally: rich markup in paths and messages is not interpreted."""

from __future__ import annotations

import shutil

import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app, lit

runner = CliRunner()


@pytest.mark.parametrize("name", ["[/bad]", "[word]", "[bold red]x[/]"])
def test_markup_in_a_path_is_printed_literally(tmp_path, name):
    missing = tmp_path / name / "seq"
    res = runner.invoke(app, ["run", "--robot", f"car1={missing}", "--rerun", "off", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    assert name in res.output.replace("\n", "")


def test_lit_keeps_brackets():
    from rich.console import Console

    console = Console(record=True, width=200)
    console.print(lit("position must be three finite numbers, got [nan] [/x]"))
    assert "got [nan] [/x]" in console.export_text()


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_stop_signals_keep_the_results_like_ctrl_c(tiny_scenario, tmp_path, sig):
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out"
    robots = []
    for k in range(3):
        robots += ["--robot", f"car{k}={tiny_scenario / 'car1'}", "--robot", f"van{k}={tiny_scenario / 'car2'}"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "shgm_slam", "run", *robots, "--rerun", "off", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "COLUMNS": "200"},
    )
    deadline = time.monotonic() + 120
    while not (out / "car0_odometry_tum.txt").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(getattr(signal, sig))
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, (stdout.decode()[-1500:], stderr.decode()[-3000:])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] is True
    assert b"interrupted: results written so far are kept" in stdout
    assert (out / "car0_odometry_tum.txt").is_file()


def test_a_benchmark_stopped_by_sigterm_writes_what_it_finished(tmp_path, monkeypatch):
    """``timeout``, a job scheduler or a closed terminal stop a benchmark with SIGTERM / SIGHUP: it must stop as
    after a Ctrl-C (the seeds finished written, marked interrupted, exit 130), not die with nothing written."""
    import json
    import os
    import signal

    import shgm_slam.bench.localization_sparse as sparse

    class UnhandledError(Exception):
        pass

    def unhandled(_signum, _frame):
        raise UnhandledError("SIGTERM reached the test's handler: the command did not take it")

    real, seen = sparse._run_seed, []

    def stopped_in_second_seed(seed, *args, **kwargs):
        seen.append(seed)
        if len(seen) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(seed, *args, **kwargs)

    monkeypatch.setattr(sparse, "_run_seed", stopped_in_second_seed)
    previous = signal.signal(signal.SIGTERM, unhandled)
    try:
        res = runner.invoke(app, ["bench", "sparse", "--seeds", "10-12", "--pairs", "1", "--no-full-rotation",
                                  "-o", str(tmp_path / "o")])  # fmt: skip
        assert signal.getsignal(signal.SIGTERM) is unhandled  # the command put the handler back
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert res.exit_code == 130 and not isinstance(res.exception, UnhandledError), res.output
    assert seen == [10, 11]
    written = json.loads((tmp_path / "o" / "sparse.json").read_text())
    assert written["interrupted"] is True and written["seeds_done"] == [10]


def _summary(names, failures=0):
    from types import SimpleNamespace

    robots = [
        SimpleNamespace(name=n, frames=4541, keyframes=1520, nodes=12345, odometry_failures=failures, localized=k != 1,
           segments=failures + 1, segments_placed=failures, path_length_m=3724.4, ate_odometry_m=float("nan"),
           ate_fused_m=1234.56, ate_odometry_aligned_m=12.345, ate_fused_aligned_m=56.78, failure_reasons=[],
           provisional=k == 2)
        for k, n in enumerate(names)
    ]  # fmt: skip
    return SimpleNamespace(robots=robots, matches_tried=1, closures_accepted=1, closures_rejected=0,
                           timings_ms={"odometry": 1.0}, per_keyframe_ms=2.0, skipped_reasons=[], interrupted=False,
                           out_dir="results/x")  # fmt: skip


@pytest.mark.parametrize("failures", [0, 12])
def test_summary_table_fits_80_columns_without_cutting(failures):
    from rich.console import Console

    from shgm_slam.cli import summary_table

    console = Console(width=80, record=True, color_system=None)
    console.print(summary_table(_summary(["car1", "kitti08a", "uav"], failures)))
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    for word in ("robot", "frames", "kf", "nodes", "odo", "fail", "fused", "path", "ATE", "aligned", "odo/fused"):
        assert word in text
    for value in ("kitti08a", "4541", "1520", "12345", "3724", "1235", "12.35/56.78", "-"):
        assert value in text
    if failures:
        assert f"{failures}/{failures + 1}" in text
    uav_row = next(line for line in text.splitlines() if line.strip().startswith("uav"))
    assert "prov" in uav_row and "prov" in text.split("ATE:")[1]  # the provisional robot, explained in the caption
    assert not any("prov" in line for line in text.splitlines() if line.strip().startswith(("car1", "kitti08a")))


def test_summary_table_folds_long_robot_names_instead_of_cutting():
    from rich.console import Console

    from shgm_slam.cli import summary_table

    name = "a_very_long_robot_name_of_32_chr"
    console = Console(width=80, record=True, color_system=None)
    console.print(summary_table(_summary([name])))
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    assert "".join(line.split()[0] for line in text.splitlines() if line.strip() and line.split()[0] in name)


@pytest.mark.parametrize("command", [["run"], ["graph"], ["perceive"], ["eval"], ["robot"]])
def test_frame_range_semantics_in_help(command):
    import re

    res = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    text = re.sub(r"[\s│]+", " ", res.output)
    assert "half-open" in text or "start..end-1" in text


def test_check_model_writes_a_preview_only_when_asked(tmp_path, monkeypatch):
    from pathlib import Path

    model = Path(__file__).resolve().parents[1] / "models" / "demo_seg.onnx"
    if not model.is_file():
        pytest.skip("demo models are absent")
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(app, ["check-model", str(model), "--runs", "1", "--threads", "1"])
    assert res.exit_code == 0, res.output
    assert not list(tmp_path.rglob("*.png")) and "preview" not in res.output
    res = runner.invoke(app, ["check-model", str(model), "--runs", "1", "--threads", "1", "--preview", "p.png"])
    assert res.exit_code == 0 and (tmp_path / "p.png").is_file()
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| `shgm-slam check-model"))
    assert "--preview" in row  # the README says a preview needs --preview


def _commands(group, path=()):
    from typer.core import TyperGroup

    for name, cmd in group.commands.items():
        if isinstance(cmd, TyperGroup):
            yield from _commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def test_every_help_text_is_shown_whole():
    """Help texts are printed as written: no ``[default: …]`` or ``[all]`` swallowed as rich markup."""
    import re

    import typer

    def flat(text: str) -> str:
        return re.sub(r"[\s│]+", " ", text)

    for path, cmd in _commands(typer.main.get_command(app)):
        res = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "250"})
        assert res.exit_code == 0, (path, res.output)
        shown = flat(res.output)
        assert flat(cmd.help or "") in shown, (path, cmd.help)
        for param in cmd.params:
            if getattr(param, "help", None):
                assert flat(param.help) in shown, (path, param.name, param.help)
            if isinstance(getattr(param, "show_default", None), str):
                assert f"[default: ({param.show_default})]" in shown, (path, param.name)


def test_demo_help_names_both_default_folders():
    res = runner.invoke(app, ["demo", "--help"], env={"COLUMNS": "250"})
    assert "results/demo;" in res.output and "results/demo-rgb" in res.output


def test_eval_table_fits_80_columns_without_cutting(monkeypatch):
    """Long robot names fold, numbers stay whole, at 80 columns (the table used to cut names with '…')."""
    from types import SimpleNamespace

    import shgm_slam.evaluation as evaluation

    name = "a_very_long_robot_name_of_32_chr"
    note = "provisional: no independent graph match confirms its place; 3 fused pose(s) have no ground truth"
    robots = [evaluation.RobotEvaluation(name, 4541, 4541, 1234.56, 12.345, 2345.6, note=note, provisional=True),
              evaluation.RobotEvaluation("car1", 4541, 4540, 0.39, 0.13, 0.67, ate_fused_joint_m=0.21),
              evaluation.RobotEvaluation("uav", 0, 0, note="not placed (no fused trajectory)")]  # fmt: skip
    robots[0].ate_fused_joint_m = 987.65
    result = SimpleNamespace(robots=robots, reference_robot="car1", gt_source="results folder", gt_files_written=[],
                             joint_robots=2, ate_joint_m=1.5, interrupted=False)  # fmt: skip
    monkeypatch.setattr(evaluation, "evaluate_results", lambda *a, **k: result)
    res = runner.invoke(app, ["eval", "anywhere"], env={"COLUMNS": "80"})
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert "…" not in res.output and max(map(len, lines)) <= 80
    assert name in "".join(line.split()[0] for line in lines if line.strip() and line.split()[0] in name)
    for value in ("4541/4541", "1235", "12.35", "2346", "988", "4540/4541", "0.39", "0.13", "0.67", "0.21", "aligned",
                  "joint", "1.50 m"):
        assert value in res.output
    assert "not placed (no fused trajectory)" in " ".join(res.output.split())


def test_bench_reports_fit_80_columns_on_a_terminal():
    """A benchmark's markdown table wider than the terminal is shown as a folding table: nothing cut."""
    from rich.console import Console

    from shgm_slam.cli import markdown_tables

    head = ["recovered folder", "journal records", "from snapshot", "replayed", "snapshot MB", "s with snapshots",
            "s journal only", "speed-up", "server → robots KB (corrections + status)"]  # fmt: skip
    row = ["at the kill", "300", "200", "100", "1.23", "2.0", "10.0", "5.0x", "5 + 0"]
    md = "\n".join(["intro line", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                    "| " + " | ".join(row) + " |", "", "| a | b |", "|---|---:|", "| 1 | 2 |"])  # fmt: skip
    console = Console(width=80, record=True, color_system=None)
    for item in markdown_tables(md, 80):
        console.print(item)
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80
    assert "intro line" in text and "| a | b |" in text  # narrow tables and text stay markdown
    for cell in ["300", "200", "100", "1.23", "2.0", "10.0", "5.0x", "5 + 0"]:
        assert cell in text, cell  # numbers stay whole; long header words fold only when they must


def test_a_refused_run_leaves_nothing_in_its_out_folder(tmp_path):
    """A run refused for its config, a model or its poses file exits 2 before --out gets a file: it used to
    leave <robot>_gt_*.txt and run.rrd there, so the corrected run was told to pass --overwrite."""
    from tests.data.conftest import make_frames, write_frames

    seq = write_frames(tmp_path / "seq", make_frames(6))
    ranges = tmp_path / "ranges.yaml"
    ranges.write_text("odometry:\n  min_range_m: 50\n  max_range_m: 10\n")
    out = tmp_path / "out"
    refused = [["--config", str(ranges)], ["--depth-model", str(tmp_path / "missing.onnx")],
               ["--odometry", str(tmp_path / "{robot}_poses.txt")], ["--rerun", "connect", "--rerun-url", "nope"]]
    for args in refused:
        res = CliRunner().invoke(app, ["run", "--robot", f"a={seq}", "--out", str(out), *args])
        assert res.exit_code == 2 and "error:" in res.output, (args, res.output)
        assert not out.exists() or not any(out.iterdir()), (args, sorted(p.name for p in out.iterdir()))
    res = CliRunner().invoke(app, ["run", "--robot", f"a={seq}", "--out", str(out), "--rerun", "off"])
    assert res.exit_code == 0, res.output


def test_graph_refuses_to_write_into_its_own_sequence(tiny_scenario, tmp_path):
    """`graph -o SEQ/poses.txt` overwrote the poses the sequence is read from."""
    seq = tmp_path / "car1"
    shutil.copytree(tiny_scenario / "car1", seq)
    before = (seq / "poses.txt").read_bytes()
    res = runner.invoke(app, ["graph", f"{seq}:0-20", "-o", str(seq / "poses.txt")], env={"COLUMNS": "200"})
    assert res.exit_code == 2
    assert "is in the sequence folder" in res.output
    assert (seq / "poses.txt").read_bytes() == before


def test_bench_out_that_is_a_file_is_refused_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    for bench in (["sparse", "--seeds", "1"], ["table3"], ["scale"]):
        res = runner.invoke(app, ["bench", *bench, "-o", str(afile)], env={"COLUMNS": "200"})
        assert res.exit_code == 2, res.output
        assert "is a file; give a folder" in res.output
    # bench simulate writes one JSON file: running it again over that file is not refused
    res = runner.invoke(app, ["bench", "simulate", "-o", str(afile), "--short-frames", "0"], env={"COLUMNS": "200"})
    assert res.exit_code == 2 and "is a file" not in res.output and "short-frames" in res.output


@pytest.mark.parametrize("args", [["--rerun", "save"], ["--rerun", "bogus"]])
def test_demo_refuses_its_out_or_rerun_before_rendering_the_world(tmp_path, monkeypatch, args):
    """The world takes 1-2 minutes to render; a demo the run would refuse is refused before it, not after."""
    from shgm_slam import demo

    rendered = []

    def render(*a, **k):
        rendered.append(a)
        raise AssertionError("the world was rendered before the refusal")

    monkeypatch.setattr(demo, "prepare_world", render)
    out = tmp_path / "out"
    out.mkdir()
    if args[1] == "save":  # an earlier run's results, no --overwrite
        (out / "metrics.json").write_text("{}")
    else:  # an empty folder is fine: only --rerun is wrong
        out.rmdir()
    res = runner.invoke(app, ["demo", "--out", str(out), "--cache", str(tmp_path / "cache"), *args],
                        env={"COLUMNS": "200"})  # fmt: skip
    assert res.exit_code == 2, (res.output, res.exception)
    assert not rendered
    assert ("--overwrite" in res.output) if args[1] == "save" else ("choose spawn, save, connect or off" in res.output)
    if args[1] == "save":
        assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]  # untouched, no lock file left


def test_a_run_that_lost_a_robot_s_front_end_exits_1_saying_so(capsys) -> None:
    """A robot whose front end failed in its worker process: the run writes its results and used to exit 0, its
    robot's frames "skipped" among unreadable ones; now it says so in red and exits 1 (130 when stopped)."""
    from types import SimpleNamespace

    import typer

    from shgm_slam.cli.system import FRONT_END_LOST_EXIT_CODE, _exit_for

    lost = SimpleNamespace(interrupted=False, front_ends_lost=["at frame 3: car2: its front end failed (a bug)"])
    with pytest.raises(typer.Exit) as info:
        _exit_for(lost)
    assert info.value.exit_code == FRONT_END_LOST_EXIT_CODE == 1
    assert "front end was lost at frame 3: car2" in " ".join(capsys.readouterr().out.split())
    with pytest.raises(typer.Exit) as info:
        _exit_for(SimpleNamespace(interrupted=True, front_ends_lost=lost.front_ends_lost))
    assert info.value.exit_code == 130
    _exit_for(SimpleNamespace(interrupted=False, front_ends_lost=[]))  # a whole run: exit 0
