"""Strict JSON text for every JSON file and ``--json`` output: what any JSON parser reads.

Python's ``json`` writes bare ``NaN`` and ``Infinity`` for non-finite floats, which is not JSON (jq,
JavaScript and ``json.loads(..., parse_constant=...)`` reject it). Here a number that is not measurable
(a robot not placed, an undefined ATE) is written as ``null``; numpy arrays and scalars become lists and
numbers, paths their text.
"""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path

import numpy as np


def finite_or_none(value: object) -> object:
    """``value`` with every non-finite float (NaN, inf) replaced by None, recursively: valid JSON."""
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_none(v) for v in value]
    return value


def json_default(o: object) -> object:
    """Plain values for what ``json`` cannot write itself: numpy arrays and scalars, paths, enums."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, Enum):
        return o.value
    try:
        return float(o)  # other numeric types (Decimal, tensors of one element)
    except (TypeError, ValueError):
        raise TypeError(f"cannot serialize {type(o).__name__}") from None


def to_json_text(data: object, *, indent: int | None = 1, compact: bool = False) -> str:
    """``data`` as strict JSON text (no trailing newline): non-finite numbers as ``null``.

    Args:
        data: dicts, lists, numbers, strings, numpy values, paths.
        indent: spaces per level (None: one line).
        compact: one line without spaces after separators (large files such as graphs).
    """
    plain = json.loads(json.dumps(data, default=json_default))  # numpy, paths -> plain values (NaN kept)
    if compact:
        return json.dumps(finite_or_none(plain), indent=None, separators=(",", ":"), allow_nan=False)
    return json.dumps(finite_or_none(plain), indent=indent, allow_nan=False)
