"""The ``shgm-slam`` Typer apps and the error boundary: ``ShgmError`` becomes one red line and exit code 2."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer

from shgm_slam import __version__
from shgm_slam.cli.render import console, err_console, lit
from shgm_slam.cli.signals import stop_signals_as_interrupt
from shgm_slam.errors import ShgmError
from shgm_slam.interrupts import INTERRUPTED_EXIT_CODE

app = typer.Typer(
    name="shgm-slam",
    help="Multi-robot global localization and map fusion with semantic histogram graph matching.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks that measure speed and accuracy; results go to JSON and markdown.",
                        no_args_is_help=True)
app.add_typer(bench_app, name="bench")

F = TypeVar("F", bound=Callable[..., Any])


def handle_errors(fn: F) -> F:
    """Turn ``ShgmError`` into one red line on stderr and exit code 2 (the CLI's error boundary)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ShgmError as exc:
            err_console.print(f"[bold red]error:[/] {lit(exc)}", soft_wrap=True)  # one line: paths stay whole
            raise typer.Exit(2) from None
        except KeyboardInterrupt:  # before a run's loop (which keeps its results itself) or in another command
            err_console.print("[yellow]interrupted[/]")
            raise typer.Exit(INTERRUPTED_EXIT_CODE) from None

    return wrapper  # type: ignore[return-value]


def stops_like_ctrl_c(fn: F) -> F:
    """Run a command with SIGTERM and SIGHUP stopping it as Ctrl-C does (``stop_signals_as_interrupt``): a
    benchmark stopped by ``timeout``, a job scheduler or a closed terminal writes what it finished and exits 130,
    instead of dying by the signal with its report unwritten."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with stop_signals_as_interrupt():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    """``--version``: print the package version and exit."""
    if value:
        console.print(f"shgm-slam {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """shgm_slam: several robots find each other and fuse their maps from camera images alone."""

