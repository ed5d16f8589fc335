"""Monocular depth from an ONNX model: RGB image -> metric z-depth in metres.

The card's ``output.kind`` says what the network predicts (metric depth, inverse depth, relative
depth with a known scale/shift, or stereo-style disparity) and the adapter converts it to metres,
undoes the input resize/pad/crop and returns a depth map on the image grid (0 = invalid).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import cv2
import numpy as np

from shgm_slam.errors import ModelError
from shgm_slam.perception.card import DepthCard, DepthKind, Layout, TaskKind
from shgm_slam.perception.onnx_model import (
    _FLOAT_TYPES,
    OnnxModel,
    PerceptionTimings,
    TensorSpec,
)
from shgm_slam.perception.resize import ResizePlan, paste_back
from shgm_slam.types import Intrinsics


class DepthModel(OnnxModel):
    """A monocular depth network behind its card.

    Args:
        model_path: the .onnx file; its card is the YAML with the same stem unless ``card`` is given.
        card: a ``DepthCard``, a card path, or None.
        threads: intra-op threads (0 = onnxruntime default).

    Example:
        >>> model = DepthModel("models/depth.onnx")
        >>> depth_m = model.predict(frame.image_rgb, frame.intrinsics)   # (H, W) float32, 0 = invalid
    """

    task = TaskKind.DEPTH
    card: DepthCard

    def _check_output(self, output: TensorSpec) -> None:
        shape = output.shape
        if len(shape) not in (2, 3, 4):  # (H, W): a model without an output batch axis, fed one image per call
            raise ModelError(
                f"{self.where}: depth output '{output.name}' has rank {len(shape)} (shape {list(shape)}); "
                "expected (N, H, W), (N, 1, H, W), (N, H, W, 1) or (H, W): set output.name to the depth output"
            )
        if len(shape) == 4 and all(isinstance(shape[a], int) and shape[a] != 1 for a in (1, 3)):
            raise ModelError(
                f"{self.where}: depth output '{output.name}' (shape {list(shape)}) has no single channel on "
                "axis 1 (NCHW) or 3 (NHWC); a depth map has one: set output.name to the depth output"
            )
        if output.type not in _FLOAT_TYPES:
            raise ModelError(
                f"{self.where}: depth output '{output.name}' is {output.type}; expected a float tensor: set "
                "output.name to the depth output, or export the depth as float"
            )

    @property
    def needs_intrinsics(self) -> bool:
        """True when depth needs the frame's fx (disparity cards with ``baseline_m``)."""
        return self.card.output.kind is DepthKind.DISPARITY and self.card.output.baseline_m is not None

    def predict(self, image_rgb: np.ndarray, intrinsics: Intrinsics | None = None) -> np.ndarray:
        """Depth of one image.

        Args:
            image_rgb: (H, W, 3) uint8 RGB.
            intrinsics: the image's intrinsics; needed only for disparity cards with ``baseline_m``.

        Returns:
            (H, W) float32 z-depth in metres on the image grid; 0 = invalid or not seen by the model.
        """
        return self.predict_batch([image_rgb], intrinsics)[0]

    def predict_batch(
        self, images_rgb: Sequence[np.ndarray], intrinsics: Intrinsics | None = None
    ) -> list[np.ndarray]:
        """Depth of several images in one session run (chunked when the model's batch axis is fixed).

        Returns:
            list of (H, W) float32 depth maps in metres, one per image.
        """
        if self.needs_intrinsics and intrinsics is None:
            raise ModelError(
                f"{self.where}: the card's output.baseline_m needs the image intrinsics (fx): pass "
                "intrinsics= or give output.focal_x_baseline in the card"
            )
        out, plans, pre_ms, inf_ms = self._run(images_rgb)
        t0 = time.perf_counter()
        maps = self._squeeze(out)
        depths = [self._postprocess(m, plan, intrinsics) for m, plan in zip(maps, plans, strict=True)]
        self.last_timings = PerceptionTimings(pre_ms, inf_ms, (time.perf_counter() - t0) * 1e3)
        return depths

    def _squeeze(self, out: np.ndarray) -> np.ndarray:
        """(N, h, w) from (N, h, w), (N, 1, h, w) or (N, h, w, 1) (the input layout's axis first)."""
        if out.ndim == 3:
            return out
        axes = (1, 3) if self.card.input.layout is Layout.NCHW else (3, 1)
        for axis in axes:
            if out.ndim == 4 and out.shape[axis] == 1:
                return out[:, 0] if axis == 1 else out[..., 0]
        raise ModelError(f"{self.where}: depth output has shape {list(out.shape)}; expected one channel")

    def _postprocess(self, raw: np.ndarray, plan: ResizePlan, intrinsics: Intrinsics | None) -> np.ndarray:
        """Model output (h, w) -> metric depth (H, W) on the image grid."""
        bx0, by0, bx1, by1 = plan.output_box((raw.shape[1], raw.shape[0]))
        x = raw[by0:by1, bx0:bx1].astype(np.float32, copy=False)
        depth = self.to_metric(x, plan, intrinsics)
        valid = depth > 0
        return paste_back(depth, plan, 0.0, cv2.INTER_LINEAR, valid=valid)

    def to_metric(self, x: np.ndarray, plan: ResizePlan, intrinsics: Intrinsics | None = None) -> np.ndarray:
        """Convert raw output values to metres per the card; invalid (non-finite, <= 0) -> 0, else clamped
        to [min_depth_m, max_depth_m]. Disparity is in model-input pixels (``plan`` gives the resize)."""
        spec = self.card.output
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if spec.kind is DepthKind.METRIC:
                depth = x
            elif spec.kind is DepthKind.RELATIVE:
                depth = spec.scale * x + spec.shift
            elif spec.kind is DepthKind.INVERSE:
                depth = 1.0 / (spec.scale * x + spec.shift)
            else:
                depth = self._focal_baseline(plan, intrinsics) * plan.scale_x / x
            depth = np.asarray(depth, dtype=np.float32)
            ok = np.isfinite(depth) & (depth > 0)
        return np.where(ok, np.clip(depth, spec.min_depth_m, spec.max_depth_m), 0.0).astype(np.float32)

    def _focal_baseline(self, plan: ResizePlan, intrinsics: Intrinsics | None) -> float:
        """fx * baseline in image pixels * metres."""
        spec = self.card.output
        if spec.focal_x_baseline is not None:
            return spec.focal_x_baseline
        if intrinsics is None or spec.baseline_m is None:
            raise ModelError(
                f"{self.where}: disparity needs output.focal_x_baseline, or baseline_m and intrinsics"
            )
        fx_image = intrinsics.fx * plan.image_wh[0] / intrinsics.width
        return fx_image * spec.baseline_m
