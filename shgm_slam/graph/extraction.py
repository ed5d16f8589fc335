"""Object extraction: semantic objects (graph node candidates) from one depth + label frame.

Sec. III-A of the paper segments objects per class with seed filling and splits neighbouring objects
of the same class with the pixels' 3D coordinates; the authors' release flood-fills 4-connected
pixels across depth steps below 1 m, up to 30 m, and keeps blobs above 5000 px at 1024x576.

Here an object is exactly a connected component of the 4-neighbour pixel graph whose edges join
pixels that are both valid (depth in (min, max], label in the kept set), share the label and differ
in depth by less than ``depth_step_m``. The components are found in one OpenCV pass over a
(2H-1, 2W-1) "link grid": pixels sit on even/even cells and each kept 4-neighbour link on the cell
between its two pixels, so 4-connected labelling of that grid is the pixel graph's components.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from shgm_slam.config import ExtractionConfig
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import transform_points
from shgm_slam.types import Frame, Intrinsics

EXTENT_PERCENTILES = (5.0, 95.0)
"""Robust object extent: the spread between these percentiles of its 3D points, per camera axis."""

MAX_EXTENT_SAMPLES = 8000
"""Extent percentiles use a pixel grid of about this many samples per frame..."""

MIN_EXTENT_SAMPLES = 32
"""...and every pixel of objects that the grid hits fewer times than this."""


@dataclass
class ObjectObservations:
    """Objects seen in one frame (M objects).

    Attributes:
        label_ids: (M,) int64 Cityscapes train ids.
        centroids_cam: (M, 3) float64 mean of the object's back-projected pixels, camera frame, metres.
        centroids_world: (M, 3) float64 the same centroids mapped by the frame's ``T_world_cam``.
        pixel_counts: (M,) int64 number of pixels of the object (its size, weights Eq. 2).
        extents_m: (M, 3) float64 robust 3D extent along camera x, y, z (5-95 percentile spread), metres.
    """

    label_ids: np.ndarray
    centroids_cam: np.ndarray
    centroids_world: np.ndarray
    pixel_counts: np.ndarray
    extents_m: np.ndarray

    def __len__(self) -> int:
        return int(self.label_ids.shape[0])

    @staticmethod
    def empty() -> ObjectObservations:
        """No objects (all arrays with M = 0)."""
        z3 = np.zeros((0, 3))
        return ObjectObservations(
            np.zeros(0, np.int64), z3, z3.copy(), np.zeros(0, np.int64), z3.copy()
        )

    def subset(self, rows: np.ndarray) -> ObjectObservations:
        """The objects at ``rows`` (indices or boolean mask)."""
        return ObjectObservations(
            self.label_ids[rows], self.centroids_cam[rows], self.centroids_world[rows],
            self.pixel_counts[rows], self.extents_m[rows],
        )  # fmt: skip


def min_blob_pixels(min_blob_fraction: float, width: int, height: int) -> int:
    """Minimum object size in pixels for a ``width`` x ``height`` image (the fraction of its area, >= 1)."""
    return max(1, int(np.ceil(min_blob_fraction * width * height)))


def _check_inputs(depth_m: np.ndarray, label_ids: np.ndarray, intrinsics: Intrinsics) -> None:
    if depth_m.ndim != 2 or label_ids.shape != depth_m.shape:
        raise DataError(
            f"object extraction needs (H, W) depth and labels of the same shape, got depth {depth_m.shape} "
            f"and labels {label_ids.shape}; resize the label image to the depth image"
        )
    H, W = depth_m.shape
    if (intrinsics.width, intrinsics.height) != (W, H):
        raise DataError(
            f"depth is {W}x{H} px but the intrinsics are for {intrinsics.width}x{intrinsics.height}; "
            "pass intrinsics.scaled(W, H)"
        )
    if label_ids.dtype != np.uint8 and label_ids.size and (label_ids.min() < 0 or label_ids.max() > 255):
        lo, hi = label_ids.min(), label_ids.max()
        raise DataError(f"label ids must be Cityscapes train ids in 0..255, got range {lo}..{hi}")


def _components(
    depth_m: np.ndarray, labels_u8: np.ndarray, valid: np.ndarray, depth_step_m: float
) -> tuple[int, np.ndarray, np.ndarray]:
    """Connected components of the valid, same-label, depth-continuous 4-neighbour pixel graph.

    Returns the number of component ids (0 = background, invalid pixels), the (H, W) int32 ids and
    the (H, W) float32 depth with NaN at invalid pixels.
    """
    H, W = depth_m.shape
    depth_nan = np.where(valid, depth_m, np.float32(np.nan))  # NaN never passes the depth-step test
    link_h = cv2.compare(labels_u8[:, :-1], labels_u8[:, 1:], cv2.CMP_EQ)
    cv2.bitwise_and(link_h, cv2.compare(cv2.absdiff(depth_nan[:, :-1], depth_nan[:, 1:]), depth_step_m,
                                        cv2.CMP_LT), dst=link_h)  # fmt: skip
    link_v = cv2.compare(labels_u8[:-1], labels_u8[1:], cv2.CMP_EQ)
    cv2.bitwise_and(link_v, cv2.compare(cv2.absdiff(depth_nan[:-1], depth_nan[1:]), depth_step_m,
                                        cv2.CMP_LT), dst=link_v)  # fmt: skip
    grid = np.zeros((2 * H - 1, 2 * W - 1), dtype=np.uint8)
    grid[::2, ::2] = valid
    grid[::2, 1::2] = link_h
    grid[1::2, ::2] = link_v
    n, comp_grid = cv2.connectedComponentsWithAlgorithm(grid, 4, cv2.CV_32S, cv2.CCL_WU)
    return int(n), comp_grid[::2, ::2], depth_nan


def _group_spread(groups: np.ndarray, values: np.ndarray, num_groups: int) -> np.ndarray:
    """Per-group spread between the EXTENT_PERCENTILES (nearest rank) of ``values``; groups non-empty."""
    span = float(values.max() - values.min()) + 1.0 if values.size else 1.0
    key = np.sort(groups * span + (values - values.min()))  # one sort orders by group, then value
    sorted_values = key - np.sort(groups) * span + values.min()
    counts = np.bincount(groups, minlength=num_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo = sorted_values[starts + np.rint(EXTENT_PERCENTILES[0] / 100.0 * (counts - 1)).astype(np.int64)]
    hi = sorted_values[starts + np.rint(EXTENT_PERCENTILES[1] / 100.0 * (counts - 1)).astype(np.int64)]
    return hi - lo


def _group_percentile(comp_flat: np.ndarray, values: np.ndarray, ids: np.ndarray, percentile: float) -> np.ndarray:
    """(K,) the ``percentile`` (nearest rank) of ``values`` over the pixels of each component in (K,) ``ids``."""
    sorted_ids = np.sort(ids)
    rows = np.flatnonzero(np.isin(comp_flat, ids))
    group = np.searchsorted(sorted_ids, comp_flat[rows])
    order = np.lexsort((values[rows], group))
    counts = np.bincount(group, minlength=ids.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    picked = values[rows][order][starts + np.rint(percentile / 100.0 * (counts - 1)).astype(np.int64)]
    return picked[np.searchsorted(sorted_ids, ids)]


def extract_objects(
    depth_m: np.ndarray,
    label_ids: np.ndarray,
    intrinsics: Intrinsics,
    T_world_cam: np.ndarray | None,
    *,
    labels: Iterable[int],
    max_depth_m: float = 30.0,
    min_depth_m: float = 0.5,
    depth_step_m: float = 1.0,
    min_blob_fraction: float = 5000.0 / (1024 * 576),
    depth_percentiles: Mapping[int, float] | None = None,
) -> ObjectObservations:
    """Segment one frame into semantic objects and return their 3D centroids (Sec. III-A, graph nodes).

    Args:
        depth_m: (H, W) metric z-depth; 0, negative or non-finite is invalid (never an error).
        label_ids: (H, W) integer Cityscapes train ids (uint8 preferred).
        intrinsics: pinhole intrinsics for this W x H image.
        T_world_cam: (4, 4) pose of the camera in the world (None = identity: world = camera frame).
        labels: train ids that become objects; other labels are ignored.
        max_depth_m, min_depth_m: pixels with depth outside (min, max] are ignored.
        depth_step_m: 4-neighbours of one label join only if their depths differ by less than this.
        min_blob_fraction: objects need at least this fraction of the image area in pixels.
        depth_percentiles: train id -> percentile: objects of these labels are placed on the ray through their
            centroid at that percentile (nearest rank) of their pixels' depths instead of the mean (thin objects
            in predicted depth, which blends them with the background: ``ExtractionConfig``); None: the mean.

    Returns:
        The objects, ordered by the raster position of their first pixel.

    Raises:
        DataError: the images do not have matching (H, W) shapes or do not fit the intrinsics.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    lab = np.asarray(label_ids)
    _check_inputs(depth, lab, intrinsics)
    lab = lab.astype(np.uint8, copy=False)
    H, W = depth.shape

    label_list = np.asarray(list(labels), dtype=np.int64)
    if label_list.size and (label_list.min() < 0 or label_list.max() > 255):
        raise ConfigError(f"extraction labels must be train ids in 0..255, got {label_list.tolist()}")
    keep_label = np.zeros(256, dtype=bool)
    keep_label[label_list] = True
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > max(min_depth_m, 0.0)) & (depth <= max_depth_m)
    valid &= keep_label[lab]

    n_comp, comp, depth_nan = _components(depth, lab, valid, depth_step_m)
    # Per-component sums over row runs of equal id (a few thousand runs instead of H*W scattered adds).
    comp_flat = comp.ravel()
    starts = np.flatnonzero(np.concatenate(([True], comp_flat[1:] != comp_flat[:-1])))
    run_comp = comp_flat[starts]

    def component_sums(per_pixel: np.ndarray) -> np.ndarray:
        return np.bincount(run_comp, np.add.reduceat(per_pixel.ravel(), starts), minlength=n_comp)

    counts = np.bincount(run_comp, np.diff(np.append(starts, comp_flat.size)), minlength=n_comp)
    counts = counts.astype(np.int64)
    keep = counts >= min_blob_pixels(min_blob_fraction, W, H)
    keep[0] = False
    kept_ids = np.flatnonzero(keep)
    if kept_ids.size == 0:
        return ObjectObservations.empty()
    M = kept_ids.size

    # Centroids = means of the back-projected pixels (the pinhole model of geometry.camera.backproject),
    # from per-component sums of z, u*z and v*z; invalid pixels (NaN) all sit in component 0.
    z = depth_nan.astype(np.float64)
    n_px = counts[kept_ids].astype(np.float64)
    z_mean = component_sums(z)[kept_ids] / n_px
    uz_mean = component_sums(z * np.arange(W, dtype=np.float64))[kept_ids] / n_px
    vz_mean = component_sums(z * np.arange(H, dtype=np.float64)[:, None])[kept_ids] / n_px
    centroids_cam = np.stack(
        [
            (uz_mean - intrinsics.cx * z_mean) / intrinsics.fx,
            (vz_mean - intrinsics.cy * z_mean) / intrinsics.fy,
            z_mean,
        ],
        axis=1,
    )

    # Labels and robust extents from a strided pixel sample (every pixel of objects it barely hits).
    compact = np.full(n_comp, -1, dtype=np.int64)
    compact[kept_ids] = np.arange(M)
    stride = max(1, int(np.sqrt(H * W / MAX_EXTENT_SAMPLES)))
    v, u = np.mgrid[0:H:stride, 0:W:stride]
    obj = compact[comp[v, u]]
    sparse = np.bincount(obj[obj >= 0], minlength=M) < MIN_EXTENT_SAMPLES
    if sparse.any():
        add_v, add_u = np.nonzero(np.isin(comp, kept_ids[sparse]))
        drop = (obj >= 0) & sparse[obj]
        v, u = np.concatenate([v[~drop], add_v]), np.concatenate([u[~drop], add_u])
    else:
        v, u = v.ravel(), u.ravel()
    obj = compact[comp[v, u]]
    hit = obj >= 0
    v, u, obj = v[hit], u[hit], obj[hit]
    z_s = z[v, u]
    x_s, y_s = (u - intrinsics.cx) * z_s / intrinsics.fx, (v - intrinsics.cy) * z_s / intrinsics.fy
    points = np.stack([x_s, y_s, z_s], axis=1)
    extents = np.stack([_group_spread(obj, points[:, k], M) for k in range(3)], axis=1)
    label_of_obj = np.zeros(M, dtype=np.int64)
    label_of_obj[obj] = lab[v, u]

    for percentile in sorted(set((depth_percentiles or {}).values())):
        chosen = [label for label, q in depth_percentiles.items() if q == percentile]
        rows = np.flatnonzero(np.isin(label_of_obj, np.asarray(chosen, dtype=np.int64)))
        if rows.size:
            z_q = _group_percentile(comp.ravel(), z.ravel(), kept_ids[rows], percentile)
            centroids_cam[rows] *= (z_q / centroids_cam[rows, 2])[:, None]

    T = np.eye(4) if T_world_cam is None else np.asarray(T_world_cam, dtype=np.float64)
    return ObjectObservations(
        label_ids=label_of_obj,
        centroids_cam=centroids_cam,
        centroids_world=transform_points(T, centroids_cam),
        pixel_counts=counts[kept_ids].astype(np.int64),
        extents_m=extents,
    )


