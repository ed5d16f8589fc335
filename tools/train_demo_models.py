"""Train the demo monocular depth and segmentation models on simulated cities and export them to ONNX.

The RGB-only path of shgm_slam needs a depth model and a segmentation model. These demo models are
small CNNs trained here on images rendered by ``shgm_slam.sim`` (no external data, no downloads), so the
whole system runs from RGB alone on the synthetic worlds. Steps::

    render   simulate() airsim-like (cars + UAV), synthia-like (forward + backward cameras) and kitti-paths
             cities of the TRAINING seeds at 1 frame/s, 640x192, half of them antialiased (2 x 2 rays per
             pixel); cache them as .npz at the model input size (``--render-jobs`` processes)
    train    one encoder-decoder (depthwise-separable, ``--net base``: 32-64-128-256 channels, a whole-image
             context, a thin full-resolution path) with a log-depth head and a 19-class head, jointly, for
             ``--max-steps`` steps (or a wall-time budget): class-weighted L1 + scale-invariant + gradient
             loss on log depth (sky masked, far clamped to 80 m) and class-weighted cross entropy;
             ``--device cuda`` trains on a GPU (bfloat16 autocast), the default on CPU
    export   two ONNX files (opset 17, IR <= 10, dynamic batch, fixed 320x96 input) + model cards:
             demo_depth.onnx -> metric depth (N, 1, 96, 320), 0 where the model sees sky;
             demo_seg.onnx   -> label map (N, 96, 320) of Cityscapes train ids (ArgMax in the graph)
    evaluate HELD-OUT cities (airsim-like seed 100, synthia-like seed 101, one-ray and antialiased) through
             the project's DepthModel / SegmentationModel adapters at the demo resolution 640x192: depth
             AbsRel, delta < 1.25, segmentation mIoU + per-class IoU, inference ms/frame with 2 threads;
             writes models/demo_models_metrics.json and models/README.md

Usage (needs the ``train`` extra: ``.venv/bin/pip install -e '.[train]'``)::

    .venv/bin/python tools/train_demo_models.py --device cuda   # the committed recipe on a GPU (~9 min)
    .venv/bin/python tools/train_demo_models.py                 # the same recipe on CPU (hours: models/README.md)
    .venv/bin/python tools/train_demo_models.py --eval-only     # re-measure the models in models/
    .venv/bin/python tools/train_demo_models.py --render-only   # only render + cache the data
    .venv/bin/python tools/train_demo_models.py --net small --extra-seeds 0 --supersample 1 \
        --no-kitti-paths-worlds --batch 12 --lr 3e-3 --max-steps 9000 --train-minutes 38
                                          # the first demo models' recipe (CPU, 38 min)

Variants measured and not (yet) taken: ``--scale-weight W`` adds W x each image's absolute mean log-depth
error to the loss (a UAV's per-frame scale), ``--crop-width`` trains on wider crops (320: whole images),
``--airsim-fps`` renders the airsim-like cities (and so the UAV's views) more often (docs/benchmarks.md,
held-out notes).

The rendered data is cached under ``--cache-dir`` (default /tmp/shgm_demo_models/cache), never in the
repo; delete that folder after changing the simulator, or the models train on its old renders.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import dataclass, replace
from enum import Enum
from pathlib import Path
from typing import Any

import cv2
import numpy as np

# OpenMP threads that sleep instead of spinning while they wait: on a shared, oversubscribed CPU spinning
# made 2-thread training steps 3-7x slower (measured); must be set before torch loads libgomp.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from shgm_slam.data import open_sequence
from shgm_slam.labels import CITYSCAPES_CLASSES, IGNORE_ID, NUM_CLASSES, Label
from shgm_slam.perception import DepthModel, SegmentationModel, measure_overhead
from shgm_slam.perception.card import (
    DepthCard,
    DepthKind,
    DepthOutputSpec,
    InputSpec,
    LabelSpace,
    ResizeMode,
    SegmentationCard,
    SegOutputKind,
    SegOutputSpec,
    TaskKind,
)
from shgm_slam.sim.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from export_onnx import export_module, write_full_card  # sibling tool script

REPO = Path(__file__).resolve().parents[1]
RENDER_WH = (640, 192)  # the demo resolution (what `shgm-slam simulate` writes by default)
INPUT_WH = (320, 96)  # model input; the adapter shrinks 640x192 by 2 with INTER_AREA
CROP_W = 192  # training crops along x (the y-coordinate channel keeps the vertical position); --crop-width
SCALE_WEIGHT = 0.0
"""``--scale-weight``: weight of the per-image scale term of the depth loss (the mean log-depth error of each
image, absolute): a UAV's objects 45-90 m away came out 0.91-1.13 of the truth frame by frame (the
scale-invariant term forgives a whole image's offset by design)."""
AIRSIM_FPS = 1.0
"""``--airsim-fps``: frames per second of motion rendered from the airsim-like training cities (cars and the
UAV; the UAV flies 90 s, the cars ~40 s, so more frames are mostly more UAV views)."""
MIN_DEPTH_M, MAX_DEPTH_M = 0.5, 80.0
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
WIDTHS = (24, 32, 64, 128)
THING_CLASSES = (Label.WALL, Label.FENCE, Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN, Label.VEGETATION,
                 Label.CAR, Label.TRUCK, Label.BUS)
THING_DEPTH_WEIGHT = 3.0  # depth loss weight of these classes (road, sidewalk, building, terrain: 1)
LICENSE = "MIT (same as shgm_slam); trained in this repository on synthetic data rendered by shgm_slam.sim"
MODEL_TABLE = "\n".join((
    "| file | card | task | input | output |",
    "|---|---|---|---|---|",
    "| `demo_depth.onnx` | `demo_depth.yaml` | monocular metric depth | RGB 320x96 (stretch), ImageNet "
    "mean/std | `depth` (N, 1, 96, 320) metres, 0.5..80, **0 where the model sees sky** |",
    "| `demo_seg.onnx` | `demo_seg.yaml` | semantic segmentation | RGB 320x96 (stretch), ImageNet mean/std "
    "| `labels` (N, 96, 320) int64 Cityscapes train ids (ArgMax inside the graph) |",
))
SOURCE = "tools/train_demo_models.py (trained from scratch on shgm_slam.sim renders)"


@dataclass(frozen=True)
class Split:
    """One simulated city: scenario name, seed, frame rate (frames per second of driving), size, colour rays
    per pixel (``supersample`` x ``supersample``, averaged: what a camera pixel integrates) and, for
    kitti-paths, the KITTI drives."""

    scenario: str
    seed: int
    fps: float = 1.0
    compact: bool = False
    supersample: int = 1
    kitti_robots: tuple[str, ...] | None = None
    frame_stride: int = 1  # keep every n-th rendered frame (kitti-paths: KITTI's own 10 Hz frames, every 5th)

    @property
    def key(self) -> str:
        ss = f"-ss{self.supersample}" if self.supersample > 1 else ""
        return f"{self.scenario}-s{self.seed}-f{self.fps:g}{'-compact' if self.compact else ''}{ss}"


