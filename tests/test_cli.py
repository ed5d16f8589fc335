"""The CLI's error boundary prints user text literally: rich markup in paths and messages is not interpreted."""

from __future__ import annotations

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
        [sys.executable, "-m", "shgm_slam.cli", "run", *robots, "--rerun", "off", "--out", str(out)],
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
