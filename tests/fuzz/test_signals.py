"""Stop signals at random moments of a run: exit 130 (or 0 when the run finished first), never a traceback,
never a half-written results file."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from hypothesis import event, given
from hypothesis import strategies as st

from shgm_slam.cli import LATE_STOP_NOTE
from tests.fuzz.conftest import fuzz_settings, scratch


@fuzz_settings(3)
@given(sig=st.sampled_from(["SIGINT", "SIGTERM", "SIGHUP"]), delay_s=st.floats(0.0, 4.0))
def test_a_stop_signal_at_any_moment_keeps_the_results(tiny_scenario: Path, sig: str, delay_s: float) -> None:
    with scratch() as d:
        out = d / "out"
        proc = subprocess.Popen(
            [sys.executable, "-m", "shgm_slam", "run", "--robot", f"car1={tiny_scenario / 'car1'}",
             "--robot", f"car2={tiny_scenario / 'car2'}", "--rerun", "off", "--out", str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "COLUMNS": "200"},
        )  # fmt: skip
        deadline = time.monotonic() + 120
        while not (out / "config.yaml").is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # the run has started (its handlers are installed; imports are done)
        time.sleep(delay_s)
        proc.send_signal(getattr(signal, sig))
        stdout, stderr = proc.communicate(timeout=120)
        text = (stdout + stderr).decode()
        event(f"exit {proc.returncode}")
        assert proc.returncode in (0, 130), text[-3000:]
        assert "Traceback" not in text, text[-3000:]
        assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporaries left
        metrics = out / "metrics.json"
        if proc.returncode == 130:
            assert "interrupted" in text
        late = LATE_STOP_NOTE in text  # the signal came after the results were complete (exit 130 all the same)
        if late:
            assert proc.returncode == 130 and metrics.is_file(), text[-3000:]  # the run had written everything
        if metrics.is_file():  # absent only when the signal came while the final results were being written
            assert json.loads(metrics.read_text())["interrupted"] is (proc.returncode == 130 and not late)
            for robot in ("car1", "car2"):
                assert (out / f"{robot}_odometry_tum.txt").is_file()


def test_a_stop_signal_after_the_run_ended_exits_as_interrupted_not_killed() -> None:
    """Once the results are written and the command returns, a SIGTERM/SIGHUP during the process's
    shutdown ends it with 130 (interrupted) instead of killing it by the signal."""
    code = (
        "import os, signal, time\n"
        "import shgm_slam.cli as cli\n"
        "cli.signals.OWN_PROCESS = True\n"
        "with cli.stop_signals_as_interrupt():\n"
        "    pass\n"
        "print('done', flush=True)\n"
        "os.kill(os.getpid(), signal.SIGHUP)\n"
        "time.sleep(30)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert proc.stdout.strip() == "done"


def test_a_stop_signal_in_the_interpreter_teardown_does_not_kill_a_finished_command() -> None:
    """Python puts the default handlers back for its teardown: a SIGTERM arriving then (a finalizer runs
    late) killed a run that had written everything by the signal (-15). The command now ends before it."""
    code = (
        "import os, signal, sys, time\n"
        "import shgm_slam.cli as cli\n"
        "class Late:\n"
        "    def __del__(self):\n"
        "        os.kill(os.getpid(), signal.SIGTERM)\n"
        "        time.sleep(5)\n"
        "cli._late = Late()\n"  # a module global: finalized in the interpreter's teardown
        "sys.argv = ['shgm-slam', '--version']\n"
        "cli.main()\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert proc.stdout.startswith("shgm-slam")
