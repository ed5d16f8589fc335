"""shgm_slam: multi-robot global localization and map fusion with semantic histogram graph matching.

Implements Guo et al., "Semantic Histogram Based Graph Matching for Real-Time Multi-Robot Global
Localization in Large Scale Environment", RA-L 2021, as an incremental SLAM plugin on KISS-ICP.

From Python (``api``): ``run`` the multi-robot system on sequences (``open_sequence`` for folders,
``ArraySequence`` for frames in memory), ``match`` two semantic graphs, ``read_fused`` a robot's fused
trajectory and ``evaluate`` a results folder; ``LiveRun`` (``live``) takes frames one by one as cameras
deliver them, ``LiveRobot`` one robot's frames for a map server over Zenoh. The names below load their
modules when first used, so ``import shgm_slam`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "run": "shgm_slam.api",
    "match": "shgm_slam.api",
    "read_fused": "shgm_slam.api",
    "evaluate": "shgm_slam.api",
    "FusedTrajectory": "shgm_slam.api",
    "GraphMatch": "shgm_slam.api",
    "LiveRun": "shgm_slam.live",
    "LivePose": "shgm_slam.live",
    "LiveRobot": "shgm_slam.live",
    "ArraySequence": "shgm_slam.data.memory",
    "open_sequence": "shgm_slam.data.base",
    "read_graph": "shgm_slam.io.graph_json",
    "ShgmConfig": "shgm_slam.config",
    "load_config": "shgm_slam.config",
    "Dof": "shgm_slam.config",
    "DepthOrigin": "shgm_slam.types",
    "Frame": "shgm_slam.types",
    "GraphArrays": "shgm_slam.types",
    "Intrinsics": "shgm_slam.types",
    "ShgmError": "shgm_slam.errors",
    "RerunMode": "shgm_slam.viz.rerun_logger",
}
"""Public name -> the module that defines it."""

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'shgm_slam' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
