"""Per-robot scale of the scene from its first frames: camera height, depth spread, derived defaults.

A car camera 1.6 m above the road and a UAV camera 50 m up looking 50 deg down see the same city at
ranges an order of magnitude apart; the extraction range, the minimum blob size and the odometry voxel
must follow. ``measure_scene_scale`` fits the ground plane (road, sidewalk and terrain pixels; the lowest
image rows when there are no ground labels) of a few frames: its distance from the camera is the
camera's height, and intersecting the image corners' rays with it gives the depth of the nearest and
the range of the farthest ground in view. ``resolve_robot_config`` fills the config fields left None
from that geometry (rules in the fields' descriptions, ``config.py``); values set in a config win.

Pure: arrays in, numbers out (no IO, no logging); ``sample_scene_scale`` reads frames through the
sequence protocol and a perception callable.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from shgm_slam.config import ExtractionConfig, OdometryConfig, ShgmConfig
from shgm_slam.errors import DataError
from shgm_slam.geometry.camera import backproject
from shgm_slam.labels import Label
from shgm_slam.types import Frame, Intrinsics, Sequence

GROUND_LABEL_IDS = (Label.ROAD, Label.SIDEWALK, Label.TERRAIN)
"""Train ids on the ground plane (as ``geometry.ground.GROUND_LABELS``)."""

MIN_PLANE_POINTS = 200
"""A frame's plane fit needs at least this many ground points."""

MAX_PLANE_POINTS = 20000
"""Ground points per frame are subsampled to about this many."""

PLANE_RMS_M = 0.3
PLANE_RMS_PER_M = 0.05
"""A fitted ground is planar when its RMS residual is below ``PLANE_RMS_M + PLANE_RMS_PER_M x height``
(depth error grows with range: the demo depth model's UAV ground, ~47 m below, fits within 0.04 x height)."""

NEAR_GROUND_FACTOR = 2.0
"""Extraction range: this many times the depth of the nearest ground in view (at least the fleet's)."""

BLOB_RANGE_EXPONENT = 1.5
"""Minimum blob size: the fleet's times (30 m / extraction range) ** this. 2 would give an object at the far
end of the range as many pixels as at 30 m; that admits fragments of far objects whose centroids are
noisy, 1 drops too many true objects. Airsim-like UAV, gt odometry, tuning seeds 10-14: 1.5 placed it in
3 worlds (2 within 2 m), 2 in 3 (1 within 2 m), 1 in 2 (none within 2 m)."""

VOXEL_PER_MEDIAN_DEPTH = 1.0 / 40.0
"""Odometry voxel: the median depth of the first frames times this (at least the fleet's)."""

NOISE_VOXEL_SIGMAS = 3.0
"""Odometry voxel: at least this many times the depth noise at the median depth (``depth_noise_rel`` x the
median depth), so that one surface's noisy samples share a voxel of KISS-ICP's map and pass the point-spacing
filter (``max_spacing_m`` follows the voxel) instead of being dropped or scattered over several voxels. 0 on
noise-free depth: no change there. Chosen on tuning world airsim-like 75 at 5 % depth noise (a car's
KISS-ICP alone: voxel 1 m 3.4 m ATE, 2 m 1.9 m; on the same world's perfect depth 0.25 / 0.36 m)."""

NOISE_STEPS_PX = (8, 16)
"""Pixel steps of the second differences ``relative_depth_noise`` measures noise over: a sensor's error is
correlated over a few pixels (a stereo matcher's window), so 1-px differences see little of it; farther steps
cross more object edges (on perfect renders 24 px reads 1.5 % where 8 and 16 read < 0.03 %)."""

NOISE_DECIMALS = 3
"""The measured depth noise goes into the config to 0.1 %: what perfect renders read (< 0.03 %, curved
surfaces) is 0 there, and their runs stay exactly as without the measurement."""

