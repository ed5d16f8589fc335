"""Perception stage: where each frame's metric depth and semantic labels come from.

Either the sequence's own files (``depth/`` and ``semantic/``, e.g. the simulator's ground truth)
or ONNX models (monocular depth, semantic segmentation) described by model cards; per modality a
model wins when configured, the files otherwise. The pipeline calls ``source.process(frame)`` per
frame and gets a ``PerceptionOutput``::

    source = make_perception(cfg.perception, sequence.has_depth, sequence.has_labels)
    out = source.process(frame)          # out.depth_m (H, W) float32 m, out.label_ids (H, W) uint8
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from shgm_slam.config import PerceptionConfig
from shgm_slam.errors import DataError
from shgm_slam.perception.card import DepthCard, SegmentationCard, load_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.ground_scale import GroundScale
from shgm_slam.perception.onnx_model import PerceptionTimings, measure_overhead
from shgm_slam.perception.segmentation import SegmentationModel
from shgm_slam.types import Frame, Sequence

__all__ = [
    "DepthCard",
    "DepthModel",
    "GroundScale",
    "OnnxPerception",
    "PerceptionOutput",
    "PerceptionSource",
    "PerceptionTimings",
    "SegmentationCard",
    "SegmentationModel",
    "SequenceFilesSource",
    "load_card",
    "make_perception",
    "measure_overhead",
]


@dataclass
class PerceptionOutput:
    """Depth and labels of one frame, on the frame's image grid.

    Attributes:
        depth_m: (H, W) float32 z-depth in metres, camera frame; 0 = invalid.
        label_ids: (H, W) uint8 Cityscapes train ids; 255 = ignore.
        timings_ms: per-step milliseconds (``depth_preprocess``, ``depth_inference``, ...; empty for files).
        depth_scale: the factor the predicted depth was multiplied by to put the road at the camera's
            known height (``ground_scale``); None when it was not scaled (files, no road plane yet, off).
    """

    depth_m: np.ndarray
    label_ids: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)
    depth_scale: float | None = None


@runtime_checkable
class PerceptionSource(Protocol):
    """Anything that turns a frame into depth + labels; ``reset`` forgets the frames it has seen (the depth scale
    it keeps over a window of frames), so that what it was shown before a run does not reach into the run."""

    def process(self, frame: Frame) -> PerceptionOutput: ...

    def reset(self) -> None: ...


def _file_depth(frame: Frame) -> np.ndarray:
    if frame.depth_m is None:
        raise DataError(
            f"frame {frame.index} has no depth (no depth/ files in the sequence) and no depth model is "
            "configured: set perception.depth_model to an .onnx model with a card"
        )
    return frame.depth_m


def _file_labels(frame: Frame) -> np.ndarray:
    if frame.label_ids is None:
        raise DataError(
            f"frame {frame.index} has no labels (no semantic/ files in the sequence) and no segmentation "
            "model is configured: set perception.seg_model to an .onnx model with a card"
        )
    return frame.label_ids


def _apply_ground_scale(
    ground_scale: GroundScale | None, depth_m: np.ndarray, label_ids: np.ndarray, frame: Frame
) -> tuple[np.ndarray, float | None]:
    """``depth_m`` scaled to put the road at the camera's height (``GroundScale``), and the factor (None:
    not scaled)."""
    if ground_scale is None:
        return depth_m, None
    factor = ground_scale.update(depth_m, label_ids, frame.intrinsics)
    if factor is None:
        return depth_m, None
    return depth_m * np.float32(factor), factor


class _GroundScaled:
    """A perception source whose predicted depth may be scaled to the road (``ground_scale``, or None)."""

    ground_scale: GroundScale | None

    def reset(self) -> None:
        """Forget the frames seen (``GroundScale.reset``)."""
        if self.ground_scale is not None:
            self.ground_scale.reset()


class SequenceFilesSource(_GroundScaled):
    """Depth and labels straight from the sequence's ``depth/`` and ``semantic/`` files.

    Args:
        ground_scale: for depth files a depth model wrote (``shgm-slam perceive``): scales them to a known
            camera height above the road, as ``OnnxPerception`` does; None for measured depth.
    """

    def __init__(self, ground_scale: GroundScale | None = None) -> None:
        self.ground_scale = ground_scale

    def process(self, frame: Frame) -> PerceptionOutput:
        """The frame's own ``depth_m`` and ``label_ids``; DataError naming the missing modality."""
        labels = _file_labels(frame)
        depth, factor = _apply_ground_scale(self.ground_scale, _file_depth(frame), labels, frame)
        return PerceptionOutput(depth, labels, {}, factor)


