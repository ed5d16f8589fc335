"""viz stage: all Rerun logging (``RerunLogger``), a do-nothing ``NullLogger`` and the default blueprint."""

from shgm_slam.viz.blueprint import default_blueprint
from shgm_slam.viz.rerun_logger import LogLevel, NullLogger, RerunLogger, RerunMode, Viz, make_viz

__all__ = ["LogLevel", "NullLogger", "RerunLogger", "RerunMode", "Viz", "default_blueprint", "make_viz"]
