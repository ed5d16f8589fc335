"""World seeds of the benchmarks' ``--seeds``: one parser for every benchmark."""

from __future__ import annotations

from collections.abc import Mapping

from shgm_slam.errors import ConfigError

MAX_SEED = 2**31 - 1
"""Largest world seed (``simulate --seed``'s bound)."""


def parse_seeds(text: str, named: Mapping[str, tuple[int, ...]] | None = None) -> tuple[int, ...]:
    """World seeds from ``--seeds``: a name of ``named`` (e.g. ``report``, ``tuning``), an inclusive range
    ``A-B`` or a list ``A,B,C`` of distinct seeds, each 0 .. ``MAX_SEED``.

    Raises:
        ConfigError: anything else, an empty range (B < A) or a seed given twice (it would be counted twice).
    """
    named = named or {}
    if text in named:
        return tuple(named[text])
    forms = ", ".join([*named, "A-B (inclusive)", "A,B,C"])
    try:
        if "-" in text:
            lo, hi = (int(x) for x in text.split("-"))
            seeds = tuple(range(lo, hi + 1))
            if not seeds:
                raise ConfigError(f"--seeds {text!r} selects no world (A-B needs A <= B)")
        else:
            seeds = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise ConfigError(f"--seeds {text!r}: write {forms} with seeds 0-{MAX_SEED}, e.g. 10-14") from None
    if min(seeds) < 0 or max(seeds) > MAX_SEED:
        raise ConfigError(f"--seeds {text!r}: seeds lie in 0-{MAX_SEED}")
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ConfigError(f"--seeds {text!r} gives seed {repeated[0]} more than once (its worlds would count twice)")
    return seeds
