"""The entity tree and the default Rerun layout: what a person sees without clicking.

Entity tree (all 3D data in the SHARED world frame = robot 0's odometry frame, camera RDF axes):
```
/world                                  ViewCoordinates RDF, AnnotationContext (Cityscapes train ids)
/world/<robot>/cam                      Transform3D T_shared_cam + Pinhole (static)
/world/<robot>/cam/{rgb,depth,seg}      camera images (2D views)
/world/<robot>/cloud                    current frame's point cloud (class ids)
/world/<robot>/trajectory/{odometry,fused}/<chunk>   trajectory, in stretches (``run_view``)
/world/<robot>/graph/{nodes,edges}/<chunk>           semantic graph, in parts (``run_view``)
/world/matches/<a>__<b>/{accepted,rejected}   one per robot pair, a before b in display order
/log                                    TextLog
/timings/<robot>/<stage>                per-stage milliseconds
/metrics/error_m/<robot>                distance of the drawn camera from its ground truth in the shared frame,
                                        metres (robots placed in it whose sequence has ground truth)
/metrics/...                            any other scalar
```
"""

from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

WORLD = "/world"
LOG = "/log"
TIMINGS = "/timings"
METRICS = "/metrics"
MATCHES = f"{WORLD}/matches"
CAMERA_IMAGES = ("rgb", "depth", "seg")


def robot_path(robot: str) -> str:
    """``/world/<robot>`` with the robot name escaped into one entity-path part."""
    return f"{WORLD}/{rr.escape_entity_path_part(robot)}"


def camera_path(robot: str) -> str:
    """``/world/<robot>/cam``: the camera (pinhole + T_shared_cam); images are its children."""
    return f"{robot_path(robot)}/cam"


def timings_path(robot: str, stage: str) -> str:
    """``/timings/<robot>/<stage>``: one series per robot and stage (no collisions between robots)."""
    return f"{TIMINGS}/{rr.escape_entity_path_part(robot)}/{rr.escape_entity_path_part(stage)}"


def error_path(robot: str) -> str:
    """``/metrics/error_m/<robot>``: the robot's distance from its ground truth in the shared frame, metres."""
    return f"{METRICS}/error_m/{rr.escape_entity_path_part(robot)}"


def matches_path(robot_a: str, robot_b: str) -> str:
    """``/world/matches/<a>__<b>``: the latest match attempt between two robots."""
    return f"{MATCHES}/{rr.escape_entity_path_part(f'{robot_a}__{robot_b}')}"


def _camera_views(robot: str, *, side_by_side: bool) -> rrb.Container:
    """RGB with the segmentation overlaid (SegmentationImage draws half-transparent over an Image) + depth."""
    cam = camera_path(robot)
    views = (
        rrb.Spatial2DView(
            origin=cam, contents=[f"{cam}/rgb", f"{cam}/seg"], name=f"{robot}: camera + labels"
        ),
        rrb.Spatial2DView(origin=cam, contents=[f"{cam}/depth"], name=f"{robot}: depth"),
    )
    return rrb.Horizontal(*views) if side_by_side else rrb.Vertical(*views)


def default_blueprint(robots: list[str]) -> rrb.Blueprint:
    """The default layout for ``robots`` (1..N names, in order).

    Left: one 3D view of the shared world (trajectories, clouds, graphs, matches, camera frusta; the
    raw camera images are excluded there because they clutter it). Right: per robot, the RGB image with
    the segmentation overlaid and the depth image. Bottom: per-stage timings, each placed robot's distance from its
    ground truth in the shared frame (runs whose sequences have ground truth) and the text log.
    """
    excluded = [f"- {camera_path(r)}/{kind}" for r in robots for kind in CAMERA_IMAGES]
    world = rrb.Spatial3DView(origin=WORLD, contents=[f"+ {WORLD}/**", *excluded], name="shared world")
    # Wide driving images (KITTI ~3.3:1) are biggest stacked; from 3 robots on, side by side wins.
    side_by_side = len(robots) >= 3
    cameras = rrb.Vertical(*[_camera_views(r, side_by_side=side_by_side) for r in robots], name="cameras")
    top = rrb.Horizontal(world, cameras, column_shares=[3, 2])
    bottom = rrb.Horizontal(
        rrb.TimeSeriesView(origin=TIMINGS, name="timings [ms]"),
        rrb.TimeSeriesView(origin=f"{METRICS}/error_m", name="error in the shared frame [m] (ground truth)"),
        rrb.TextLogView(origin=LOG, name="log"),
        column_shares=[2, 1, 2],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[3, 1]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        # "following" keeps the newest data in view while a run streams in (and in a loaded file).
        rrb.TimePanel(state="collapsed", timeline="step", play_state="following"),
    )
