"""Whole-sequence checks before a run starts: a few frames' depth and labels, and the models' outputs.

A sequence whose every depth PNG has the wrong size, whose depth is all zeros, or whose depth model
gives NaN everywhere would otherwise start, skip (or use) every frame one by one and finish with exit 0
and a robot that never moved. ``check_sequence_start`` reads the first frames and a few spread over the
sequence through the robot's perception and raises one clear error when none of them is usable:

- no probed frame can be read or perceived (corrupt PNGs, wrong size or dtype, missing files): DataError;
- depth is (H, W) on the image grid but no probed pixel is valid (finite and > 0): DataError for depth
  files, ModelError naming the depth model;
- no probed label is a Cityscapes train id (0-18; all 255 = ignore, or garbage): DataError / ModelError;
- depth whose median over the probed frames is beyond ``MAX_MEDIAN_DEPTH_M`` and whose nearest tenth is beyond
  ``MAX_NEAR_DEPTH_M`` (not metres: millimetres):
  DataError, or ModelError naming the depth model;
- a model's output is constant over every probed frame (one depth value; one class, ignore (255) aside):
  ModelError, as ``shgm-slam check-model`` says;
- depth files that hold one value in every valid pixel of every probed frame (a sensor's saturation value or a
  placeholder written for every pixel): DataError. Such a "scene" is a sphere around the camera; KISS-ICP slid
  through it with no warning (65535 everywhere: a car's odometry 68 m off its path).

A single bad frame is not an error here (the run skips it with a reason); only a sequence none of whose
probed frames is usable is. Pure apart from reading frames through the ``Sequence`` protocol.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from shgm_slam.errors import DataError, ModelError
from shgm_slam.labels import IGNORE_ID, NUM_CLASSES, label_name
from shgm_slam.types import Frame, Sequence

FIRST_FRAMES = 3
"""Frames 0, 1, 2 are probed ..."""
SPREAD = (0.25, 0.5, 0.75)
"""... and these fractions of the sequence (a range that starts with a few bad frames is still accepted)."""

Perceive = Callable[[Frame], tuple[np.ndarray, np.ndarray | None]]


def probe_indices(num_frames: int) -> list[int]:
    """The frame indices ``check_sequence_start`` reads: the first few and a few spread over the sequence."""
    spread = [int(f * num_frames) for f in SPREAD]
    return sorted({i for i in [*range(FIRST_FRAMES), *spread] if 0 <= i < num_frames})


def check_sequence_start(
    name: str,
    sequence: Sequence,
    perceive: Perceive,
    *,
    depth_model: Path | str | None = None,
    seg_model: Path | str | None = None,
) -> None:
    """Raise when none of the probed frames (``probe_indices``) gives usable depth and labels.

    Args:
        name: the robot, for messages.
        sequence: its frames.
        perceive: frame -> (depth_m (H, W) metres, label_ids (H, W) train ids or None), e.g. the robot's
            perception source; a ``DataError`` it raises counts against that frame.
        depth_model, seg_model: the models the depth / labels come from (None: the sequence's files);
            their outputs' problems are ModelErrors naming them.

    Raises:
        DataError: no probed frame can be read, or the depth / label files hold nothing usable (depth files:
            also one value everywhere).
        ModelError: a model's output has no valid value or is constant on every probed frame.
    """
    indices = probe_indices(len(sequence))
    errors: list[str] = []
    depths: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    for index in indices:
        try:
            frame = sequence[index]
            depth, label = perceive(frame)
            depth = _checked_map(np.asarray(depth), frame, "depth", np.floating)
            if label is not None:
                labels.append(_checked_map(np.asarray(label), frame, "labels", np.integer))
        except DataError as exc:
            errors.append(f"frame {index}: {exc}")
            continue
        depths.append(depth)
    where = f"robot {name!r} ({sequence.name}), frames {', '.join(map(str, indices))}"
    if not depths:
        raise DataError(f"{where}: none can be used, so every frame would be skipped; first problem: {errors[0]}")
    valid = [np.isfinite(d) & (d > 0) for d in depths]
    if not any(v.any() for v in valid):
        if depth_model is not None:
            raise ModelError(
                f"depth model {depth_model}: no valid depth (every pixel non-finite or <= 0) on {where}; "
                "check the card's output kind and scale with shgm-slam check-model"
            )
        raise DataError(
            f"{where}: depth has no valid pixel (all 0 or non-finite); depth/ needs uint16 PNGs of "
            "metres x 256 with 0 = invalid"
        )
    values = np.concatenate([d[v] for d, v in zip(depths, valid, strict=True)])
    _check_depth_units(values, where, depth_model)
    constant_depth = values.size > 1 and values.min() == values.max()
    flat_frames = values.size > 1 and all(_one_value(d[v]) for d, v in zip(depths, valid, strict=True))
    if depth_model is not None:
        if constant_depth:
            raise ModelError(
                f"depth model {depth_model}: constant output ({values[0]:.3g} m everywhere) on {where}; "
                "check the model and its card (output kind, scale, clamp range) with shgm-slam check-model"
            )
        if flat_frames:
            raise ModelError(
                f"depth model {depth_model}: one value in each frame ({values.min():.3g}-{values.max():.3g} m "
                f"across frames, a 1x1 output resized to the image?) on {where}; check the model and its card "
                "(output name and size) with shgm-slam check-model"
            )
    if labels:
        known = [lab[lab < NUM_CLASSES] for lab in labels]  # train ids 0-18
        if not any(k.size for k in known):
            if seg_model is not None:
                raise ModelError(
                    f"segmentation model {seg_model}: every pixel maps to ignore (255) on {where}; check the "
                    "card's classes (model class -> Cityscapes train id) with shgm-slam check-model"
                )
            raise DataError(
                f"{where}: no label is a Cityscapes train id 0-18 (all 255 = ignore, or other values); "
                "semantic/ needs uint8 PNGs of train ids"
            )
        if seg_model is None:
            _check_label_space(labels, where)
        flat = np.concatenate(known)  # ignore (255) is no class: one class and ignore is still one class
        if seg_model is not None and flat.size > 1 and flat.min() == flat.max():
            raise ModelError(
                f"segmentation model {seg_model}: constant output (train id {flat[0]}, {label_name(int(flat[0]))}, "
                f"wherever not ignore) on {where}; a graph of one class cannot be matched: check the model and "
                "its card (classes: one per class the model outputs) with shgm-slam check-model"
            )
    if flat_frames and depth_model is None:  # after the labels: their errors say more about such files
        what = f"{values[0]:.6g} m" if constant_depth else f"one value ({values.min():.6g}-{values.max():.6g} m)"
        raise DataError(
            f"{where}: depth is {what} in every valid pixel of each frame (a sensor's saturated or placeholder "
            "value, never a measured scene); depth/ needs uint16 PNGs of metres x 256 with 0 = invalid: re-export "
            "it, or remove depth/ and set a depth model"
        )


MAX_MEDIAN_DEPTH_M = 2000.0
"""Probed frames whose valid depths have a median beyond this are refused: depth not in metres (a street in
millimetres is 5,000-50,000 "m"; a UAV at 115 m sees its ground at 120-250 m). Such depth ran to the end with an
odometry that did not move and no graph nodes (everything beyond the extraction range). The pixels at the largest
probed value are left out of the median: a sensor's or renderer's one value for the sky (1e4 m, 65504 m) may be most
of a frame that looks at the horizon."""


MAX_NEAR_DEPTH_M = 200.0
"""...unless the nearest tenth of those depths (``NEAR_DEPTH_QUANTILE``) lies within this: a scene whose median is
far only because a varying sky (a network's, a renderer's per-pixel far values) covers most of the frame still has
its ground and objects near (a car's road at 4-20 m, a UAV's at its altitude), while a street in millimetres has
its nearest tenth at thousands of "metres"."""

NEAR_DEPTH_QUANTILE = 0.1
"""Quantile of the probed valid depths read as the scene's near part (``MAX_NEAR_DEPTH_M``)."""


def _check_depth_units(depth_m: np.ndarray, where: str, depth_model: Path | str | None) -> None:
    """Raise when (K,) valid depths ``depth_m`` of the probed frames, those at their largest value (the sky) left
    out, have a median beyond ``MAX_MEDIAN_DEPTH_M`` and their nearest tenth beyond ``MAX_NEAR_DEPTH_M``: a
    ModelError naming ``depth_model`` (its card's scale), else a DataError (depth given in other units)."""
    scene_m = depth_m[depth_m < depth_m.max()]
    scene_m = scene_m if scene_m.size else depth_m
    median_m = float(np.median(scene_m))
    if median_m <= MAX_MEDIAN_DEPTH_M or float(np.quantile(scene_m, NEAR_DEPTH_QUANTILE)) <= MAX_NEAR_DEPTH_M:
        return
    seen = f"median valid depth {median_m:.4g} m on {where}, farther than any camera's scene ({MAX_MEDIAN_DEPTH_M:g} m)"
    if depth_model is not None:
        raise ModelError(f"depth model {depth_model}: {seen}; check the card's output kind and scale with "
                         "shgm-slam check-model")  # fmt: skip
    raise DataError(f"{seen}: depth must be in metres (in millimetres? divide it by 1000)")


ONE_VALUE_SPAN = 1e-6
"""A frame's valid depths spanning at most this fraction of their largest are one value (a 1x1 output resized to the
image in float32 spans ~2e-7 of it)."""


def _one_value(depth_m: np.ndarray) -> bool:
    """(K,) valid depths, metres, of one frame: one value within float noise (``ONE_VALUE_SPAN``); an empty frame
    says nothing against the others (True)."""
    if depth_m.size == 0:
        return True
    return float(depth_m.max() - depth_m.min()) <= ONE_VALUE_SPAN * max(float(np.abs(depth_m).max()), 1.0)


def _check_label_space(labels: list[np.ndarray], where: str) -> None:
    """DataError when more than ``MAX_FOREIGN_LABEL_SHARE`` of the probed label pixels are neither a train id
    (0-18) nor ignore (255): the files are in another label space (Cityscapes' full label ids 0-33 put road at
    7, a train id's traffic sign), and even their values in 0-18 would be read as the wrong classes."""
    flat = np.concatenate([lab.ravel() for lab in labels])
    foreign = (flat >= NUM_CLASSES) & (flat != IGNORE_ID)
    if foreign.mean() > MAX_FOREIGN_LABEL_SHARE:
        values = np.unique(flat[foreign])
        shown = ", ".join(map(str, values[:8])) + (", ..." if values.size > 8 else "")
        raise DataError(
            f"{where}: {100 * foreign.mean():.0f} % of the label pixels are {shown}, no Cityscapes train id "
            "(0-18, 255 = ignore); semantic/ needs train ids: are these Cityscapes label ids (0-33)? Map them "
            "to train ids (cityscapesscripts' labels.py: id -> trainId)"
        )


MAX_FOREIGN_LABEL_SHARE = 0.01
"""Share of label pixels outside 0-18 and 255 beyond which label files are refused as another label space."""


def _checked_map(array: np.ndarray, frame: Frame, what: str, kind: type) -> np.ndarray:
    """``array`` when it is (H, W) of ``kind`` on the frame's image grid; DataError otherwise."""
    if array.ndim != 2 or not np.issubdtype(array.dtype, kind):
        raise DataError(f"{what} is {array.dtype} with shape {array.shape}; expected (H, W) {kind.__name__}")
    if frame.image_rgb is not None and array.shape != frame.image_rgb.shape[:2]:
        h, w = frame.image_rgb.shape[:2]
        raise DataError(f"{what} is {array.shape[1]}x{array.shape[0]} but the image is {w}x{h}")
    return array
