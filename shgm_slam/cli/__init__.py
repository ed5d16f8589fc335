"""The ``shgm-slam`` command line: parse -> validate -> call one library function -> render.

This package is the only place that catches ``ShgmError`` (``app.handle_errors``: one clear line, exit code
2) and talks to the user. Each command is a thin wrapper over a library function that tests call directly:

- ``app``: the Typer apps, the error boundary and the stop-signal decorator;
- ``options``: option parsers and bounds shared by the commands;
- ``maps``: ``dump-config``, ``simulate``, ``graph``, ``match``;
- ``system``: ``run``, ``server``, ``robot``, ``demo``, ``eval``;
- ``perception``: ``check-model``, ``perceive``;
- ``bench``: the benchmarks;
- ``render``: what the commands print;
- ``signals``: stop signals and the process's end.

The command modules register their commands on ``app`` when imported (in this order, which is the order of
``--help``).
"""

from __future__ import annotations

from shgm_slam.cli import bench, maps, perception, signals, system  # noqa: F401  (registers the commands)
from shgm_slam.cli.app import app
from shgm_slam.cli.render import lit, markdown_tables, summary_table
from shgm_slam.cli.signals import LATE_STOP_NOTE, stop_signals_as_interrupt

__all__ = ["LATE_STOP_NOTE", "app", "lit", "main", "markdown_tables", "stop_signals_as_interrupt", "summary_table"]


def main() -> None:
    """The ``shgm-slam`` command (entered through ``shgm_slam.__main__``, which loads this package)."""
    import atexit

    signals.OWN_PROCESS = True
    atexit.register(signals.skip_teardown)
    try:
        app()
        signals.EXIT_CODE = 0
    except SystemExit as exc:
        signals.EXIT_CODE = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        raise
