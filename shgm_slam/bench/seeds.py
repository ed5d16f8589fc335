"""World seeds of the benchmarks' ``--seeds``: one parser for every benchmark."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping

from shgm_slam.errors import ConfigError

MAX_SEED = 2**31 - 1
"""Largest world seed (``simulate --seed``'s bound)."""
MAX_SEEDS = 10_000
"""Most world seeds one ``--seeds`` selects: a range is checked against it before its seeds are listed (0-2000000000
listed two billion integers, gigabytes, before anything was said)."""


def parse_seeds(text: str, named: Mapping[str, tuple[int, ...]] | None = None) -> tuple[int, ...]:
    """World seeds from ``--seeds``: a name of ``named`` (e.g. ``report``, ``tuning``), an inclusive range
    ``A-B`` or a list ``A,B,C`` of distinct seeds, each 0 .. ``MAX_SEED``, at most ``MAX_SEEDS`` of them.

    Raises:
        ConfigError: anything else, an empty range (B < A), more than ``MAX_SEEDS`` seeds or a seed given twice
            (it would be counted twice).
    """
    named = named or {}
    if text in named:
        return tuple(named[text])
    forms = ", ".join([*named, "A-B (inclusive)", "A,B,C"])
    try:
        if "-" in text:
            lo, hi = (int(x) for x in text.split("-"))
            if hi < lo:
                raise ConfigError(f"--seeds {text!r} selects no world (A-B needs A <= B)")
            _check_count(text, hi - lo + 1)
            seeds = tuple(range(lo, hi + 1))
        else:
            seeds = tuple(int(x) for x in text.split(","))
            _check_count(text, len(seeds))
    except ValueError:
        raise ConfigError(f"--seeds {text!r}: write {forms} with seeds 0-{MAX_SEED}, e.g. 10-14") from None
    if min(seeds) < 0 or max(seeds) > MAX_SEED:
        raise ConfigError(f"--seeds {text!r}: seeds lie in 0-{MAX_SEED}")
    repeated = sorted(s for s, n in Counter(seeds).items() if n > 1)
    if repeated:
        raise ConfigError(f"--seeds {text!r} gives seed {repeated[0]} more than once (its worlds would count twice)")
    return seeds


def _check_count(text: str, count: int) -> None:
    """ConfigError when ``--seeds text`` selects more than ``MAX_SEEDS`` seeds (``count``)."""
    if count > MAX_SEEDS:
        shown = text if len(text) <= 40 else f"{text[:20]}...{text[-12:]}"
        raise ConfigError(f"--seeds {shown!r} selects {count} worlds; give at most {MAX_SEEDS} (e.g. 10-19)")