SUPERSAMPLE = (1, 2)
"""Colour rays per pixel side of the training renders (``--supersample``), given to the cities in turn: one ray
per pixel as the benchmark worlds are rendered (640x192 shrunk 2x to the model input averages 2 x 2 of them),
and 2 x 2 rays, antialiased as a camera's pixel integrates light (one ray aliases the road's fine texture:
docs/benchmarks.md, held-out notes). The held-out cities are rendered with each."""
KITTI_PATHS_WORLDS = True
KITTI_TRAIN_DRIVES = (("02:0-301", "05:0-301"), ("03:0-301", "06:0-301"), ("04:0-271", "05:1200-1501"))
"""``--kitti-paths-worlds`` (on by default): kitti-paths training worlds driving KITTI sequences the held-out
pairs never use (02-06; their poses from ``../shared/data``)."""
EXTRA_SEEDS = 10
"""``--extra-seeds``: more airsim-like and synthia-like training cities, each."""


def _ss_cycle(supersample: int | tuple[int, ...]) -> tuple[int, ...]:
    return (supersample,) if isinstance(supersample, int) else tuple(supersample)


MAX_STEPS = 10637
"""Training steps of the committed models (a 4-minute budget on one GPU ended there; README)."""
EXTRA_SEED0 = 40
"""First seed of ``--extra-seeds`` training cities."""


def train_splits(
    supersample: int | tuple[int, ...] = SUPERSAMPLE, kitti_paths: bool = KITTI_PATHS_WORLDS,
    extra_seeds: int = EXTRA_SEEDS, airsim_fps: float = AIRSIM_FPS,
) -> tuple[Split, ...]:
    """The training cities (seeds the held-out benchmark never uses).

    ``supersample``: one S for every city, or several given to the cities in turn (a mix of aliased and
    antialiased looks). ``extra_seeds``: that many more airsim-like and synthia-like cities each, seeds
    from ``EXTRA_SEED0`` on (outside the benchmarks' tuning 10-39 and report 200-219 / 300-309 seeds and
    the models' held-out 100-101). ``airsim_fps``: frames per second of the airsim-like cities (not the compact
    ones)."""
    cycle = _ss_cycle(supersample)
    kitti = tuple(Split("kitti-paths", s, fps=10.0, kitti_robots=d, frame_stride=5)
                  for s, d in zip(range(1, 4), KITTI_TRAIN_DRIVES, strict=True)) if kitti_paths else ()
    extra = range(EXTRA_SEED0, EXTRA_SEED0 + extra_seeds)
    splits = (
        *(Split("airsim-like", s, fps=airsim_fps) for s in (*range(1, 7), *extra)),
        *(Split("synthia-like", s) for s in (*range(1, 7), *extra)),
        *kitti,
        Split("airsim-like", 21, fps=2.0, compact=True),
        Split("airsim-like", 22, fps=2.0, compact=True),
        Split("synthia-like", 23, fps=2.0, compact=True),
    )
    return tuple(replace(sp, supersample=cycle[i % len(cycle)]) for i, sp in enumerate(splits))


def heldout_splits(supersample: int | tuple[int, ...] = SUPERSAMPLE) -> tuple[Split, ...]:
    """The cities the models are measured on after training (never trained on), rendered with every S given."""
    return tuple(Split(scenario, seed, supersample=ss) for ss in _ss_cycle(supersample)
                 for scenario, seed in (("airsim-like", 100), ("synthia-like", 101)))


# --- data: simulator renders ------------------------------------------------------------------------


def render_split(split: Split, cache_dir: Path) -> Path:
    """Render ``split`` with ``shgm_slam.sim.simulate`` at 640x192 into ``cache_dir/raw/<key>`` (cached)."""
    out = cache_dir / "raw" / split.key
    if (out / "scenario.json").is_file():
        return out
    t0 = time.perf_counter()
    res = simulate(split.scenario, out, seed=split.seed, resolution=RENDER_WH, fps=split.fps,
                   compact=split.compact, overwrite=True, supersample=split.supersample,
                   kitti_robots=split.kitti_robots)
    took = time.perf_counter() - t0
    print(f"  rendered {split.key}: {res.total_frames} frames in {took:.0f} s", flush=True)
    return out


def robot_folders(scenario_dir: Path) -> list[Path]:
    """The robot sequence folders of a rendered scenario (``scenario.json`` lists them)."""
    meta = json.loads((scenario_dir / "scenario.json").read_text())
    return [scenario_dir / r["folder"] for r in meta["robots"]]


def to_model_grid(
    image_rgb: np.ndarray, depth_m: np.ndarray, label_ids: np.ndarray
) -> tuple[np.ndarray, ...]:
    """One 640x192 frame -> model-input-size arrays, exactly as the adapter feeds the model.

    Returns:
        image (96, 320, 3) uint8 (INTER_AREA, as the adapter's automatic interpolation for a 2x shrink),
        depth (96, 320) float16 metres (nearest; 0 = invalid), labels (96, 320) uint8 train ids (nearest).
    """
    W, H = INPUT_WH
    image = cv2.resize(image_rgb, (W, H), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(depth_m, (W, H), interpolation=cv2.INTER_NEAREST).astype(np.float16)
    labels = cv2.resize(label_ids, (W, H), interpolation=cv2.INTER_NEAREST)
    return image, depth, labels


def _split_cache(split: Split, cache_dir: Path) -> Path:
    return cache_dir / f"{split.key}-{INPUT_WH[0]}x{INPUT_WH[1]}.npz"


def load_split(split: Split, cache_dir: Path) -> dict[str, np.ndarray]:
    """Arrays of one training split at the model input size (cached as .npz; raw PNGs removed after).
    ``prepare_s`` (scalar) is the wall time it took to render and convert the split when it was cached."""
    path = _split_cache(split, cache_dir)
    if path.is_file():
        with np.load(path) as data:
            return _strided(dict(data), split.frame_stride)
    t0 = time.perf_counter()
    raw = render_split(split, cache_dir)
    images, depths, labels = [], [], []
    for folder in robot_folders(raw):
        for frame in open_sequence(folder):
            im, d, lab = to_model_grid(frame.image_rgb, frame.depth_m, frame.label_ids)
            images.append(im)
            depths.append(d)
            labels.append(lab)
    data = {"images": np.stack(images), "depth_m": np.stack(depths), "labels": np.stack(labels)}
    data["prepare_s"] = np.array(time.perf_counter() - t0)
    np.savez(path, **data)
    shutil.rmtree(raw)
    return _strided(data, split.frame_stride)


def _strided(data: dict[str, np.ndarray], stride: int) -> dict[str, np.ndarray]:
    """Every ``stride``-th frame of a split's arrays (scalars such as ``prepare_s`` kept)."""
    return {k: v[::stride] if v.ndim else v for k, v in data.items()}


def load_training_set(
    cache_dir: Path, supersample: int | tuple[int, ...] = SUPERSAMPLE, kitti_paths: bool = KITTI_PATHS_WORLDS,
    extra_seeds: int = EXTRA_SEEDS, jobs: int = 1, airsim_fps: float = AIRSIM_FPS,
) -> dict[str, np.ndarray]:
    """All training splits concatenated: images (N, 96, 320, 3) uint8, depth_m (N, 96, 320) float16,
    labels (N, 96, 320) uint8. ``jobs`` > 1 renders the uncached cities in that many processes first."""
    splits = train_splits(supersample, kitti_paths, extra_seeds, airsim_fps)
    cache_all(splits, cache_dir, jobs)
    parts = [load_split(s, cache_dir) for s in splits]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("images", "depth_m", "labels")}


