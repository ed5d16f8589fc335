"""The one exception tree of shgm_slam.

Library code raises these with actionable messages (what is wrong, which file, how to fix it);
only the command line (``shgm_slam.cli``) catches them, prints one line and exits non-zero.
"""

from __future__ import annotations

import re


class ShgmError(Exception):
    """Base class of every error shgm_slam raises on purpose."""


class DataError(ShgmError):
    """A sequence, image, calibration, pose or graph file is missing, unreadable or inconsistent."""


class ConfigError(ShgmError):
    """A configuration file or option is invalid."""


class ModelError(ShgmError):
    """An ONNX model or its model card does not fit what the adapter needs."""


class GraphError(ShgmError):
    """A semantic graph is malformed (bad ids, labels, edges) or unusable for matching."""


class SimulationError(ShgmError):
    """The synthetic world or a scenario cannot be built as requested."""


class BackendError(ShgmError):
    """The pose graph back end failed (for example an indeterminate system)."""


class RunError(ShgmError):
    """A run did not go as its results would claim (a robot's front end lost mid-run), so what measures it stops."""


class ProtocolError(ShgmError):
    """A message from a peer is malformed, of another protocol version, or from a clashing robot."""


class TransportError(ShgmError):
    """The network transport between robots and the map server cannot be opened or used."""


def parse_failure(exc: BaseException) -> str:
    """Why a YAML or JSON file could not be parsed, said in our words where Python's would mislead: an integer
    of thousands of digits (Python's text advises ``sys.set_int_max_str_digits()``) or nesting too deep."""
    if isinstance(exc, RecursionError):
        return "its nesting is too deep"
    text = str(exc)
    if "integer string conversion" in text:
        digits = re.search(r"value has (\d+) digits", text)
        size = f"{digits[1]} digits" if digits else "thousands of digits"
        return f"it holds an integer of {size}, far beyond any value it can mean; fix that number"
    return text