FAR_GROUND_MARGIN = 1.1
"""Odometry range: this many times the range of the farthest ground in view (at least the fleet's)."""

OBSERVED_RANGE_FACTOR = 1.5
"""Odometry range: at most ``FAR_GROUND_MARGIN`` x this many times the farthest range the measured frames' depth
holds. A very wide camera (150 deg) tilted down has every corner ray meet the ground, one of them kilometres away
(4 km for the airsim-like UAV at 320x96): a ``max_range_m`` that far holds no more points (the depth ends long
before) but scales KISS-ICP's adaptive threshold with every rotation, and the UAV's odometry failed on every frame
(17 segments, then stopped). Capped at 1.5 x its farthest depth (765 m there) it ran without a failure (2 x: 5
failures). At the tuned 82 deg the farthest depth is the farthest ground (109 vs 108 m): the cap binds only when
the frames show less than two thirds of the ground's range, far from any camera here."""

FALLBACK_NEAR_PERCENTILE = 5.0
"""Without a ground plane the nearest ground's depth is this percentile of the valid depths."""


@dataclass(frozen=True)
class SceneScale:
    """Scale of one robot's view, measured on its first frames.

    Attributes:
        frames: frames measured.
        camera_height_m: distance of the camera above the fitted ground plane (median over frames), or
            None when no frame gave a planar ground.
        pitch_down_deg: angle of the optical axis below the ground plane (positive looking down), or None.
        nearest_ground_depth_m: z-depth of the nearest ground in view (the image corner whose ray meets
            the ground first); without a plane the ``FALLBACK_NEAR_PERCENTILE`` of the valid depths.
        farthest_ground_range_m: Euclidean range of the farthest ground in view; inf when some corner's
            ray does not meet the ground (the horizon is in view) or there is no plane.
        depth_percentiles_m: (p5, p50, p95) of the valid depths of all frames, metres.
        image_px: (width, height) of the depth maps, pixels.
        depth_noise_rel: the depth's random error relative to the depth (``relative_depth_noise``, median
            over the frames; 0 when not measured): 0 for perfect renders, ~0.05 for 5 % sensor noise.
        frame_indices: the sequence's frames measured (``sample_scene_scale``; empty when not known).
        farthest_depth_range_m: the largest Euclidean range of any valid depth pixel of the frames, metres
            (inf when not measured).
    """

    frames: int
    camera_height_m: float | None
    pitch_down_deg: float | None
    nearest_ground_depth_m: float
    farthest_ground_range_m: float
    depth_percentiles_m: tuple[float, float, float]
    image_px: tuple[int, int] = (0, 0)
    depth_noise_rel: float = 0.0
    frame_indices: tuple[int, ...] = ()
    farthest_depth_range_m: float = float("inf")

    @property
    def horizon_in_view(self) -> bool:
        """True unless every image ray meets the ground (aerial / strongly oblique view)."""
        return not np.isfinite(self.farthest_ground_range_m)