def cache_all(splits: tuple[Split, ...], cache_dir: Path, jobs: int) -> None:
    """Render and cache every uncached split of ``splits``, ``jobs`` at a time (the longest first)."""
    todo = [sp for sp in splits if not _split_cache(sp, cache_dir).is_file()]
    if jobs <= 1 or len(todo) <= 1:
        return
    from concurrent.futures import ProcessPoolExecutor

    todo.sort(key=lambda sp: -sp.supersample * sp.fps)
    with ProcessPoolExecutor(min(jobs, len(todo))) as pool:
        for _ in pool.map(_cache_one, todo, [cache_dir] * len(todo)):
            pass


def _cache_one(split: Split, cache_dir: Path) -> None:
    cv2.setNumThreads(1)
    load_split(split, cache_dir)


def uncached_prepare_minutes(
    cache_dir: Path, supersample: int | tuple[int, ...] = SUPERSAMPLE, kitti_paths: bool = KITTI_PATHS_WORLDS,
    extra_seeds: int = EXTRA_SEEDS, airsim_fps: float = AIRSIM_FPS,
) -> float | None:
    """Minutes it took to render + convert all training splits when the cache was built (None if unknown)."""
    total = 0.0
    for split in train_splits(supersample, kitti_paths, extra_seeds, airsim_fps):
        path = _split_cache(split, cache_dir)
        if not path.is_file():
            return None
        with np.load(path) as data:
            if "prepare_s" not in data.files:
                return None
            total += float(data["prepare_s"])
    return round(total / 60.0, 2)


# --- the network --------------------------------------------------------------------------------------


class NetSize(str, Enum):
    """The network's size (``--net``)."""

    SMALL = "small"  # the first demo models: 83 k parameters, ~5 ms per frame on 2 CPU threads
    BASE = "base"  # wider, deeper at 1/8 and 1/16, a whole-image context: meant for a GPU's training budget


@dataclass(frozen=True)
class NetSpec:
    """Widths and blocks of ``build_network``: encoder widths at 1/2..1/16, the dilations of the extra
    separable blocks at 1/8 and 1/16, decoder widths, and whether a whole-image context (global average
    of the 1/16 features, added back to them) tells the decoder the scene's scale (a UAV's height)."""

    widths: tuple[int, int, int, int]
    dilations8: tuple[int, ...]
    dilations16: tuple[int, ...]
    dec2: int
    head: int
    fine: int
    context: bool


NETS = {
    NetSize.SMALL: NetSpec((24, 32, 64, 128), (1, 2), (2, 4), dec2=48, head=16, fine=8, context=False),
    NetSize.BASE: NetSpec((32, 64, 128, 256), (1, 2, 4), (2, 4, 8), dec2=96, head=24, fine=12, context=True),
}


