"""Building one robot's front end from the fleet configuration: its perception, scene scale, odometry.

Apart from ``runner`` so that a worker process (``robot.remote``) builds its robots' front ends without
importing the map server, the pose graph and the viewer (~100 MB less per worker).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data.validate import check_sequence_start
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.odometry.sources import choose_odometry, given_odometry, make_odometry
from shgm_slam.odometry.visual import depth_window_on_image
from shgm_slam.perception import PerceptionSource, make_perception
from shgm_slam.perception.perceive import depth_model_of
from shgm_slam.robot.frontend import RobotFrontend
from shgm_slam.scene_scale import ScaleSampler, resolve_robot_config, sample_scene_scale
from shgm_slam.types import Frame, Sequence

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RobotPerception:
    """A robot's configuration (the fleet's with its overrides) and perception source, before its front end.

    Attributes:
        cfg: the robot's configuration (a poses file's ``{robot}`` replaced by its name).
        perception: its perception source (models or the sequence's files).
        written_by: the depth model a ``perceive`` folder's files came from (``perceive.json``), or None.
        predicted: its depth comes from a network (a configured model, or files a model wrote).
    """

    cfg: ShgmConfig
    perception: PerceptionSource
    written_by: dict | None
    predicted: bool

    def perceive(self, frame: Frame) -> tuple[np.ndarray, np.ndarray | None]:
        """Frame -> (depth_m (H, W) metres, label_ids (H, W) train ids or None)."""
        out = self.perception.process(frame)
        return out.depth_m, out.label_ids


def robot_perception(name: str, sequence: Sequence, cfg: ShgmConfig) -> RobotPerception:
    """The robot's configuration and perception source (the first half of ``make_frontend``).

    Raises:
        ConfigError: ground-truth odometry for a sequence without ground truth.
        DataError, ModelError: a missing depth or label source, a model that cannot be loaded.
    """
    rcfg = cfg.for_robot(name)
    if rcfg.odometry.kind is OdometryKind.FILE and rcfg.odometry.poses_file is not None:
        path = Path(str(rcfg.odometry.poses_file).replace("{robot}", name))
        rcfg = rcfg.model_copy(update={"odometry": rcfg.odometry.model_copy(update={"poses_file": path})})
    if rcfg.odometry.kind is OdometryKind.GT and sequence.gt_poses is None:
        raise ConfigError(
            f"robot {name!r}: --odometry gt needs ground-truth poses (poses.txt, or <root>/poses/<seq>.txt for "
            "KITTI), and its sequence has none; use --odometry auto"
        )
    if rcfg.odometry.kind is OdometryKind.GIVEN and not given_odometry(sequence):
        raise ConfigError(
            f"robot {name!r}: odometry 'given' runs the robot's own odometry given with its frames "
            "(ArraySequence(T_odom_cam=...), LiveRun.add_frame(..., T_odom_cam=...)), and its frames come without "
            "it; for a sequence folder give a poses file (--odometry PATH), or use odometry 'auto'"
        )
    written_by = depth_model_of(sequence) if rcfg.perception.depth_model is None else None
    if written_by is not None:
        log.info("%s: its depth files were predicted by %s (perceive.json): treated as predicted depth", name,
                 written_by.get("path", "a depth model"))  # fmt: skip
    predicted = rcfg.perception.depth_model is not None or written_by is not None
    try:
        perception = make_perception(rcfg.perception, sequence, files_depth_predicted=written_by is not None)
    except DataError as exc:  # which robot lacks its depth or labels
        raise DataError(f"robot {name!r}: {exc}") from None
    return RobotPerception(rcfg, perception, written_by, predicted)


def make_frontend(
    name: str,
    sequence: Sequence,
    cfg: ShgmConfig,
    *,
    max_segments: int | None = None,
    prepared: RobotPerception | None = None,
    sampler: ScaleSampler | None = None,
) -> RobotFrontend:
    """Build one robot's front end from the fleet config (with the robot's overrides merged in).

    A poses-file odometry path may contain ``{robot}``, replaced by the robot name, so every robot
    reads its own file (e.g. ``orbslam_{robot}.txt``). Fields left None (extraction range, blob size,
    odometry voxel, ...) are derived from the robot's first frames through its perception source
    (``scene_scale``); the fleet values when none has usable depth (logged). The front end's ``cfg``
    holds the resolved values. ``max_segments``: the trajectory segments it may start (``RobotFrontend``).
    ``prepared`` and ``sampler``: its ``robot_perception`` and a ``ScaleSampler`` already offered its first frames
    (frames that arrive one by one, ``live``); None: made and sampled here.

    Raises:
        ConfigError, DataError, ModelError: what ``robot_perception`` and ``check_sequence_start`` raise.
    """
    p = prepared or robot_perception(name, sequence, cfg)
    rcfg, perception, written_by, predicted = p.cfg, p.perception, p.written_by, p.predicted
    # whole-sequence problems (every frame unreadable, no valid depth, a broken model) end here, not as skips
    check_sequence_start(name, sequence, p.perceive, depth_model=rcfg.perception.depth_model,
                         seg_model=rcfg.perception.seg_model)  # fmt: skip
    # the probes reach across the whole sequence: neither the scale sampled from the first frames nor the run
    # starts from what they showed the perception (its depth-scale window), so both see only frames in order
    # (and frames that arrive one by one, sampled as they came, give the same)
    perception.reset()
    scale = sample_scene_scale(sequence, p.perceive) if sampler is None else sampler.result()
    perception.reset()
    if scale is None:
        log.warning("%s: no usable depth in the first frames; extraction and odometry use the fleet defaults", name)
    else:
        log.info("%s: camera %.1f m above the ground, nearest ground at %.1f m, depth noise %.1f %% of the depth",
                 name, scale.camera_height_m or float("nan"), scale.nearest_ground_depth_m,
                 100.0 * scale.depth_noise_rel)  # fmt: skip
        if scale.frame_indices and scale.frame_indices[0] > 0:
            log.info("%s: its first frames show no labelled ground; its scale is measured on frames %s", name,
                     ", ".join(map(str, scale.frame_indices)))  # fmt: skip
    rcfg = resolve_robot_config(rcfg, scale)
    rcfg = _window_on_image(name, rcfg, sequence, perception, written_by)
    rcfg = _road_at_camera_height(rcfg, perception)
    choice = choose_odometry(rcfg.odometry.kind, depth_from_model=predicted, odometry_given=given_odometry(sequence))
    if choice.kind is OdometryKind.KISS_ICP and rcfg.odometry.image_step_blend:
        noise = 100.0 * (rcfg.odometry.depth_noise_rel or 0.0)
        choice = replace(choice, reason=f"{choice.reason}; its depth is noisy ({noise:.1f} %), so each step is "
                         "blended with the one the image tracks give (odometry.image_step_blend)")  # fmt: skip
    log.info("%s: odometry %s (%s)", name, choice.kind.value, choice.reason)
    odometry = make_odometry(rcfg.odometry.model_copy(update={"kind": choice.kind}), len(sequence),
                             timestamps_s=sequence.timestamps_s)  # fmt: skip
    return RobotFrontend(name, sequence, rcfg, perception, odometry, choice, depth_predicted=predicted,
                         max_segments=max_segments, settings_digest=cfg.front_end_digest(name))  # fmt: skip


def _road_at_camera_height(rcfg: ShgmConfig, perception: object) -> ShgmConfig:
    """``rcfg`` with the visual odometry's road steps at ``perception.camera_height_m`` where the robot's predicted
    depth is scaled to that height (``perception.ground_scale``) and no road height is set: the configured height
    is what the scale assumes, and each frame's measured one swings with the network's scale."""
    if getattr(perception, "ground_scale", None) is None or rcfg.odometry.visual_road_height_m is not None:
        return rcfg
    height = rcfg.perception.camera_height_m
    return rcfg.model_copy(update={"odometry": rcfg.odometry.model_copy(update={"visual_road_height_m": height})})


def _window_on_image(
    name: str, rcfg: ShgmConfig, sequence: Sequence, perception: object, written_by: dict | None
) -> ShgmConfig:
    """``rcfg`` with the visual odometry's corner-depth window grown to the image when the depth model ran
    on a smaller input (``visual.depth_window_on_image``); unchanged for measured depth or an unknown input."""
    model = getattr(perception, "depth_model", None)
    image_wh = (sequence.intrinsics.width, sequence.intrinsics.height)
    if model is not None:
        model_w = int(model.target_size(image_wh)[0])
    elif written_by is not None and isinstance(written_by.get("input_wh"), list) and written_by["input_wh"]:
        model_w = int(written_by["input_wh"][0])
    else:
        return rcfg
    window = rcfg.odometry.visual_depth_window_px
    on_image = depth_window_on_image(window, image_wh[0], model_w)
    if on_image == window:
        return rcfg
    log.info("%s: visual odometry corner-depth window %d px on the %d px wide images (%d px on the depth "
             "model's %d px input)", name, on_image, image_wh[0], window, model_w)  # fmt: skip
    return rcfg.model_copy(update={"odometry": rcfg.odometry.model_copy(update={"visual_depth_window_px": on_image})})