def extract_objects_from_config(
    frame: Frame, cfg: ExtractionConfig, T_world_cam: np.ndarray | None = None, *, depth_predicted: bool = False
) -> ObjectObservations:
    """``extract_objects`` on a ``Frame`` with an ``ExtractionConfig``.

    ``T_world_cam`` overrides the frame's (ground-truth) pose, e.g. with an odometry estimate; when
    both are None the centroids stay in the camera frame. Data-derived fields still None (``scene_scale``)
    take the fleet values. ``depth_predicted``: the frame's depth comes from a depth model, so thin objects
    take ``cfg.predicted_depth_percentiles`` (measured depth keeps the mean).

    Raises:
        DataError: the frame carries no depth or no labels.
    """
    if frame.depth_m is None or frame.label_ids is None:
        missing = "depth" if frame.depth_m is None else "labels"
        raise DataError(
            f"frame {frame.index} has no {missing}; object extraction needs depth/ and semantic/ images "
            "(or the perception models to predict them)"
        )
    cfg = cfg.filled()
    intrinsics = frame.intrinsics
    if (intrinsics.width, intrinsics.height) != (frame.depth_m.shape[1], frame.depth_m.shape[0]):
        intrinsics = intrinsics.scaled(frame.depth_m.shape[1], frame.depth_m.shape[0])
    return extract_objects(
        frame.depth_m, frame.label_ids, intrinsics,
        T_world_cam if T_world_cam is not None else frame.T_world_cam,
        labels=cfg.labels, max_depth_m=cfg.max_depth_m, min_depth_m=cfg.min_depth_m,
        depth_step_m=cfg.depth_step_m, min_blob_fraction=cfg.min_blob_fraction,
        depth_percentiles=cfg.depth_percentiles(depth_predicted),
    )  # fmt: skip