class OnnxPerception(_GroundScaled):
    """Depth and/or labels from ONNX models; a modality without a model comes from the frame's files.

    Args:
        depth_model: monocular depth adapter, or None to use the frame's ``depth_m``.
        seg_model: segmentation adapter, or None to use the frame's ``label_ids``.
        ground_scale: scales the depth to a known camera height above the road
            (``ground_scale.GroundScale``) when it is predicted (``make_perception`` decides), or None.
    """

    def __init__(
        self,
        depth_model: DepthModel | None = None,
        seg_model: SegmentationModel | None = None,
        ground_scale: GroundScale | None = None,
    ) -> None:
        self.depth_model = depth_model
        self.seg_model = seg_model
        self.ground_scale = ground_scale

    def process(self, frame: Frame) -> PerceptionOutput:
        """Run the configured models on ``frame.image_rgb``; timings keyed ``depth_*`` and ``seg_*``."""
        if frame.image_rgb is None and (self.depth_model or self.seg_model):
            raise DataError(f"frame {frame.index} has no image: the perception models need frame.image_rgb")
        timings: dict[str, float] = {}
        if self.depth_model is not None:
            depth = self.depth_model.predict(frame.image_rgb, frame.intrinsics)  # type: ignore[arg-type]
            timings.update(self.depth_model.last_timings.as_dict("depth_"))
        else:
            depth = _file_depth(frame)
        if self.seg_model is not None:
            labels = self.seg_model.predict(frame.image_rgb)  # type: ignore[arg-type]
            timings.update(self.seg_model.last_timings.as_dict("seg_"))
        else:
            labels = _file_labels(frame)
        depth, factor = _apply_ground_scale(self.ground_scale, depth, labels, frame)
        return PerceptionOutput(depth, labels, timings, factor)


def make_perception(
    cfg: PerceptionConfig,
    sequence_has_depth: bool | Sequence,
    sequence_has_labels: bool | None = None,
    *,
    files_depth_predicted: bool = False,
) -> SequenceFilesSource | OnnxPerception:
    """The perception source for a sequence: models where configured, the sequence's files elsewhere.

    Predicted depth (from ``cfg.depth_model``, or files a depth model wrote: ``files_depth_predicted``) is
    scaled to ``cfg.camera_height_m`` above the road where set (``ground_scale``); measured depth never is.

    Args:
        cfg: perception config (model paths, threads, camera height); cards sit next to the models.
        sequence_has_depth: whether the sequence has depth files, or the ``Sequence`` itself (then
            both flags are read from its ``has_depth`` / ``has_labels``).
        sequence_has_labels: whether the sequence has label files (omit when passing a ``Sequence``).
        files_depth_predicted: the sequence's depth files were written by a depth model
            (``perceive.depth_model_of``).

    Raises:
        DataError: a modality has neither files nor a model (the message names it and the config key).
        ModelError: a configured model or its card is missing or does not fit.
    """
    which = "the sequence"
    if isinstance(sequence_has_depth, Sequence):
        which = f"sequence {sequence_has_depth.name}"
        sequence_has_depth, sequence_has_labels = sequence_has_depth.has_depth, sequence_has_depth.has_labels
    if cfg.depth_model is None and not sequence_has_depth:
        raise DataError(
            f"{which} has no depth (no depth/ folder; in memory, no depth_m) and no depth model is configured: set "
            "perception.depth_model (an .onnx model with a YAML card next to it) or give depth (depth/ PNGs; depth_m)"
        )
    if cfg.seg_model is None and not sequence_has_labels:
        raise DataError(
            f"{which} has no labels (no semantic/ folder; in memory, no label_ids) and no segmentation model is "
            "configured: set perception.seg_model (an .onnx model with a YAML card next to it) or give labels "
            "(semantic/ PNGs; label_ids)"
        )
    predicted = cfg.depth_model is not None or files_depth_predicted
    ground = GroundScale(cfg.camera_height_m) if predicted and cfg.camera_height_m is not None else None
    if cfg.depth_model is None and cfg.seg_model is None:
        return SequenceFilesSource(ground)
    depth = DepthModel(cfg.depth_model, threads=cfg.threads) if cfg.depth_model is not None else None
    seg = SegmentationModel(cfg.seg_model, threads=cfg.threads) if cfg.seg_model is not None else None
    return OnnxPerception(depth, seg, ground)