def fit_ground_plane(
    depth_m: np.ndarray, label_ids: np.ndarray | None, intrinsics: Intrinsics, *, labelled_only: bool = False
) -> tuple[np.ndarray, float] | None:
    """Ground plane of one frame in the camera frame: ``(n, h)`` with ``n . p = -h`` for ground points.

    Args:
        depth_m: (H, W) z-depth, metres; 0 or non-finite = invalid.
        label_ids: (H, W) train ids, or None; the road, sidewalk and terrain pixels are the ground, the
            lowest quarter of the image rows when there are too few of them.
        intrinsics: pinhole intrinsics of ``depth_m``.
        labelled_only: with ``label_ids``, no fit (None) when too few pixels are labelled ground, instead of
            taking the lowest rows (a UAV beside a tower sees its facade there, not the ground).

    Returns:
        ``n`` (3,) unit normal pointing up (towards the camera) and ``h`` the camera's height above the
        plane, metres; None when there are too few ground points or they are not planar.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    H, W = depth.shape
    stride = max(1, int(np.sqrt(H * W / (4 * MAX_PLANE_POINTS))))
    points, pixel = backproject(depth, intrinsics, stride=stride)
    ground = None
    if label_ids is not None:
        ground = np.isin(np.asarray(label_ids).reshape(-1)[pixel], GROUND_LABEL_IDS)
        if ground.sum() < MIN_PLANE_POINTS:
            if labelled_only:
                return None
            ground = None
    if ground is None:
        ground = pixel // W >= (3 * H) // 4
    pts = points[ground]
    if len(pts) < MIN_PLANE_POINTS:
        return None
    pts = pts[:: max(1, len(pts) // MAX_PLANE_POINTS)]
    keep = np.ones(len(pts), bool)
    for _ in range(3):  # least squares, then drop the points off the plane (kerbs, mislabels) and refit
        centre = pts[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[keep] - centre, full_matrices=False)
        n = vt[2]
        residual = np.abs((pts - centre) @ n)
        rms = float(np.sqrt(np.mean(residual[keep] ** 2)))
        keep = residual <= max(3.0 * rms, 0.1)
        if keep.sum() < MIN_PLANE_POINTS:
            return None
    if n @ -centre < 0:
        n = -n
    h = float(n @ -centre)
    rms = float(np.sqrt(np.mean(residual[keep] ** 2)))
    if h <= 0 or rms > PLANE_RMS_M + PLANE_RMS_PER_M * h or keep.mean() < 0.5:
        return None
    return n, h


def relative_depth_noise(depth_m: np.ndarray, label_ids: np.ndarray | None) -> float:
    """Random depth error of one frame relative to the depth (a robust std), from the data alone.

    Inverse depth is linear in the pixel coordinates across a plane, so its second differences vanish on
    planar surfaces whatever their pose; depth ``d (1 + s e)`` with unit noise ``e`` leaves
    ``|diff2(1/d)| d ~ s |diff2(e)|``. The median over pixel triples that lie on one label along rows and
    columns (object edges left out), scaled to a Gaussian's std (``diff2`` of independent samples has 6x
    their variance), at each of ``NOISE_STEPS_PX``; the largest counts (noise correlated over a few pixels
    reads low at short steps). Curved surfaces and edges the labels miss add a little: perfect renders read
    below 0.0003.

    Args:
        depth_m: (H, W) z-depth, metres; 0 or non-finite = invalid.
        label_ids: (H, W) train ids, or None (every pixel one surface: edges then count).

    Returns:
        The relative noise std (0.05 = 5 %), 0 when the image is too small or has too few valid triples.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(depth) & (depth > 0)
    inv = np.where(ok, 1.0 / np.where(ok, depth, 1.0), np.nan)
    labels = np.zeros(depth.shape, np.int64) if label_ids is None else np.asarray(label_ids)
    if labels.shape != depth.shape:
        labels = np.zeros(depth.shape, np.int64)
    best = 0.0
    for step in NOISE_STEPS_PX:
        ratios = []
        for axis in (0, 1):
            a, lab = np.moveaxis(inv, axis, 0), np.moveaxis(labels, axis, 0)
            if a.shape[0] <= 2 * step:
                continue
            mid = a[step:-step]
            second = (a[: -2 * step] - 2.0 * mid + a[2 * step :]) / mid
            same = (lab[: -2 * step] == lab[step:-step]) & (lab[2 * step :] == lab[step:-step])
            r = np.abs(second[same])
            ratios.append(r[np.isfinite(r)])
        r = np.concatenate(ratios) if ratios else np.zeros(0)
        if r.size >= MIN_PLANE_POINTS:
            best = max(best, float(np.median(r)) / (0.6745 * np.sqrt(6.0)))
    return best