def build_network(spec: NetSpec = NETS[NetSize.SMALL]) -> Any:
    """The joint depth + segmentation encoder-decoder (torch module; imported lazily).

    forward(x (N, 3, H, W) normalized RGB) -> (log_depth (N, 1, H, W) log metres, logits (N, 19, H, W));
    H, W multiples of 16. Most of the compute sits at 1/4..1/16 resolution (what makes CPU training in
    minutes possible); a thin full-resolution path sharpens the edges of thin objects. A constant
    y-coordinate channel joins the input: metric depth from one view depends on where a pixel sits relative
    to the horizon. ``spec`` sets the widths (``NETS``; the small one is the committed first recipe).
    """
    import torch
    from torch import nn
    from torch.nn import functional as F  # noqa: N812 (torch's own convention)

    def conv(ci: int, co: int, stride: int = 1) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(ci, co, 3, stride, 1, bias=False), nn.BatchNorm2d(co), nn.ReLU(inplace=True)
        )

    def sep(ci: int, co: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(ci, ci, 3, stride, dilation, dilation=dilation, groups=ci, bias=False),
            nn.Conv2d(ci, co, 1, bias=False), nn.BatchNorm2d(co), nn.ReLU(inplace=True),
        )

    a, b, c, d = spec.widths

    class DemoNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.enc1 = conv(4, a, 2)  # 1/2
            self.enc2 = nn.Sequential(sep(a, b, 2), sep(b, b))  # 1/4
            self.enc3 = nn.Sequential(sep(b, c, 2), *(sep(c, c, dilation=k) for k in spec.dilations8))  # 1/8
            self.enc4 = nn.Sequential(sep(c, d, 2), *(sep(d, d, dilation=k) for k in spec.dilations16))  # 1/16
            self.context = (nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(d, d, 1), nn.ReLU(inplace=True))
                            if spec.context else None)
            self.dec3 = sep(d + c, c)
            self.dec2 = sep(c + b, spec.dec2)
            self.dec1 = sep(spec.dec2 + a, a)
            self.fine = conv(4, spec.fine)  # full resolution: edges of thin objects
            self.dec0 = sep(a + spec.fine, spec.head)
            self.depth_head = nn.Conv2d(spec.head, 1, 1)
            self.seg_head = nn.Conv2d(spec.head, NUM_CLASSES, 1)
            nn.init.constant_(self.depth_head.bias, float(np.log(15.0)))

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            n, _, h, w = x.shape
            y = torch.linspace(-1.0, 1.0, h, dtype=x.dtype, device=x.device).view(1, 1, h, 1).expand(n, 1, h, w)
            xy = torch.cat([x, y], 1)
            x1 = self.enc1(xy)
            x2 = self.enc2(x1)
            x3 = self.enc3(x2)
            x4 = self.enc4(x3)
            if self.context is not None:
                x4 = x4 + self.context(x4)

            def up(t: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
                return F.interpolate(t, size=ref.shape[2:], mode="bilinear", align_corners=False)

            u = self.dec3(torch.cat([up(x4, x3), x3], 1))
            u = self.dec2(torch.cat([up(u, x2), x2], 1))
            u = self.dec1(torch.cat([up(u, x1), x1], 1))
            u = self.dec0(torch.cat([up(u, xy), self.fine(xy)], 1))
            return self.depth_head(u), self.seg_head(u)

    return DemoNet()


def export_heads(net: Any) -> tuple[Any, Any]:
    """Two single-output torch modules around the trained ``net`` for export: depth (N, 1, H, W) metres
    clamped to [0.5, 80], 0 where the class head says sky; labels (N, H, W) int64 train ids."""
    import torch
    from torch import nn

    class DepthHead(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            log_depth, logits = self.net(x)
            depth = torch.exp(log_depth.clamp(float(np.log(MIN_DEPTH_M)), float(np.log(MAX_DEPTH_M))))
            sky = logits[:, Label.SKY : Label.SKY + 1] >= logits.amax(1, keepdim=True)
            return depth * (~sky).to(depth.dtype)

    class LabelHead(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.net(x)[1].argmax(1)

    return DepthHead().eval(), LabelHead().eval()


# --- training -------------------------------------------------------------------------------------------


def class_weights(labels: np.ndarray) -> np.ndarray:
    """(19,) float32 cross-entropy weights ``sqrt(median freq / freq)`` clipped to [0.25, 8]; absent -> 0."""
    counts = np.bincount(labels.ravel(), minlength=256)[:NUM_CLASSES].astype(np.float64)
    present = counts > 0
    freq = counts / counts.sum()
    w = np.zeros(NUM_CLASSES)
    w[present] = np.clip(np.sqrt(np.median(freq[present]) / freq[present]), 0.25, 8.0)
    return w.astype(np.float32)


def log_depth_loss(
    log_depth: Any, depth_m: Any, labels: Any, class_weight: Any, scale_weight: float = SCALE_WEIGHT
) -> Any:
    """Depth loss of (N, H, W) predicted log depth against (N, H, W) true depth in metres (0 = beyond the
    render range, read as 80 m) over non-sky pixels: class-weighted L1 on log depth (``class_weight``
    (256,) per label: objects that anchor odometry and graph nodes count more) + 0.5 x scale-invariant
    log error + gradient matching at 1/1, 1/2 and 1/4 scale (sharp depth edges at object borders) +
    ``scale_weight`` x the mean over images of each image's absolute mean log error (its scale,
    ``SCALE_WEIGHT``)."""
    import torch

    valid = (labels != Label.SKY) & (labels != IGNORE_ID)
    target = torch.where(depth_m > 0, depth_m, torch.full_like(depth_m, MAX_DEPTH_M))
    r = log_depth - target.clamp(MIN_DEPTH_M, MAX_DEPTH_M).log()
    w = class_weight[labels.long()] * valid
    l1 = (w * r.abs()).sum() / w.sum().clamp(min=1.0)
    rv = r[valid]
    si = torch.sqrt((rv**2).mean() - 0.85 * rv.mean() ** 2 + 1e-8)
    grad = r.new_zeros(())
    m = valid.float()
    for k in (1, 2, 4):
        rk, mk = r[:, ::k, ::k], m[:, ::k, ::k]
        mx, my = mk[:, :, 1:] * mk[:, :, :-1], mk[:, 1:] * mk[:, :-1]
        gx = (rk[:, :, 1:] - rk[:, :, :-1]).abs() * mx
        gy = (rk[:, 1:] - rk[:, :-1]).abs() * my
        grad = grad + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp(min=1.0)
    loss = l1 + 0.5 * si + 0.5 * grad
    if scale_weight:
        per_image = (r * valid).sum((1, 2)) / valid.sum((1, 2)).clamp(min=1)
        loss = loss + scale_weight * per_image.abs().mean()
    return loss


def learning_rate(peak: float, progress: float, warmup: float = 0.04) -> float:
    """Linear warm-up then cosine decay to 2 % of ``peak`` over ``progress`` in [0, 1]."""
    if progress < warmup:
        return peak * (0.1 + 0.9 * progress / warmup)
    t = (progress - warmup) / (1.0 - warmup)
    return peak * (0.02 + 0.98 * 0.5 * (1.0 + np.cos(np.pi * min(t, 1.0))))


def train(
    data: dict[str, np.ndarray], minutes: float | None, max_steps: int, batch: int, lr: float, seed: int,
    spec: NetSpec = NETS[NetSize.SMALL], device: str = "cpu", scale_weight: float = SCALE_WEIGHT,
    crop_width: int = CROP_W,
) -> tuple[Any, dict]:
    """Train the joint network for ``minutes`` of wall time or ``max_steps`` steps, whichever ends first
    (the learning-rate schedule follows that progress, so a busy machine gets a complete, shorter run;
    ``minutes=None``: ``max_steps`` steps whatever they take).
    On ``device="cuda"`` the whole training set sits on the GPU and the forward pass runs in bfloat16
    autocast (losses in float32).

    Returns:
        the network (eval mode) and a log: steps, losses every 50 steps, wall time.
    """
    import torch
    from torch.nn import functional as F  # noqa: N812 (torch's own convention)

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    dev = torch.device(device)
    gpu = dev.type == "cuda"
    net = build_network(spec).to(dev, memory_format=torch.channels_last)  # faster convolutions (measured)
    images = torch.from_numpy(data["images"]).to(dev).permute(0, 3, 1, 2).contiguous()  # (N, 3, H, W) uint8
    depth = torch.from_numpy(data["depth_m"]).to(dev).float()
    labels = torch.from_numpy(data["labels"]).to(dev)
    weights = torch.from_numpy(class_weights(data["labels"])).to(dev)
    thing_weight = torch.ones(256, device=dev)
    thing_weight[list(THING_CLASSES)] = THING_DEPTH_WEIGHT
    mean = torch.tensor(IMAGENET_MEAN, device=dev).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=dev).view(1, 3, 1, 1)

    def rand(low: float, high: float, shape: tuple[int, ...]) -> torch.Tensor:
        return torch.from_numpy(rng.uniform(low, high, shape).astype(np.float32)).to(dev)

    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    n, W = images.shape[0], images.shape[3]
    log: dict[str, list] = {"step": [], "depth_loss": [], "seg_loss": [], "elapsed_s": []}
    t0 = time.perf_counter()
    run_d = run_s = 0.0
    step = 0
    net.train()
    budget_s = float("inf") if minutes is None else 60.0 * minutes
    while (progress := max((time.perf_counter() - t0) / budget_s, step / max_steps)) < 1.0:
        step += 1
        for group in opt.param_groups:
            group["lr"] = learning_rate(lr, progress)
        idx = torch.from_numpy(rng.integers(0, n, batch)).to(dev)
        x0 = 2 * int(rng.integers(0, (W - crop_width) // 2 + 1))
        x = images[idx, :, :, x0 : x0 + crop_width].float() / 255.0
        d = depth[idx, :, x0 : x0 + crop_width]
        lab = labels[idx, :, x0 : x0 + crop_width].long()
        if rng.random() < 0.5:
            x, d, lab = x.flip(3), d.flip(2), lab.flip(2)
        # photometric jitter per image: contrast, gain, per-channel tint, pixel noise
        c = rand(0.8, 1.2, (batch, 1, 1, 1))
        g = rand(0.7, 1.3, (batch, 1, 1, 1))
        tint = rand(0.9, 1.1, (batch, 3, 1, 1))
        m = x.mean((1, 2, 3), keepdim=True)
        x = ((x - m) * c + m) * g * tint + 0.02 * torch.randn_like(x)
        x = ((x.clamp(0.0, 1.0) - mean) / std).contiguous(memory_format=torch.channels_last)

        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=gpu):
            log_depth, logits = net(x)
        depth_loss = log_depth_loss(log_depth[:, 0].float(), d, lab, thing_weight, scale_weight)
        seg_loss = F.cross_entropy(logits.float(), lab, weight=weights, ignore_index=IGNORE_ID)
        opt.zero_grad(set_to_none=True)
        (depth_loss + seg_loss).backward()
        opt.step()
        run_d = run_d + depth_loss.detach()  # no .item() per step: it would wait for the GPU every step
        run_s = run_s + seg_loss.detach()
        if step % 50 == 0:
            run_d, run_s = float(run_d), float(run_s)
            elapsed = time.perf_counter() - t0
            lr_now = opt.param_groups[0]["lr"]
            print(f"  step {step}  depth {run_d / 50:.3f}  seg {run_s / 50:.3f}  lr {lr_now:.1e}  "
                  f"{elapsed / 60:.1f} min", flush=True)
            for key, val in zip(log, (step, run_d / 50, run_s / 50, elapsed), strict=True):
                log[key].append(round(float(val), 4))
            run_d = run_s = 0.0
    print(f"  trained {step} steps in {(time.perf_counter() - t0) / 60:.1f} min", flush=True)
    log["steps_done"] = step
    return net.to("cpu", memory_format=torch.contiguous_format).eval(), log


def cpu_steps_per_s(spec: NetSpec, batch: int, steps: int) -> float:
    """Training steps per second of ``spec`` at ``batch`` on CPU (random frames: a step's time does not
    depend on the pixels), timed over ``steps`` steps after 3 warm-up steps."""
    rng = np.random.default_rng(0)
    n = max(batch, 16)
    data = {"images": rng.integers(0, 256, (n, INPUT_WH[1], INPUT_WH[0], 3), dtype=np.uint8),
            "depth_m": rng.uniform(1.0, 60.0, (n, INPUT_WH[1], INPUT_WH[0])).astype(np.float16),
            "labels": rng.integers(0, NUM_CLASSES, (n, INPUT_WH[1], INPUT_WH[0]), dtype=np.uint8)}
    train(data, 1e9, 3, batch, 1e-3, 0, spec, "cpu")
    t0 = time.perf_counter()
    train(data, 1e9, steps, batch, 1e-3, 0, spec, "cpu")
    return steps / (time.perf_counter() - t0)


# --- export + cards ------------------------------------------------------------------------------------


def _input_spec() -> InputSpec:
    return InputSpec(layout="NCHW", size=INPUT_WH, resize=ResizeMode.STRETCH, color_order="RGB",
                     scale=1.0 / 255.0, mean=IMAGENET_MEAN, std=IMAGENET_STD)


def depth_card() -> DepthCard:
    return DepthCard(
        task=TaskKind.DEPTH, name="shgm demo depth (320x96)",
        description="small U-Net-style CNN, RGB -> metric z-depth in metres for the synthetic shgm_slam "
                    "cities (82 deg hfov, camera 1.65 m above the road or on a UAV); 0 where it sees sky. "
                    "A demo, not a general-purpose model: see models/README.md",
        source=SOURCE, license=LICENSE, input=_input_spec(),
        output=DepthOutputSpec(
            name="depth", kind=DepthKind.METRIC, min_depth_m=MIN_DEPTH_M, max_depth_m=MAX_DEPTH_M
        ),
    )


def seg_card() -> SegmentationCard:
    return SegmentationCard(
        task=TaskKind.SEGMENTATION, name="shgm demo segmentation (320x96)",
        description="small U-Net-style CNN, RGB -> Cityscapes train ids (ArgMax in the graph) for the "
                    "synthetic shgm_slam cities. A demo, not a general-purpose model: see models/README.md",
        source=SOURCE, license=LICENSE, input=_input_spec(),
        output=SegOutputSpec(name="labels", kind=SegOutputKind.LABEL_MAP, classes=LabelSpace.CITYSCAPES),
    )


def export_models(net: Any, out_dir: Path) -> dict[str, Any]:
    """Export both heads to ``out_dir`` (demo_depth.onnx, demo_seg.onnx + cards); returns export facts."""
    depth_head, label_head = export_heads(net)
    facts = {}
    for stem, module, output, card in (("demo_depth", depth_head, "depth", depth_card()),
                                       ("demo_seg", label_head, "labels", seg_card())):
        path = out_dir / f"{stem}.onnx"
        ir, opset, diff, _ = export_module(module, path, INPUT_WH, output, opset=17)
        write_full_card(card, path)
        facts[stem] = {"ir_version": ir, "opset": opset, "max_abs_diff_vs_torch": diff,
                       "size_mb": round(path.stat().st_size / 1e6, 3)}
        print(f"  exported {path} ({facts[stem]['size_mb']} MB, IR {ir}, opset {opset}, "
              f"max |ort - torch| {diff:.2e})", flush=True)
    return facts


# --- evaluation through the adapters -------------------------------------------------------------------


def evaluate(
    models_dir: Path, cache_dir: Path, threads: int = 2, supersample: int | tuple[int, ...] = SUPERSAMPLE
) -> dict[str, Any]:
    """Held-out metrics of the exported models through ``DepthModel`` / ``SegmentationModel`` at 640x192.

    Depth: over pixels whose ground truth is valid (not sky, 0 < d <= 80 m); a pixel the model marks
    invalid (it saw sky) counts as 80 m. AbsRel = mean |d - d*| / d*, delta1 = share of max(d/d*, d*/d)
    < 1.25, also on the near range <= 30 m that the pipeline uses. Segmentation: IoU per class from one
    confusion matrix over all frames; mIoU over the classes present in the ground truth.
    """
    depth_model = DepthModel(models_dir / "demo_depth.onnx", threads=threads)
    seg_model = SegmentationModel(models_dir / "demo_seg.onnx", threads=threads)
    result: dict[str, Any] = {"heldout": {}, "inference_ms_640x192": {}}
    total_conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    total_depth: list[np.ndarray] = []
    for split in heldout_splits(supersample):
        raw = render_split(split, cache_dir)
        conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
        ratios: list[np.ndarray] = []
        frames = 0
        for folder in robot_folders(raw):
            for frame in open_sequence(folder):
                pred_d = depth_model.predict(frame.image_rgb)
                pred_l = seg_model.predict(frame.image_rgb)
                gt_d, gt_l = frame.depth_m, frame.label_ids
                ok = (gt_d > 0) & (gt_d <= MAX_DEPTH_M) & (gt_l != Label.SKY)
                pd = np.where(pred_d[ok] > 0, pred_d[ok], MAX_DEPTH_M)
                ratios.append(np.stack([pd, gt_d[ok], gt_l[ok]]).astype(np.float32))
                valid_l = gt_l < NUM_CLASSES
                p = np.where(pred_l[valid_l] < NUM_CLASSES, pred_l[valid_l], 0)  # 255 never happens here
                conf += np.bincount(gt_l[valid_l].astype(np.int64) * NUM_CLASSES + p,
                                    minlength=NUM_CLASSES**2).reshape(NUM_CLASSES, NUM_CLASSES)
                frames += 1
        pairs = np.concatenate(ratios, axis=1)
        result["heldout"][split.key] = {"frames": frames, **depth_metrics(pairs), **seg_metrics(conf)}
        total_conf += conf
        total_depth.append(pairs)
    result["heldout"]["all"] = {
        "frames": sum(v["frames"] for v in result["heldout"].values()),
        **depth_metrics(np.concatenate(total_depth, axis=1)), **seg_metrics(total_conf),
    }
    image = open_sequence(robot_folders(render_split(heldout_splits(supersample)[0], cache_dir))[0])[10].image_rgb
    for name, model in (("depth", depth_model), ("seg", seg_model)):
        result["inference_ms_640x192"][name] = {k: round(v, 2) for k, v in
                                                measure_overhead(model, image, repeats=30).items()}
    result["threads"] = threads
    result["onnx_params"] = onnx_parameter_count(models_dir / "demo_depth.onnx")
    return result


def onnx_parameter_count(path: Path) -> int:
    """Number of weights stored in an ONNX file (initializers; batch norms are folded into convolutions)."""
    import onnx

    return int(sum(int(np.prod(t.dims)) for t in onnx.load(str(path)).graph.initializer))


def depth_metrics(pairs: np.ndarray) -> dict[str, float]:
    """AbsRel / delta<1.25 / RMSE of (3, M) [predicted depth; true depth; true label] rows, on all pixels
    and on true depth <= 30 m, plus the AbsRel per true class within 30 m (``depth_absrel_30m_class``)."""
    out: dict[str, Any] = {}
    for tag, sel in (("", slice(None)), ("_30m", pairs[1] <= 30.0)):
        pred, gt = pairs[0][sel].astype(np.float64), pairs[1][sel].astype(np.float64)
        ratio = np.maximum(pred / gt, gt / pred)
        out[f"depth_absrel{tag}"] = round(float(np.mean(np.abs(pred - gt) / gt)), 4)
        out[f"depth_delta1{tag}"] = round(float(np.mean(ratio < 1.25)), 4)
        out[f"depth_rmse_m{tag}"] = round(float(np.sqrt(np.mean((pred - gt) ** 2))), 3)
    near = pairs[:, pairs[1] <= 30.0].astype(np.float64)
    label = near[2].astype(np.int64)
    err = np.bincount(label, np.abs(near[0] - near[1]) / near[1], minlength=NUM_CLASSES)
    count = np.bincount(label, minlength=NUM_CLASSES)
    out["depth_absrel_30m_class"] = {
        CITYSCAPES_CLASSES[c]: round(float(err[c] / count[c]), 4) for c in np.flatnonzero(count[:NUM_CLASSES])
    }
    return out


def seg_metrics(conf: np.ndarray) -> dict[str, Any]:
    """Pixel accuracy, mIoU over classes present in the ground truth, per-class IoU from a (19, 19)
    confusion matrix (rows = truth, columns = prediction)."""
    tp = np.diag(conf).astype(np.float64)
    gt, pred = conf.sum(1), conf.sum(0)
    present = gt > 0
    iou = tp / np.maximum(gt + pred - tp, 1)
    return {
        "seg_pixel_acc": round(float(tp.sum() / max(conf.sum(), 1)), 4),
        "seg_miou": round(float(iou[present].mean()), 4),
        "seg_iou": {CITYSCAPES_CLASSES[c]: round(float(iou[c]), 4) for c in np.flatnonzero(present)},
    }


# --- report ----------------------------------------------------------------------------------------------


def write_report(metrics: dict[str, Any], models_dir: Path) -> None:
    """models/demo_models_metrics.json and models/README.md from the measured numbers."""
    (models_dir / "demo_models_metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    (models_dir / "README.md").write_text(readme_text(metrics))


def readme_text(m: dict[str, Any]) -> str:
    h = m["heldout"]
    rows = "\n".join(
        f"| {k} | {v['frames']} | {v['depth_absrel']:.3f} | {v['depth_delta1']:.3f} "
        f"| {v['depth_absrel_30m']:.3f} | {v['depth_delta1_30m']:.3f} | {v['seg_miou']:.3f} "
        f"| {v['seg_pixel_acc']:.3f} |"
        for k, v in h.items()
    )
    depth_cls = h["all"]["depth_absrel_30m_class"]
    iou = "\n".join(f"| {c} | " + " | ".join(f"{h[k]['seg_iou'].get(c, float('nan')):.3f}" for k in h)
                    + f" | {depth_cls.get(c, float('nan')):.3f} |"
                    for c in CITYSCAPES_CLASSES if any(c in h[k]["seg_iou"] for k in h))
    inf = m["inference_ms_640x192"]
    tr = m.get("training", {})
    ss = tr.get("supersample", 1)
    ss = sorted(set(ss)) if isinstance(ss, list) else [int(ss)]
    ss_line = " or ".join(f"{k}x{k} colour rays averaged per pixel" if k > 1 else "one colour ray per pixel (aliased)"
                          for k in ss) + (" (given to the cities in turn)" if len(ss) > 1 else "")
    kitti_line = (",\n`kitti-paths` seeds 1-3 (KITTI drives of sequences 02-06, which no held-out pair uses)"
                  if any(k.startswith("kitti-paths") for k in tr.get("splits", ())) else "")
    extra = int(tr.get("extra_seeds", 0))
    seeds = f"1-6 and {EXTRA_SEED0}-{EXTRA_SEED0 + extra - 1}" if extra else "1-6"
    spec = NETS[NetSize(tr.get("net", NetSize.SMALL.value))]
    device = tr.get("device", "cpu")
    where = (f"on one {device} GPU (bfloat16 autocast)" if device != "cpu"
             else f"on {tr.get('threads', 2)} CPU threads ({tr.get('machine', '')}, a machine shared with other jobs)")
    train_line = (
        f"Training: {tr['frames']} frames, {tr['steps']} steps of batch {tr['batch']} "
        f"({tr.get('crop_width', CROP_W)}x{INPUT_WH[1]} crops): {tr['train_minutes']:.1f} min of training {where}. "
        f"Rendering + caching the training cities took {tr.get('render_minutes', float('nan')):.1f} min "
        f"({tr.get('render_jobs', 1)} processes)."
        if tr else "Training facts: see demo_models_metrics.json."
    )
    if tr.get("cpu_minutes_estimate"):
        train_line += (f" The same recipe on 2 CPU threads (`--device cpu`, float32: a network of its own, "
                       f"not these bytes): about {tr['cpu_minutes_estimate'] / 60:.0f} h "
                       f"({tr['cpu_steps_per_s']:.2f} steps/s measured with `--time-cpu-steps` on a 2-core "
                       f"machine that a benchmark shared, times the steps).")
    context = ", a whole-image context (global average at 1/16, added back)" if spec.context else ""
    net_line = (f"depthwise-separable blocks with {'-'.join(map(str, spec.widths))} channels, dilated convolutions "
                f"at 1/8 and 1/16{context}"
                f", bilinear upsampling with skip connections, a thin {spec.fine}-channel full-resolution path for "
                "object edges")
    sizes = m.get("export", {})
    size_line = ", ".join(f"`{k}.onnx` {v['size_mb']:.2f} MB" for k, v in sizes.items()) or "see the files"
    return f"""# Demo models for the RGB-only path

Two small CNNs that give `shgm-slam run` metric depth and Cityscapes labels from RGB alone on the
synthetic cities of `shgm_slam.sim`:

{MODEL_TABLE}

Sizes: {size_line}. ONNX opset 17, IR version <= 10, dynamic batch axis, fixed 320x96 input; the adapters
(`DepthModel`, `SegmentationModel`) resize any image to 320x96 and the outputs back to the image grid.

```bash
shgm-slam run --robot car1=DIR/car1 --robot car2=DIR/car2 \\
    --depth-model models/demo_depth.onnx --seg-model models/demo_seg.onnx
```

## What they are and how they were trained
One encoder-decoder (U-Net style: 3x3 stem, {net_line}, a constant y-coordinate input channel;
{m['onnx_params'] / 1e3:.0f} k parameters, `--net {tr.get('net', 'small')}`) with two heads, trained jointly
from scratch by `tools/train_demo_models.py`
(torch {tr.get('torch', '2.13')}, fixed seed, AdamW, warm-up + cosine schedule over the steps or a wall-time
budget, whichever ends first)
and exported twice: the depth export keeps the log-depth head (and zeroes pixels the class head
calls sky), the segmentation export keeps the class head. Losses: on log depth, L1 (3x weight on
walls, fences, poles, lights, signs, vegetation and vehicles: the objects that anchor odometry and
graph nodes) + 0.5 scale-invariant + 0.5 gradient matching at three scales (sky masked, surfaces
beyond the render range clamped to 80 m); class-weighted cross entropy for the labels.
Augmentation: horizontal flips, x crops, brightness/contrast/tint jitter and pixel noise.

Training data (rendered by `shgm_slam.sim.simulate` at 640x192, 82 deg hfov, {ss_line}, 1 frame per
second of motion, shrunk to 320x96 as the adapter does): `airsim-like` seeds {seeds} (two cars + the UAV's
50 deg oblique view from 44-54 m), `synthia-like` seeds {seeds} (forward and backward car cameras){kitti_line}
and three compact worlds (seeds 21-23, 2 frames/s). Different seeds are different cities.

{train_line}

## Held-out accuracy (measured through the adapters at 640x192)
Cities never seen in training: `airsim-like` seed 100 and `synthia-like` seed 101 (every robot,
1 frame/s, rendered with each colour-ray count of the training cities: `-ss2` = antialiased). Depth over
pixels with valid ground truth (not sky,
<= 80 m; a pixel the model calls sky counts as 80 m); "<= 30 m" is the range the pipeline uses
(`extraction.max_depth_m`, `odometry.max_range_m`).
mIoU is over the classes present in the ground truth (the simulator renders no person, rider,
train, motorcycle or bicycle).

| held-out set | frames | AbsRel | delta<1.25 | AbsRel <= 30 m | delta<1.25 <= 30 m | mIoU | pixel acc. |
|---|---|---|---|---|---|---|---|
{rows}

Per-class segmentation IoU, and depth AbsRel per true class within 30 m (all held-out frames):

| class | {' | '.join(f'IoU {k}' for k in h)} | depth AbsRel <= 30 m |
|---|{'---|' * len(h)}---|
{iou}

Inference at the demo resolution (640x192 image, onnxruntime CPU, {m['threads']} threads, median of 30,
adapter pre/postprocessing included in total): depth {inf['depth']['inference_ms']:.1f} ms model /
{inf['depth']['total_ms']:.1f} ms total, segmentation {inf['seg']['inference_ms']:.1f} ms model /
{inf['seg']['total_ms']:.1f} ms total per frame (measured on a shared machine; numbers in
`demo_models_metrics.json`).

## Limits
* Trained only on the simulator's look (its palette, lighting and 82 deg camera); not evaluated on real
  photos and not meant for them: for KITTI use a real exported model (`tools/export_onnx.py`).
* Thin objects are weak: poles are a few pixels wide at 320x96 (low IoU, depth of the background).
* Pseudo-LiDAR odometry from such depth maps is not reliable (the main README's depth-quality study: KISS-ICP
  drifts 9 % at AbsRel 0.03 already). With the first demo models on the `airsim-like` seed-0 demo world
  (car1, car2), KISS-ICP followed only 30-45 % of the true path length: road and facades, predicted
  well, look the same in every frame, while the objects that carry the forward motion (poles, cars,
  trees) have the largest depth errors. With `--odometry gt` the semantic graphs built from those
  models localized both cars (fused ATE 0.9 m and 2.4 m; ground-truth depth + labels: 0.5 m and 1.1 m).

## Licence
{LICENSE}. No third-party data or weights are involved.

Reproduce: `.venv/bin/pip install -e '.[train]' && .venv/bin/python tools/train_demo_models.py --device cuda`
on a machine with a GPU (without `--device cuda`, the same recipe on CPU); `--eval-only` re-measures the
committed models.
"""


# --- main -------------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cache-dir", type=Path, default=Path("/tmp/shgm_demo_models/cache"),
                   help="rendered data cache (outside the repository)")
    p.add_argument("--out-dir", type=Path, default=REPO / "models", help="where the .onnx + cards go")
    p.add_argument("--train-minutes", type=float, default=None,
                   help="training wall-time budget (default: none, --max-steps steps whatever they take)")
    p.add_argument("--max-steps", type=int, default=MAX_STEPS, help="training steps at most")
    p.add_argument("--batch", type=int, default=64, help="crops per step")
    p.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (one-cycle)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch and onnxruntime threads")
    p.add_argument("--supersample", type=_supersample_list, default=SUPERSAMPLE, metavar="S[,S...]",
                   help="render the training cities with S x S colour rays per pixel (several: given to the "
                        "cities in turn); the held-out cities are rendered with each")
    p.add_argument("--extra-seeds", type=int, default=EXTRA_SEEDS, metavar="N",
                   help=f"N more airsim-like and synthia-like training cities each (seeds {EXTRA_SEED0}...)")
    p.add_argument("--net", type=NetSize, default=NetSize.BASE, choices=list(NetSize),
                   help="network size (small: the first demo models; base: wider and deeper, for a GPU)")
    p.add_argument("--device", default="cpu", help="torch device for training (cpu, cuda)")
    p.add_argument("--render-jobs", type=int, default=os.cpu_count() or 1,
                   help="render the training cities in this many processes")
    p.add_argument("--kitti-paths-worlds", action=argparse.BooleanOptionalAction, default=KITTI_PATHS_WORLDS,
                   help="also train on three kitti-paths cities (KITTI drives 02-06; needs ../shared/data)")
    p.add_argument("--eval-only", action="store_true", help="only evaluate the models in --out-dir")
    p.add_argument("--render-only", action="store_true", help="only render + cache the training/held-out data")
    p.add_argument("--save-weights", type=Path, default=None, metavar="PT",
                   help="also save the trained network's state dict (torch.save) here")
    p.add_argument("--time-cpu-steps", type=int, default=0, metavar="N",
                   help="time N training steps of --net/--batch on CPU (--threads) and record, in --out-dir's "
                        "metrics, how long the recorded training would take on CPU")
    p.add_argument("--scale-weight", type=float, default=SCALE_WEIGHT,
                   help="weight of the per-image scale term of the depth loss (each image's absolute mean log error)")
    p.add_argument("--crop-width", type=int, default=CROP_W,
                   help=f"training crop width in pixels, a multiple of 16 up to {INPUT_WH[0]} (the whole image)")
    p.add_argument("--airsim-fps", type=float, default=AIRSIM_FPS,
                   help="frames per second of motion rendered from the airsim-like training cities")
    p.add_argument("--skip-eval", action="store_true",
                   help="train and export only (evaluate later here with --eval-only --out-dir DIR)")
    return p


def _supersample_list(text: str) -> tuple[int, ...]:
    values = tuple(int(v) for v in text.split(","))
    if not values or any(not 1 <= v <= 8 for v in values):
        raise argparse.ArgumentTypeError(f"S must be 1..8, got {text!r}")
    return values


def _device_name(device: str) -> str:
    import torch

    return torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu"


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if not (16 <= args.crop_width <= INPUT_WH[0] and args.crop_width % 16 == 0):
        raise SystemExit(f"--crop-width {args.crop_width}: a multiple of 16 from 16 to {INPUT_WH[0]}")
    if not args.airsim_fps > 0:
        raise SystemExit(f"--airsim-fps {args.airsim_fps}: must be > 0")
    import torch

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    previous = args.out_dir / "demo_models_metrics.json"
    metrics: dict[str, Any] = {}
    if args.time_cpu_steps:
        rate = cpu_steps_per_s(NETS[args.net], args.batch, args.time_cpu_steps)
        metrics = json.loads(previous.read_text())
        tr = metrics["training"]
        tr["cpu_steps_per_s"] = round(rate, 3)
        tr["cpu_minutes_estimate"] = round(tr["steps"] / rate / 60.0, 1)
        previous.write_text(json.dumps(metrics, indent=2) + "\n")
        print(f"{rate:.2f} steps/s on {args.threads} CPU threads: {tr['steps']} steps "
              f"~{tr['cpu_minutes_estimate']:.0f} min", flush=True)
        return 0
    if args.eval_only:
        if previous.is_file():
            kept = json.loads(previous.read_text())
            metrics = {k: v for k, v in kept.items() if k in ("training", "export")}
    elif args.render_only:
        load_training_set(args.cache_dir, args.supersample, args.kitti_paths_worlds, args.extra_seeds,
                          args.render_jobs, args.airsim_fps)
        for split in heldout_splits(args.supersample):
            render_split(split, args.cache_dir)
        prep = uncached_prepare_minutes(args.cache_dir, args.supersample, args.kitti_paths_worlds, args.extra_seeds,
                                        args.airsim_fps)
        print(f"training data: {prep} min to render + convert; "
              f"this run {(time.perf_counter() - t_start) / 60:.1f} min", flush=True)
        return 0
    else:
        print("rendering training cities ...", flush=True)
        data = load_training_set(args.cache_dir, args.supersample, args.kitti_paths_worlds, args.extra_seeds,
                                 args.render_jobs, args.airsim_fps)
        t_render = time.perf_counter()
        n = data["images"].shape[0]
        budget = "no time limit" if args.train_minutes is None else f"{args.train_minutes:g} min"
        print(f"training on {n} frames, {budget} (at most {args.max_steps} steps, "
              f"batch {args.batch}) ...", flush=True)
        net, log = train(data, args.train_minutes, args.max_steps, args.batch, args.lr, args.seed,
                         NETS[args.net], args.device, args.scale_weight, args.crop_width)
        t_train = time.perf_counter()
        if args.save_weights is not None:
            torch.save(net.state_dict(), args.save_weights)
        metrics["export"] = export_models(net, args.out_dir)
        metrics["training"] = {
            "frames": n, "steps": log["steps_done"], "train_minutes_budget": args.train_minutes,
            "max_steps": args.max_steps, "batch": args.batch, "lr": args.lr, "seed": args.seed,
            "threads": args.threads, "net": args.net.value, "device": _device_name(args.device),
            "splits": [s.key for s in train_splits(args.supersample, args.kitti_paths_worlds, args.extra_seeds,
                                                   args.airsim_fps)],
            "scale_weight": args.scale_weight, "crop_width": args.crop_width, "airsim_fps": args.airsim_fps,
            "supersample": list(args.supersample), "render_jobs": args.render_jobs, "extra_seeds": args.extra_seeds,
            "torch": torch.__version__,
            "render_minutes": round((t_render - t_start) / 60, 2),
            "train_minutes": round((t_train - t_render) / 60, 2),
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "loss_log": log,
        }
    if args.skip_eval:
        (args.out_dir / "demo_models_metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        print(f"trained and exported to {args.out_dir}; not evaluated (--skip-eval)", flush=True)
        return 0
    print("evaluating on held-out cities through the adapters ...", flush=True)
    metrics.update(evaluate(args.out_dir, args.cache_dir, args.threads, args.supersample))
    if "training" in metrics:
        if not args.eval_only:
            metrics["training"]["total_minutes"] = round((time.perf_counter() - t_start) / 60, 2)
        prep = uncached_prepare_minutes(args.cache_dir, args.supersample, args.kitti_paths_worlds, args.extra_seeds,
                                        args.airsim_fps)
        metrics["training"]["render_minutes_uncached"] = prep if prep is not None else metrics["training"].get(
            "render_minutes_uncached")
    write_report(metrics, args.out_dir)
    print(json.dumps({k: metrics[k] for k in ("heldout", "inference_ms_640x192")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
