"""The ``shgm-slam`` command line: parse -> validate -> call one library function -> render.

This is the only module that catches ``ShgmError`` (one clear line, exit code 2) and talks to the
user. Each command is a thin wrapper over a library function that tests call directly.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console

from shgm_slam import __version__
from shgm_slam.errors import ShgmError

console = Console()
err_console = Console(stderr=True)

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
            err_console.print(f"[bold red]error:[/] {exc}")
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
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


@app.command("dump-config")
@handle_errors
def dump_config(
    config: Annotated[Path | None, typer.Option("--config", help="Show this YAML merged over the defaults.")] = None,
) -> None:
    """Print the effective configuration as YAML (defaults, or a file merged over them)."""
    from shgm_slam.config import load_config

    typer.echo(load_config(config).to_yaml(), nl=False)


# --- simulate (sim/) -------------------------------------------------------------------------------
# --- graph / match (graph/, descriptors/, matching/) -----------------------------------------------
# --- run / demo (pipeline.py) -----------------------------------------------------------------------
# --- check-model (perception/) ----------------------------------------------------------------------
# --- bench (bench.py) -------------------------------------------------------------------------------
