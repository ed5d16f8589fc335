"""Stop signals are held inside a step and delivered after it (``stops_deferred``); a Ctrl-C while the command
line loads ends it like one during a command (``shgm_slam.__main__``)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import pytest

from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE, STOP_SIGNALS, stops_deferred


def test_a_ctrl_c_inside_the_block_lets_it_finish_and_then_interrupts(python_ctrl_c) -> None:
    steps = []
    with pytest.raises(KeyboardInterrupt):
        with stops_deferred():
            signal.raise_signal(signal.SIGINT)
            steps.append("after the signal")  # a half-done step would stop here without the guard
            steps.append("end of the step")
    assert steps == ["after the signal", "end of the step"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_handlers_are_restored_and_nothing_is_raised_without_a_signal() -> None:
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    with stops_deferred():
        assert all(signal.getsignal(s) is not before[s] for s in STOP_SIGNALS)
    assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == before


def test_a_held_sigterm_goes_to_the_handler_that_was_there_before() -> None:
    seen = []
    previous = signal.signal(signal.SIGTERM, lambda signum, _frame: seen.append(signum))
    try:
        with stops_deferred():
            signal.raise_signal(signal.SIGTERM)
            signal.raise_signal(signal.SIGTERM)
            assert seen == []
        assert seen == [signal.SIGTERM]  # delivered once, after the block
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_outside_the_main_thread_the_block_runs_unguarded() -> None:
    errors = []

    def work() -> None:
        try:
            with stops_deferred():  # signal.signal would raise ValueError here
                pass
        except Exception as exc:
            errors.append(exc)

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert errors == []


CTRL_C_WHILE_LOADING = """
import os, signal, sys

signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a shell (pytest-xdist's workers ignore it)

class CtrlC:  # a Ctrl-C that lands while the command line loads (it takes about a second)
    def find_spec(self, name, path=None, target=None):
        if name == "shgm_slam.cli":
            os.kill(os.getpid(), signal.SIGINT)
        return None

sys.meta_path.insert(0, CtrlC())
sys.argv = ["shgm-slam", "--version"]
from shgm_slam.__main__ import main
main()
"""


def test_a_ctrl_c_while_the_command_loads_says_interrupted_not_a_traceback() -> None:
    out = subprocess.run([sys.executable, "-c", CTRL_C_WHILE_LOADING], capture_output=True, text=True, timeout=120)
    assert out.returncode == INTERRUPTED_EXIT_CODE, out.stderr
    assert out.stderr.strip() == "interrupted"
    assert "Traceback" not in out.stderr


def test_python_dash_m_runs_the_command() -> None:
    out = subprocess.run([sys.executable, "-m", "shgm_slam", "--version"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("shgm-slam "), out.stderr
