"""Stop signals between steps, never inside one: a Ctrl-C (or SIGTERM / SIGHUP) that lands while a map server
ingests a keyframe or a front end builds one would leave their state half-updated (a keyframe in the
server's lists but not yet in its pose graph: "car1 has 36 keyframes but 35 poses in iSAM2"), and the
results written after the stop would fail or be wrong. Inside ``stops_deferred`` such a signal is held and
delivered, to whatever handler was there before, as soon as the step is done."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

STOP_SIGNALS = tuple(
    s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None
)
"""The signals that stop a run (the CLI turns SIGTERM and SIGHUP into a Ctrl-C)."""

INTERRUPTED_EXIT_CODE = 130
"""Exit code of a command stopped by one of them (128 + SIGINT, as the shell reports a Ctrl-C)."""


@contextlib.contextmanager
def stops_deferred() -> Iterator[None]:
    """Hold ``STOP_SIGNALS`` for the duration of the block, then deliver the first one that arrived (after the
    previous handlers are back: a KeyboardInterrupt where Ctrl-C raises one, the default action where none
    was installed). Signals are only handled in the main thread: elsewhere the block runs unguarded."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum: int, _frame: object) -> None:
        held.append(signum)

    previous = {s: signal.signal(s, hold) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if held:
        signal.raise_signal(held[0])
