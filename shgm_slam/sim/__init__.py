"""Synthetic multi-robot semantic city: world, robot trajectories, ray-cast renderer, scenarios.

The paper evaluates on SYNTHIA and AirSim, which cannot be downloaded; this package builds its own
worlds (``city``, ``corridor``), robot paths (``trajectories``, ``kitti_paths``), renders RGB, metric
depth and Cityscapes labels with embree (``render``), optionally corrupts them (``corruption``) and
writes multi-robot scenarios (``scenarios``, ``simulate``) in our sequence layout.
"""

from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.corruption import CorruptionLevels, corrupt_depth, corrupt_labels
from shgm_slam.sim.render import RenderedFrame, Renderer, make_intrinsics
from shgm_slam.sim.scenarios import SCENARIOS, ScenarioOptions, ScenarioPlan, build_scenario
from shgm_slam.sim.shapes import ObjectKind
from shgm_slam.sim.simulate import ScenarioResult, parse_resolution, simulate
from shgm_slam.sim.trajectories import RobotKind, Trajectory, shared_view_length_m
from shgm_slam.sim.world import World, WorldObject, assemble_world

__all__ = [
    "SCENARIOS",
    "CityParams",
    "CorruptionLevels",
    "ObjectKind",
    "RenderedFrame",
    "Renderer",
    "RobotKind",
    "ScenarioOptions",
    "ScenarioPlan",
    "ScenarioResult",
    "Trajectory",
    "World",
    "WorldObject",
    "assemble_world",
    "build_city",
    "build_scenario",
    "corrupt_depth",
    "corrupt_labels",
    "make_intrinsics",
    "parse_resolution",
    "shared_view_length_m",
    "simulate",
]
