"""A benchmark stops where its user stopped it, and keeps what it finished.

``run_slam`` keeps a stopped run's results itself (its trajectories end where it was stopped, its
``metrics.json`` says ``interrupted``) and returns normally, which is right for ``shgm-slam run`` but wrong
inside a benchmark: the next run would start as if nothing happened, and a held-out run cut short would be
judged and cached as finished. ``run_to_end`` turns a stopped run back into a ``KeyboardInterrupt`` for the
benchmark's own loop, which writes what it finished, marked ``interrupted``, and the CLI exits with
``INTERRUPTED_EXIT_CODE``.
"""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Any

from shgm_slam.config import ShgmConfig
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE
from shgm_slam.run_report import RunSummary
from shgm_slam.runner import run_slam
from shgm_slam.types import Sequence


class RunStopped(KeyboardInterrupt):
    """A benchmark's run was stopped (Ctrl-C, SIGTERM, SIGHUP); its results folder holds what it reached."""


def run_to_end(robots: dict[str, Sequence], cfg: ShgmConfig, out: Path, **kwargs: Any) -> RunSummary:
    """``run_slam(robots, cfg, out, **kwargs)``, raising ``RunStopped`` when that run was stopped.

    Raises:
        RunStopped: the run was interrupted (its results are written in ``out``).
    """
    summary = run_slam(robots, cfg, out, **kwargs)
    if summary.interrupted:
        raise RunStopped(f"the run in {out} was interrupted; its results folder holds what it reached")
    return summary


def stopped_exit_code(returncode: int) -> bool:
    """Whether a child ``shgm-slam`` process's exit code (``os.waitstatus_to_exitcode``: minus the signal
    that killed it) says it was stopped, not that it failed."""
    return returncode in (INTERRUPTED_EXIT_CODE, -signal.SIGINT, -signal.SIGTERM)