def corner_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(4, 3) rays with z = 1 through the image corners (camera frame)."""
    u = np.array([0.0, intrinsics.width - 1.0, 0.0, intrinsics.width - 1.0])
    v = np.array([0.0, 0.0, intrinsics.height - 1.0, intrinsics.height - 1.0])
    return np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones(4)], axis=1)


def ground_in_view(normal: np.ndarray, height_m: float, intrinsics: Intrinsics) -> tuple[float, float]:
    """``(nearest z-depth, farthest range)`` of the ground plane ``n . p = -h`` inside the image, metres.

    A ray ``t r`` meets the plane at ``t = -h / (n . r)`` when ``n . r < 0``; ``n . r`` is linear in the
    pixel, so its extremes are at the image corners. The farthest range is inf when a corner's ray does not
    meet the ground (the horizon is in view); the nearest depth is inf when none does.
    """
    rays = corner_rays(intrinsics)
    down = rays @ normal
    if not (down < 0).any():
        return float("inf"), float("inf")
    depth = -height_m / down[down < 0]
    nearest = float(depth.min())
    if (down >= 0).any():
        return nearest, float("inf")
    return nearest, float((depth * np.linalg.norm(rays, axis=1)).max())


def measure_scene_scale(
    depths_m: list[np.ndarray], label_ids: list[np.ndarray | None], intrinsics: Intrinsics
) -> SceneScale | None:
    """Scale of a robot's view from a few frames (e.g. its first five with valid depth).

    Args:
        depths_m: per frame (H, W) z-depth, metres (0 or non-finite = invalid).
        label_ids: per frame (H, W) train ids or None.
        intrinsics: intrinsics of the depth maps.

    Returns:
        The measured scale, or None when no frame has valid depth.
    """
    valid = [np.asarray(d, dtype=np.float64) for d in depths_m]
    samples = [d[np.isfinite(d) & (d > 0)] for d in valid]
    samples = [s[:: max(1, s.size // 50000)] for s in samples if s.size]
    if not samples:
        return None
    pooled = np.concatenate(samples)
    image_px = (int(valid[0].shape[1]), int(valid[0].shape[0]))
    p5, p50, p95 = (float(x) for x in np.percentile(pooled, [5.0, 50.0, 95.0]))
    noise = float(np.median([relative_depth_noise(d, lab) for d, lab in zip(valid, label_ids, strict=True)]))
    farthest = farthest_range_m(valid, intrinsics)
    planes = [fit_ground_plane(d, lab, intrinsics) for d, lab in zip(valid, label_ids, strict=True)]
    planes = [p for p in planes if p is not None]
    if not planes:
        near = float(np.percentile(pooled, FALLBACK_NEAR_PERCENTILE))
        return SceneScale(len(valid), None, None, near, float("inf"), (p5, p50, p95), image_px, noise,
                          farthest_depth_range_m=farthest)
    normal = np.sum([n for n, _ in planes], axis=0)
    normal /= np.linalg.norm(normal)
    height = float(np.median([h for _, h in planes]))
    near, far = ground_in_view(normal, height, intrinsics)
    if not np.isfinite(near):  # looking up, away from the ground: the depths still tell the scale
        near = float(np.percentile(pooled, FALLBACK_NEAR_PERCENTILE))
    pitch = float(np.degrees(np.arcsin(np.clip(-normal[2], -1.0, 1.0))))
    return SceneScale(len(valid), height, pitch, near, far, (p5, p50, p95), image_px, noise,
                      farthest_depth_range_m=farthest)


def farthest_range_m(depths_m: list[np.ndarray], intrinsics: Intrinsics) -> float:
    """The largest Euclidean range of a valid pixel over (H, W) z-depth maps (metres; 0 or non-finite invalid)
    with ``intrinsics``, metres; inf when the maps' size differs from the intrinsics' (not measured)."""
    if any(d.shape != (intrinsics.height, intrinsics.width) for d in depths_m):
        return float("inf")
    u = (np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height) - intrinsics.cy) / intrinsics.fy
    ray_norm = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)  # (H, W) range per metre of z-depth
    farthest = 0.0
    for d in depths_m:
        with np.errstate(invalid="ignore"):
            r = np.where(np.isfinite(d) & (d > 0), d * ray_norm, 0.0)
        farthest = max(farthest, float(r.max()))
    return farthest


def derived_values(scale: SceneScale | None) -> dict[str, dict[str, float | bool]]:
    """The data-derived fields, ``{"extraction": {...}, "odometry": {...}}``, from a robot's scene scale.

    ``None`` (nothing measured) gives the fleet values (``ExtractionConfig.FLEET``, ``OdometryConfig.FLEET``).
    Rules (reference: the fleet values, a car camera ~1.6 m above the road):

    * ``max_depth_m = max(30, 2 x nearest ground depth)``: a camera that sees the ground only from far
      away keeps a footprint as deep as that distance (car: the ground is 6 m away, 30 m stays);
    * ``min_blob_fraction = fleet x (30 / max_depth_m)^1.5`` (``BLOB_RANGE_EXPONENT``): far objects may
      cover fewer pixels, not quite as few as their range alone would say;
    * ``visual_max_depth_m = 40 x max_depth_m / 30``;
    * ``voxel_size_m = max(1, median depth / 40, 3 x depth noise x median depth)`` (``NOISE_VOXEL_SIGMAS``;
      the noise term is 0 on noise-free depth) (and ``max_spacing_m``, ``config.SPACING_PER_VOXEL`` times
      it, in ``resolve_robot_config``);
    * ``depth_noise_rel``: the measured noise to 0.1 % (``relative_depth_noise``, ``NOISE_DECIMALS``; the spacing
      filter's allowance);
    * ``image_step_blend``: the measured noise (as ``depth_noise_rel`` holds it) is not 0 and the horizon is in
      view: on noisy depth KISS-ICP's steps are blended with the image tracks' (``odometry.step_fusion``);
      perfect renders, on which ICP alone is best, keep ICP's, and so does a camera that sees only the ground
      (a narrow view of one distant plane, where PnP trades pitch for sideways motion);
    * ``shuffle_points`` and ``visual_ground_attitude``: the horizon is out of view;
    * ``max_range_m = max(100, 1.1 x min(farthest ground range, 1.5 x farthest depth range))`` (100 when the
      horizon is in view; ``OBSERVED_RANGE_FACTOR``: a very wide camera's corner meets the ground kilometres away);
    * ``cloud_stride = round(sqrt(W x H / CLOUD_TARGET_POINTS))``, at least 1: the pseudo-LiDAR cloud keeps
      about as many points whatever the image size (640x192 -> 2, 320x96 -> 1, KITTI's 1242x375 -> 4).
    """
    ex, od = dict(ExtractionConfig.FLEET), dict(OdometryConfig.FLEET)
    if scale is None:
        return {"extraction": ex, "odometry": od}
    max_depth_m = _rounded(max(ex["max_depth_m"], NEAR_GROUND_FACTOR * scale.nearest_ground_depth_m))
    ratio = max_depth_m / ex["max_depth_m"]
    out_ex = {"max_depth_m": max_depth_m, "min_blob_fraction": ex["min_blob_fraction"] / ratio**BLOB_RANGE_EXPONENT}
    far = min(scale.farthest_ground_range_m, OBSERVED_RANGE_FACTOR * scale.farthest_depth_range_m)
    noise_rel = round(scale.depth_noise_rel, NOISE_DECIMALS)
    out_od = {
        "voxel_size_m": max(od["voxel_size_m"], VOXEL_PER_MEDIAN_DEPTH * scale.depth_percentiles_m[1],
                            NOISE_VOXEL_SIGMAS * scale.depth_noise_rel * scale.depth_percentiles_m[1]),
        "max_range_m": max(od["max_range_m"], FAR_GROUND_MARGIN * far) if not scale.horizon_in_view
        else od["max_range_m"],
        "shuffle_points": not scale.horizon_in_view,
        "visual_ground_attitude": not scale.horizon_in_view,
        "visual_max_depth_m": od["visual_max_depth_m"] * ratio,
        "depth_noise_rel": noise_rel,
        "image_step_blend": noise_rel > 0 and scale.horizon_in_view,
    }
    out = {k: _rounded(v) for k, v in out_od.items()}
    out["cloud_stride"] = cloud_stride_for(scale.image_px) if min(scale.image_px) > 0 else od["cloud_stride"]
    return {"extraction": out_ex, "odometry": out}


CLOUD_TARGET_POINTS = 640 * 192 // 4
"""Pixels back-projected per frame: KISS-ICP's settings here were tuned on 640x192 images at stride 2."""


def cloud_stride_for(image_px: tuple[int, int]) -> int:
    """Back-projection stride that keeps about ``CLOUD_TARGET_POINTS`` pixels of a (width, height) image."""
    return max(1, round(float(np.sqrt(image_px[0] * image_px[1] / CLOUD_TARGET_POINTS))))


def _rounded(value: float | bool) -> float | bool:
    """Derived lengths to 3 significant digits (stable, readable ``config.yaml``)."""
    return value if isinstance(value, bool) else float(f"{value:.3g}")


def resolve_robot_config(cfg: ShgmConfig, scale: SceneScale | None) -> ShgmConfig:
    """A robot's config (``ShgmConfig.for_robot``) with its None fields derived from ``scale``.

    Fields set in ``cfg`` (fleet-wide or in the robot's overrides) are kept; the rest take
    ``derived_values(scale)`` (the fleet values when ``scale`` is None).
    """
    derived = derived_values(scale)
    stages = {}
    for stage, values in derived.items():
        current = getattr(cfg, stage)
        stages[stage] = current.model_copy(update={k: v for k, v in values.items() if getattr(current, k) is None})
    stages["odometry"] = stages["odometry"].with_spacing()  # from the voxel it got (derived or set)
    return cfg.model_copy(update=stages)


def effective_fields(cfg: ShgmConfig) -> dict[str, dict[str, float | bool]]:
    """The data-derived fields' values in a resolved robot config (for ``config.yaml``'s ``robots``)."""
    odometry = {k: getattr(cfg.odometry, k) for k in (*OdometryConfig.FLEET, "max_spacing_m")}
    if cfg.odometry.visual_road_height_m is not None:  # set from perception.camera_height_m (``robot.build``)
        odometry["visual_road_height_m"] = cfg.odometry.visual_road_height_m
    return {"extraction": {k: getattr(cfg.extraction, k) for k in ExtractionConfig.FLEET}, "odometry": odometry}


SAMPLE_FRAMES = 5
"""Frames measured per robot: the first with valid depth whose labels show the ground (``sample_scene_scale``)."""

SAMPLE_STEP = 5
"""Every this many frames (0.5 s at 10 fps: the frames differ a little)."""

SAMPLE_SPAN_FRAMES = 100
"""Frames searched for views of the ground, from the first (10 s at 10 fps). A UAV that takes off beside a tower
sees its facade and roof for the first seconds: measured on those frames, the scale was a car's (a 'ground' 10 m
below, objects kept up to 30 m), and from 44 m up its graph held 28 objects and it never joined (airsim-like
seed 530 at 640x192, the first world where this happened; its ground came into view after 3 s)."""


def sample_scene_scale(
    sequence: Sequence, perceive: Callable[[Frame], tuple[np.ndarray, np.ndarray | None]]
) -> SceneScale | None:
    """``measure_scene_scale`` on the first ``SAMPLE_FRAMES`` of frames ``0, SAMPLE_STEP, ...`` with valid depth
    whose labels show the ground (``fit_ground_plane(labelled_only=True)``), searched over the first
    ``SAMPLE_SPAN_FRAMES``; where none does (or frames have no labels), on the first ``SAMPLE_FRAMES`` with
    valid depth among the first ``2 x SAMPLE_FRAMES`` tried, as the ground then cannot be told apart
    (``ScaleSampler``, offered the sequence's frames in order).

    Args:
        sequence: the robot's frames.
        perceive: frame -> ``(depth_m (H, W) metres, label_ids (H, W) or None)``, e.g. the robot's
            perception source; a frame it raises ``DataError`` on is skipped.

    Returns:
        The scale (``frame_indices``: the frames measured), or None when no frame tried has valid depth.
    """
    sampler = ScaleSampler(perceive)
    for index in range(min(len(sequence), SAMPLE_SPAN_FRAMES)):
        if sampler.done:
            break
        if sampler.wants(index):
            sampler.offer(index, sequence)
    return sampler.result()


class ScaleSampler:
    """``sample_scene_scale`` one frame at a time, for frames that arrive one by one (``live``): offer each frame
    it ``wants`` in order until it is ``done`` (or the frames end), then take its ``result``. The same frames
    give the same scale as ``sample_scene_scale`` on the whole sequence.

    Args:
        perceive: frame -> ``(depth_m (H, W) metres, label_ids (H, W) or None)``; a ``DataError`` it raises
            skips the frame.
    """

    def __init__(self, perceive: Callable[[Frame], tuple[np.ndarray, np.ndarray | None]]) -> None:
        self._perceive = perceive
        self._first: list[tuple[int, np.ndarray, np.ndarray | None]] = []  # the first frames with valid depth
        self._grounded: list[tuple[int, np.ndarray, np.ndarray | None]] = []  # those whose labels show the ground
        self._intrinsics: Intrinsics | None = None
        self.done = False  # no later frame would change the result

    def wants(self, index: int) -> bool:
        """Whether frame ``index`` is one to offer (``offer``)."""
        return not self.done and index % SAMPLE_STEP == 0 and index < SAMPLE_SPAN_FRAMES

    def offer(self, index: int, sequence: Sequence) -> None:
        """Measure frame ``index`` of ``sequence`` (one it ``wants``; unreadable frames are skipped)."""
        first, grounded = self._first, self._grounded
        if index >= 2 * SAMPLE_FRAMES * SAMPLE_STEP and (len(first) < SAMPLE_FRAMES and not grounded):
            self.done = True  # no valid depth early on: the first frames decide, as they would have
            return
        self.done = index + SAMPLE_STEP >= SAMPLE_SPAN_FRAMES
        try:
            frame = sequence[index]
            depth, label = self._perceive(frame)
        except DataError:
            return
        depth = np.asarray(depth)
        if depth.ndim != 2 or not (np.isfinite(depth) & (depth > 0)).any():
            return
        K = frame.intrinsics
        if (K.width, K.height) != (depth.shape[1], depth.shape[0]):
            K = K.scaled(depth.shape[1], depth.shape[0])
        if self._intrinsics is not None and K != self._intrinsics:
            return
        self._intrinsics = self._intrinsics or K
        label = None if label is None or np.shape(label) != depth.shape else label
        if len(first) < SAMPLE_FRAMES:
            first.append((index, depth, label))
        if label is None:  # no labels: the ground cannot be told apart; the first frames decide
            self.done = self.done or len(first) == SAMPLE_FRAMES
            return
        if fit_ground_plane(depth, label, K, labelled_only=True) is not None:
            grounded.append((index, depth, label))
            self.done = self.done or len(grounded) == SAMPLE_FRAMES

    def result(self) -> SceneScale | None:
        """The scale measured on the frames offered so far (``sample_scene_scale``), or None (no valid depth)."""
        chosen = self._grounded or self._first
        if not chosen:
            return None
        scale = measure_scene_scale([d for _, d, _ in chosen], [lab for _, _, lab in chosen], self._intrinsics)
        return None if scale is None else replace(scale, frame_indices=tuple(i for i, _, _ in chosen))
