"""Perception-like corruption of perfect depth and labels, for the sensitivity study (paper Fig. 8 e, f).

Pure functions of their inputs and an ``np.random.Generator``: depth gets a range-proportional
Gaussian error (optionally spatially correlated, like a network's) and a global scale error; labels get
ragged class boundaries and whole-segment confusions between classes a segmentation network mixes up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shgm_slam.errors import SimulationError
from shgm_slam.labels import Label

CONFUSIONS: dict[int, tuple[int, ...]] = {
    Label.ROAD: (Label.SIDEWALK,),
    Label.SIDEWALK: (Label.ROAD, Label.TERRAIN),
    Label.BUILDING: (Label.WALL,),
    Label.WALL: (Label.BUILDING, Label.FENCE),
    Label.FENCE: (Label.WALL, Label.VEGETATION),
    Label.POLE: (Label.TRAFFIC_SIGN, Label.BUILDING),
    Label.TRAFFIC_LIGHT: (Label.POLE, Label.TRAFFIC_SIGN),
    Label.TRAFFIC_SIGN: (Label.POLE, Label.TRAFFIC_LIGHT),
    Label.VEGETATION: (Label.TERRAIN, Label.BUILDING),
    Label.TERRAIN: (Label.VEGETATION, Label.SIDEWALK),
    Label.CAR: (Label.TRUCK,),
    Label.TRUCK: (Label.CAR, Label.BUS),
    Label.BUS: (Label.TRUCK,),
}
"""Classes each train id is plausibly mistaken for (sky and others are never confused)."""


@dataclass(frozen=True)
class CorruptionLevels:
    """How much to corrupt; all zero = perfect ground truth.

    Attributes:
        depth_noise: std of the depth error relative to the depth (0.05 = 5 % of range).
        depth_scale_error: global relative scale error (0.1 = every depth 10 % too large).
        depth_correlation_px: smoothing radius of the depth error field (0 = independent pixels).
        label_confusion: probability that a whole segment (object) is relabelled to a confusable class.
        label_boundary_px: class boundaries are jittered by up to this many pixels.
    """

    depth_noise: float = 0.0
    depth_scale_error: float = 0.0
    depth_correlation_px: float = 0.0
    label_confusion: float = 0.0
    label_boundary_px: int = 0

    def __post_init__(self) -> None:
        if self.depth_noise < 0 or self.depth_correlation_px < 0 or self.label_boundary_px < 0:
            raise SimulationError("depth noise, correlation and label boundary corruption must be >= 0")
        if not 0.0 <= self.label_confusion <= 1.0:
            raise SimulationError(f"label confusion is a probability in 0..1, got {self.label_confusion}")
        if self.depth_scale_error <= -1.0:
            raise SimulationError(f"depth scale error must be > -1, got {self.depth_scale_error}")

    @staticmethod
    def from_levels(depth_noise: float = 0.0, label_noise: float = 0.0) -> CorruptionLevels:
        """The CLI's two knobs: ``depth_noise`` = relative depth std (correlated over 4 px);
        ``label_noise`` = segment confusion probability, boundaries jittered by ``round(10 * p)`` px."""
        return CorruptionLevels(
            depth_noise=depth_noise,
            depth_correlation_px=4.0 if depth_noise > 0 else 0.0,
            label_confusion=label_noise,
            label_boundary_px=round(10 * label_noise),
        )

    @property
    def active(self) -> bool:
        return any((self.depth_noise, self.depth_scale_error, self.label_confusion, self.label_boundary_px))


def corrupt_depth(
    depth_m: np.ndarray,
    rng: np.random.Generator,
    *,
    noise_rel: float = 0.0,
    scale_error: float = 0.0,
    correlation_px: float = 0.0,
) -> np.ndarray:
    """(H, W) float32 depth with error ``d * (scale_error + noise_rel * e)``, e a unit Gaussian field
    (smoothed over ``correlation_px`` and renormalized when > 0). Invalid (0) pixels stay 0."""
    d = np.asarray(depth_m, dtype=np.float32)
    e = rng.standard_normal(d.shape).astype(np.float32)
    if correlation_px > 0:
        e = cv2.GaussianBlur(e, (0, 0), correlation_px)
        e /= max(float(e.std()), 1e-6)
    out = d * (1.0 + scale_error + noise_rel * e)
    return np.where(d > 0, np.maximum(out, 1e-3), 0.0).astype(np.float32)


def corrupt_labels(
    label_ids: np.ndarray,
    rng: np.random.Generator,
    *,
    confusion_prob: float = 0.0,
    boundary_px: int = 0,
    segments: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) uint8 labels with whole-segment confusions and ragged class boundaries.

    Args:
        label_ids: (H, W) uint8 train ids.
        confusion_prob: per segment, the probability of relabelling it to one of ``CONFUSIONS[label]``.
        boundary_px: pixels within this distance of a class boundary take the label of a random
            pixel up to this far away (boundaries erode and dilate irregularly).
        segments: (H, W) int segment ids (e.g. rendered object ids); default: 16x16 tiles per class.
    """
    lab = np.asarray(label_ids, dtype=np.uint8)
    H, W = lab.shape
    out = lab.copy()
    if confusion_prob > 0:
        if segments is None:
            v, u = np.mgrid[0:H, 0:W]
            segments = (v // 16) * ((W + 15) // 16) + u // 16
        key = np.asarray(segments, np.int64) * 256 + lab
        uniq, inv = np.unique(key.ravel(), return_inverse=True)
        seg_label = (uniq % 256).astype(np.uint8)
        new = seg_label.copy()
        flip = rng.random(len(uniq)) < confusion_prob
        pick = rng.random(len(uniq))
        for k in np.flatnonzero(flip):
            options = CONFUSIONS.get(int(seg_label[k]))
            if options:
                new[k] = options[int(pick[k] * len(options))]
        out = new[inv].reshape(H, W)
    if boundary_px > 0:
        b = int(boundary_px)
        edge = np.zeros((H, W), bool)
        edge[:, 1:] |= out[:, 1:] != out[:, :-1]
        edge[1:, :] |= out[1:, :] != out[:-1, :]
        near = cv2.dilate(edge.astype(np.uint8), np.ones((2 * b + 1, 2 * b + 1), np.uint8)) > 0
        v, u = np.nonzero(near)
        # a smooth random displacement field keeps the ragged boundaries blob-like, not salt-and-pepper
        field = rng.standard_normal((2, H, W)).astype(np.float32)
        field = np.stack([cv2.GaussianBlur(f, (0, 0), max(1.0, b / 2)) for f in field])
        field /= max(float(field.std()), 1e-6)
        dv = np.clip(np.rint(field[0, v, u] * b / 2), -b, b).astype(int)
        du = np.clip(np.rint(field[1, v, u] * b / 2), -b, b).astype(int)
        src = out.copy()
        out[v, u] = src[np.clip(v + dv, 0, H - 1), np.clip(u + du, 0, W - 1)]
    return out


def apply_corruption(
    depth_m: np.ndarray,
    label_ids: np.ndarray,
    levels: CorruptionLevels,
    rng: np.random.Generator,
    segments: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Corrupt one frame's depth and labels by ``levels`` (returns the inputs unchanged when inactive)."""
    if not levels.active:
        return depth_m, label_ids
    depth = corrupt_depth(
        depth_m,
        rng,
        noise_rel=levels.depth_noise,
        scale_error=levels.depth_scale_error,
        correlation_px=levels.depth_correlation_px,
    )
    labels = corrupt_labels(
        label_ids,
        rng,
        confusion_prob=levels.label_confusion,
        boundary_px=levels.label_boundary_px,
        segments=segments,
    )
    return depth, labels
