"""Rendered worlds in a cache shared by benchmarks: each world rendered once, never seen half-written.

Benchmarks (``bench heldout``, ``table3``, ``system``/``scale``/``robots``) render their worlds into a cache
folder and reuse them. Two benchmarks started together on one cache used to render the same world into the
same folder at once, and one of them died inside ``shutil.rmtree`` with a stack trace. Here a process takes
an advisory lock beside the folder (``<folder>.lock``) before it renders, so the second one waits and then
finds the world finished; the render goes to a folder of its own (``<folder>.partial-<pid>``) and is renamed
into place only when it is complete, so an interrupted render never looks finished (``scenario.json``,
written last, marks a finished world). A render killed outright (SIGKILL, a machine that went down) leaves its
``.partial-<pid>`` folder behind; the next process to hold the lock removes such folders, since no other
process can be writing one then.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from shgm_slam.errors import SimulationError
from shgm_slam.sim.simulate import simulate

try:  # advisory file locks: POSIX; elsewhere concurrent renders of one world each render it (no crash)
    import fcntl
except ImportError:  # pragma: no cover - not on Linux or macOS
    fcntl = None  # type: ignore[assignment]

FINISHED = "scenario.json"
"""The file a finished world holds (``simulate`` writes it last)."""


def simulate_cached(scenario: str, folder: Path | str, **options: Any) -> Path:
    """``simulate(scenario, folder, **options)`` once per cache folder (module docstring).

    Returns ``folder`` at once when it holds a finished world; else waits for any other process rendering it,
    renders it when still missing, and returns it.

    Raises:
        SimulationError: ``folder`` is a file or its cache folder cannot be created; or what ``simulate`` raises
            (nothing is left behind then).
    """
    out = Path(folder)
    if (out / FINISHED).is_file():
        return out
    if out.exists() and not out.is_dir():
        raise SimulationError(f"cannot cache a rendered world at {out}: it is a file; remove it or use another cache")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimulationError(
            f"cannot create the cache folder {out.parent}: {exc.strerror or exc}; choose a writable folder (--cache)"
        ) from None
    with _exclusive(out.with_name(out.name + ".lock")):
        if (out / FINISHED).is_file():  # rendered by another process while this one waited
            return out
        for stale in out.parent.glob(f"{glob.escape(out.name)}.partial-*"):  # killed renders: nobody writes them now
            shutil.rmtree(stale, ignore_errors=True)
        partial = out.with_name(f"{out.name}.partial-{os.getpid()}")
        try:
            simulate(scenario, partial, overwrite=True, **options)
            if out.is_dir():  # an interrupted render of an earlier run (no scenario.json): replaced
                shutil.rmtree(out)
            partial.rename(out)
        finally:
            shutil.rmtree(partial, ignore_errors=True)
    return out


@contextlib.contextmanager
def _exclusive(lock_path: Path) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``lock_path`` (created if missing) for the block."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    with open(lock_path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
