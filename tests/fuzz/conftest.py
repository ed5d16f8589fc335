"""Fuzz suite (property-based, Hypothesis): bad inputs end in a clean ``ShgmError`` or a reported skip.

Every test here asserts the same contract: whatever the corruption, the library raises one of our
errors (the CLI turns it into one line and exit 2) or skips the frame with a reason, and never
raises anything else. Example counts are small and deadlines off so that the whole suite stays under
3 minutes on 2 cores; the database is off so runs are reproducible from the seed Hypothesis prints.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis")

from hypothesis import HealthCheck, settings  # noqa: E402

settings.register_profile(
    "fuzz",
    deadline=None,
    database=None,
    derandomize=False,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def fuzz_settings(max_examples: int) -> settings:
    """The suite's settings with ``max_examples`` (kept small: the suite's budget is 3 minutes)."""
    return settings(settings.get_profile("fuzz"), max_examples=max_examples)


@contextlib.contextmanager
def scratch() -> Iterator[Path]:
    """A fresh temporary folder per Hypothesis example (``tmp_path`` is shared by all examples)."""
    with tempfile.TemporaryDirectory(prefix="shgm-fuzz-") as d:
        yield Path(d)
