"""Stop signals and the process's end: SIGTERM/SIGHUP stop a command as Ctrl-C does, and a stop that
arrives once the results are written ends the process with exit code 130 instead of killing it."""

from __future__ import annotations

import contextlib
import os
import signal
import sys

from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE


@contextlib.contextmanager
def stop_signals_as_interrupt():
    """SIGTERM and SIGHUP stop a run like Ctrl-C does: the results so far are written, with the summary."""

    def interrupt(signum, _frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    stops = [sig for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)) if sig is not None]
    previous = {sig: signal.signal(sig, interrupt) for sig in stops}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, late_stop if OWN_PROCESS else handler)


OWN_PROCESS = False
"""True when ``shgm_slam.cli.main`` runs the process (the ``shgm-slam`` command), not a test calling it."""


LATE_STOP_NOTE = "interrupted after the results were written (they are complete)"
"""What a stop signal that arrives after a command's results are written prints before exit code 130."""


def late_stop(_signum, _frame) -> None:
    """A stop signal after the results are written (the summary being printed, the process exiting): end
    now with the interrupted exit code, saying the results are complete, instead of dying by the signal
    mid-shutdown."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    with contextlib.suppress(OSError):
        os.write(2, f"\n{LATE_STOP_NOTE}\n".encode())
    os._exit(INTERRUPTED_EXIT_CODE)


EXIT_CODE = 1
"""The command's exit code for ``skip_teardown`` (1 until the command ends normally or by SystemExit)."""


def skip_teardown() -> None:
    """The last exit hook: end the process with the command's exit code, skipping the interpreter's teardown.

    Python puts the default signal handlers back for that teardown (finalizers of modules and objects), so a
    stop signal arriving then killed a finished run by the signal (exit -15, results written, summary
    printed) instead of ending it with 0 or 130. Non-daemon threads are joined and the other exit hooks
    (logging, Rerun) have run before this one, which ``main`` registers first so that it runs last.
    """
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(EXIT_CODE)

