"""The one exception tree of shgm_slam.

Library code raises these with actionable messages (what is wrong, which file, how to fix it);
only ``cli.py`` catches them, prints one line and exits non-zero.
"""

from __future__ import annotations


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


class ProtocolError(ShgmError):
    """A message from a peer is malformed, of another protocol version, or from a clashing robot."""


class TransportError(ShgmError):
    """The network transport between robots and the map server cannot be opened or used."""
