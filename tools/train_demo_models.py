"""Train the demo monocular depth and segmentation models on simulated cities and export them to ONNX.

The RGB-only path of shgm_slam needs a depth model and a segmentation model. These demo models are
small CNNs trained here, on CPU, on images rendered by ``shgm_slam.sim`` (no external data, no
downloads), so the whole system runs from RGB alone on the synthetic worlds. Steps::

    render   simulate() airsim-like (cars + UAV) and synthia-like (forward + backward cameras) cities of
             the TRAINING seeds at 1 frame/s, 640x192; cache them as .npz at the model input size
    train    one small encoder-decoder (depthwise-separable, 24-32-64-128 channels, a thin full-resolution
             path) with a log-depth head and a 19-class head, jointly, for a wall-time budget (default
             38 min, 9000 steps at most): class-weighted L1 + scale-invariant + gradient loss on log
             depth (sky masked, far clamped to 80 m) and class-weighted cross entropy
    export   two ONNX files (opset 17, IR <= 10, dynamic batch, fixed 320x96 input) + model cards:
             demo_depth.onnx -> metric depth (N, 1, 96, 320), 0 where the model sees sky;
             demo_seg.onnx   -> label map (N, 96, 320) of Cityscapes train ids (ArgMax in the graph)
    evaluate HELD-OUT cities (airsim-like seed 100, synthia-like seed 101) through the project's
             DepthModel / SegmentationModel adapters at the demo resolution 640x192: depth AbsRel,
             delta < 1.25, segmentation mIoU + per-class IoU, inference ms/frame with 2 threads;
             writes models/demo_models_metrics.json and models/README.md

Usage (needs the ``train`` extra: ``.venv/bin/pip install -e '.[train]'``)::

    .venv/bin/python tools/train_demo_models.py                 # everything, ~26 min on 2 cores
    .venv/bin/python tools/train_demo_models.py --eval-only     # re-measure the models in models/
    .venv/bin/python tools/train_demo_models.py --render-only   # only render + cache the data
    .venv/bin/python tools/train_demo_models.py --supersample 2 --kitti-paths-worlds --out-dir DIR
                                          # the recipe measured for antialiased worlds (README), not committed

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
from dataclasses import dataclass
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
CROP_W = 192  # training crops along x (the y-coordinate channel keeps the vertical position)
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
    frame_stride: int = 1  # kitti-paths follows KITTI's 10 Hz poses whatever ``fps`` says: keep every n-th frame

    @property
    def key(self) -> str:
        ss = f"-ss{self.supersample}" if self.supersample > 1 else ""
        return f"{self.scenario}-s{self.seed}-f{self.fps:g}{'-compact' if self.compact else ''}{ss}"


SUPERSAMPLE = 1
"""Colour rays per pixel side of the training and held-out renders (``--supersample``), as the benchmark worlds
are rendered (one ray per pixel; 640x192 shrunk 2x to the model input averages 2 x 2 of them). One ray per
pixel aliases the road's fine texture (README, held-out notes); models trained with ``--supersample 2`` were
measured for antialiased worlds and are not the committed ones (README, held-out notes)."""
KITTI_TRAIN_DRIVES = (("02:0-301", "05:0-301"), ("03:0-301", "06:0-301"), ("04:0-271", "05:1200-1501"))
"""``--kitti-paths-worlds``: kitti-paths training worlds driving KITTI sequences the held-out pairs never use
(02-06; their poses from ``../shared/data``). Not in the committed models: measured, not better (README)."""


def train_splits(supersample: int = SUPERSAMPLE, kitti_paths: bool = False) -> tuple[Split, ...]:
    """The training cities (seeds the held-out benchmark never uses)."""
    kitti = tuple(Split("kitti-paths", s, supersample=supersample, kitti_robots=d, frame_stride=5)
                  for s, d in zip(range(1, 4), KITTI_TRAIN_DRIVES, strict=True)) if kitti_paths else ()
    return (
        *(Split("airsim-like", s, supersample=supersample) for s in range(1, 7)),
        *(Split("synthia-like", s, supersample=supersample) for s in range(1, 7)),
        *kitti,
        Split("airsim-like", 21, fps=2.0, compact=True, supersample=supersample),
        Split("airsim-like", 22, fps=2.0, compact=True, supersample=supersample),
        Split("synthia-like", 23, fps=2.0, compact=True, supersample=supersample),
    )


def heldout_splits(supersample: int = SUPERSAMPLE) -> tuple[Split, ...]:
    """The cities the models are measured on after training (never trained on)."""
    return (Split("airsim-like", 100, supersample=supersample), Split("synthia-like", 101, supersample=supersample))


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
    cache_dir: Path, supersample: int = SUPERSAMPLE, kitti_paths: bool = False
) -> dict[str, np.ndarray]:
    """All training splits concatenated: images (N, 96, 320, 3) uint8, depth_m (N, 96, 320) float16,
    labels (N, 96, 320) uint8."""
    parts = [load_split(s, cache_dir) for s in train_splits(supersample, kitti_paths)]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("images", "depth_m", "labels")}


def uncached_prepare_minutes(
    cache_dir: Path, supersample: int = SUPERSAMPLE, kitti_paths: bool = False
) -> float | None:
    """Minutes it took to render + convert all training splits when the cache was built (None if unknown)."""
    total = 0.0
    for split in train_splits(supersample, kitti_paths):
        path = _split_cache(split, cache_dir)
        if not path.is_file():
            return None
        with np.load(path) as data:
            if "prepare_s" not in data.files:
                return None
            total += float(data["prepare_s"])
    return round(total / 60.0, 2)


# --- the network --------------------------------------------------------------------------------------


def build_network(widths: tuple[int, int, int, int] = WIDTHS) -> Any:
    """The joint depth + segmentation encoder-decoder (torch module; imported lazily).

    forward(x (N, 3, H, W) normalized RGB) -> (log_depth (N, 1, H, W) log metres, logits (N, 19, H, W));
    H, W multiples of 16. Most of the compute sits at 1/4..1/16 resolution (what makes CPU training in
    minutes possible); a thin full-resolution path (8 channels) sharpens the edges of thin objects. A
    constant y-coordinate channel joins the input: metric depth from one view depends on where a pixel
    sits relative to the horizon.
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

    a, b, c, d = widths

    class DemoNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.enc1 = conv(4, a, 2)  # 1/2
            self.enc2 = nn.Sequential(sep(a, b, 2), sep(b, b))  # 1/4
            self.enc3 = nn.Sequential(sep(b, c, 2), sep(c, c), sep(c, c, dilation=2))  # 1/8
            self.enc4 = nn.Sequential(sep(c, d, 2), sep(d, d, dilation=2), sep(d, d, dilation=4))  # 1/16
            self.dec3 = sep(d + c, c)
            self.dec2 = sep(c + b, 48)
            self.dec1 = sep(48 + a, a)
            self.fine = conv(4, 8)  # full resolution: edges of thin objects
            self.dec0 = sep(a + 8, 16)
            self.depth_head = nn.Conv2d(16, 1, 1)
            self.seg_head = nn.Conv2d(16, NUM_CLASSES, 1)
            nn.init.constant_(self.depth_head.bias, float(np.log(15.0)))

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            n, _, h, w = x.shape
            y = torch.linspace(-1.0, 1.0, h, dtype=x.dtype).view(1, 1, h, 1).expand(n, 1, h, w)
            xy = torch.cat([x, y], 1)
            x1 = self.enc1(xy)
            x2 = self.enc2(x1)
            x3 = self.enc3(x2)
            x4 = self.enc4(x3)

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


def log_depth_loss(log_depth: Any, depth_m: Any, labels: Any, class_weight: Any) -> Any:
    """Depth loss of (N, H, W) predicted log depth against (N, H, W) true depth in metres (0 = beyond the
    render range, read as 80 m) over non-sky pixels: class-weighted L1 on log depth (``class_weight``
    (256,) per label: objects that anchor odometry and graph nodes count more) + 0.5 x scale-invariant
    log error + gradient matching at 1/1, 1/2 and 1/4 scale (sharp depth edges at object borders)."""
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
    return l1 + 0.5 * si + 0.5 * grad


def learning_rate(peak: float, progress: float, warmup: float = 0.04) -> float:
    """Linear warm-up then cosine decay to 2 % of ``peak`` over ``progress`` in [0, 1]."""
    if progress < warmup:
        return peak * (0.1 + 0.9 * progress / warmup)
    t = (progress - warmup) / (1.0 - warmup)
    return peak * (0.02 + 0.98 * 0.5 * (1.0 + np.cos(np.pi * min(t, 1.0))))


def train(
    data: dict[str, np.ndarray], minutes: float, max_steps: int, batch: int, lr: float, seed: int
) -> tuple[Any, dict]:
    """Train the joint network for ``minutes`` of wall time or ``max_steps`` steps, whichever ends first
    (the learning-rate schedule follows that progress, so a busy machine gets a complete, shorter run).

    Returns:
        the network (eval mode) and a log: steps, losses every 50 steps, wall time.
    """
    import torch
    from torch.nn import functional as F  # noqa: N812 (torch's own convention)

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = build_network().to(memory_format=torch.channels_last)  # faster CPU convolutions (measured)
    images = torch.from_numpy(data["images"]).permute(0, 3, 1, 2).contiguous()  # (N, 3, H, W) uint8
    depth = torch.from_numpy(data["depth_m"].astype(np.float32))
    labels = torch.from_numpy(data["labels"].astype(np.int64))
    weights = torch.from_numpy(class_weights(data["labels"]))
    thing_weight = torch.ones(256)
    thing_weight[list(THING_CLASSES)] = THING_DEPTH_WEIGHT
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    n, W = images.shape[0], images.shape[3]
    log: dict[str, list] = {"step": [], "depth_loss": [], "seg_loss": [], "elapsed_s": []}
    t0 = time.perf_counter()
    run_d = run_s = 0.0
    step = 0
    net.train()
    while (progress := max((time.perf_counter() - t0) / (60.0 * minutes), step / max_steps)) < 1.0:
        step += 1
        for group in opt.param_groups:
            group["lr"] = learning_rate(lr, progress)
        idx = torch.from_numpy(rng.integers(0, n, batch))
        x0 = 2 * int(rng.integers(0, (W - CROP_W) // 2 + 1))
        x = images[idx, :, :, x0 : x0 + CROP_W].float() / 255.0
        d = depth[idx, :, x0 : x0 + CROP_W]
        lab = labels[idx, :, x0 : x0 + CROP_W]
        if rng.random() < 0.5:
            x, d, lab = x.flip(3), d.flip(2), lab.flip(2)
        # photometric jitter per image: contrast, gain, per-channel tint, pixel noise
        c = torch.from_numpy(rng.uniform(0.8, 1.2, (batch, 1, 1, 1)).astype(np.float32))
        g = torch.from_numpy(rng.uniform(0.7, 1.3, (batch, 1, 1, 1)).astype(np.float32))
        tint = torch.from_numpy(rng.uniform(0.9, 1.1, (batch, 3, 1, 1)).astype(np.float32))
        m = x.mean((1, 2, 3), keepdim=True)
        x = ((x - m) * c + m) * g * tint + 0.02 * torch.randn_like(x)
        x = ((x.clamp(0.0, 1.0) - mean) / std).contiguous(memory_format=torch.channels_last)

        log_depth, logits = net(x)
        depth_loss = log_depth_loss(log_depth[:, 0], d, lab, thing_weight)
        seg_loss = F.cross_entropy(logits, lab, weight=weights, ignore_index=IGNORE_ID)
        opt.zero_grad(set_to_none=True)
        (depth_loss + seg_loss).backward()
        opt.step()
        run_d += depth_loss.item()
        run_s += seg_loss.item()
        if step % 50 == 0:
            elapsed = time.perf_counter() - t0
            lr_now = opt.param_groups[0]["lr"]
            print(f"  step {step}  depth {run_d / 50:.3f}  seg {run_s / 50:.3f}  lr {lr_now:.1e}  "
                  f"{elapsed / 60:.1f} min", flush=True)
            for key, val in zip(log, (step, run_d / 50, run_s / 50, elapsed), strict=True):
                log[key].append(round(float(val), 4))
            run_d = run_s = 0.0
    print(f"  trained {step} steps in {(time.perf_counter() - t0) / 60:.1f} min", flush=True)
    log["steps_done"] = step
    return net.to(memory_format=torch.contiguous_format).eval(), log


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


def evaluate(models_dir: Path, cache_dir: Path, threads: int = 2, supersample: int = SUPERSAMPLE) -> dict[str, Any]:
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
    ss = int(tr.get("supersample", 1))
    ss_line = (f"{ss}x{ss} colour rays averaged per pixel" if ss > 1 else "one colour ray per pixel (aliased)")
    kitti_line = (",\n`kitti-paths` seeds 1-3 (KITTI drives of sequences 02-06, which no held-out pair uses)"
                  if any(k.startswith("kitti-paths") for k in tr.get("splits", ())) else "")
    sizes = m.get("export", {})
    train_line = (
        f"Training: {tr['frames']} frames, {tr['steps']} steps of batch {tr['batch']} "
        f"({CROP_W}x{INPUT_WH[1]} crops): {tr['train_minutes']:.1f} min of training on {tr['threads']} CPU "
        f"threads ({tr['machine']}, a machine shared with other jobs); the whole script took "
        f"{tr['total_minutes']:.1f} min with the rendered data already cached. Rendering + caching the "
        f"training cities from scratch took {tr.get('render_minutes_uncached') or float('nan'):.1f} min."
        if tr else "Training facts: see demo_models_metrics.json."
    )
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
One encoder-decoder (U-Net style: 3x3 stem, depthwise-separable blocks with 24-32-64-128 channels,
dilated convolutions at 1/8 and 1/16, bilinear upsampling with skip connections, a thin 8-channel
full-resolution path for object edges, a constant y-coordinate input channel; {m['onnx_params'] / 1e3:.0f} k
parameters) with two heads, trained jointly from scratch on CPU by `tools/train_demo_models.py`
(torch {tr.get('torch', '2.13')}, fixed seed, AdamW, warm-up + cosine schedule over a wall-time budget)
and exported twice: the depth export keeps the log-depth head (and zeroes pixels the class head
calls sky), the segmentation export keeps the class head. Losses: on log depth, L1 (3x weight on
walls, fences, poles, lights, signs, vegetation and vehicles: the objects that anchor odometry and
graph nodes) + 0.5 scale-invariant + 0.5 gradient matching at three scales (sky masked, surfaces
beyond the render range clamped to 80 m); class-weighted cross entropy for the labels.
Augmentation: horizontal flips, x crops, brightness/contrast/tint jitter and pixel noise.

Training data (rendered by `shgm_slam.sim.simulate` at 640x192, 82 deg hfov, {ss_line}, 1 frame per
second of motion, shrunk to 320x96 as the adapter does): `airsim-like` seeds 1-6 (two cars + the UAV's
50 deg oblique view from 44-54 m), `synthia-like` seeds 1-6 (forward and backward car cameras){kitti_line}
and three compact worlds (seeds 21-23, 2 frames/s). Different seeds are different cities.

{train_line}

## Held-out accuracy (measured through the adapters at 640x192)
Cities never seen in training: `airsim-like` seed 100 and `synthia-like` seed 101 (every robot,
1 frame/s, rendered as the training cities). Depth over pixels with valid ground truth (not sky,
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
* Pseudo-LiDAR odometry from these depth maps is not reliable. On the `airsim-like` seed-0 demo world
  (car1, car2), KISS-ICP followed only 30-45 % of the true path length: road and facades, predicted
  well, look the same in every frame, while the objects that carry the forward motion (poles, cars,
  trees) have the largest depth errors. With `--odometry gt` the semantic graphs built from these
  models localized both cars (fused ATE 0.9 m and 2.4 m; ground-truth depth + labels: 0.5 m and 1.1 m).

## Licence
{LICENSE}. No third-party data or weights are involved.

Reproduce: `.venv/bin/pip install -e '.[train]' && .venv/bin/python tools/train_demo_models.py`
(`--eval-only` re-measures the committed models).
"""


# --- main -------------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cache-dir", type=Path, default=Path("/tmp/shgm_demo_models/cache"),
                   help="rendered data cache (outside the repository)")
    p.add_argument("--out-dir", type=Path, default=REPO / "models", help="where the .onnx + cards go")
    p.add_argument("--train-minutes", type=float, default=38.0, help="training wall-time budget")
    p.add_argument("--max-steps", type=int, default=9000, help="training steps at most")
    p.add_argument("--batch", type=int, default=12, help="crops per step")
    p.add_argument("--lr", type=float, default=3e-3, help="peak learning rate (one-cycle)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch and onnxruntime threads")
    p.add_argument("--supersample", type=int, default=SUPERSAMPLE, choices=range(1, 9), metavar="S",
                   help="render every training and held-out city with S x S colour rays per pixel")
    p.add_argument("--kitti-paths-worlds", action="store_true",
                   help="also train on three kitti-paths cities (KITTI drives 02-06; needs ../shared/data)")
    p.add_argument("--eval-only", action="store_true", help="only evaluate the models in --out-dir")
    p.add_argument("--render-only", action="store_true", help="only render + cache the training/held-out data")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    previous = args.out_dir / "demo_models_metrics.json"
    metrics: dict[str, Any] = {}
    if args.eval_only:
        if previous.is_file():
            kept = json.loads(previous.read_text())
            metrics = {k: v for k, v in kept.items() if k in ("training", "export")}
    elif args.render_only:
        load_training_set(args.cache_dir, args.supersample, args.kitti_paths_worlds)
        for split in heldout_splits(args.supersample):
            render_split(split, args.cache_dir)
        prep = uncached_prepare_minutes(args.cache_dir, args.supersample, args.kitti_paths_worlds)
        print(f"training data: {prep} min to render + convert; "
              f"this run {(time.perf_counter() - t_start) / 60:.1f} min", flush=True)
        return 0
    else:
        print("rendering training cities ...", flush=True)
        data = load_training_set(args.cache_dir, args.supersample, args.kitti_paths_worlds)
        t_render = time.perf_counter()
        n = data["images"].shape[0]
        print(f"training on {n} frames for {args.train_minutes:g} min (at most {args.max_steps} steps, "
              f"batch {args.batch}) ...", flush=True)
        net, log = train(data, args.train_minutes, args.max_steps, args.batch, args.lr, args.seed)
        t_train = time.perf_counter()
        metrics["export"] = export_models(net, args.out_dir)
        metrics["training"] = {
            "frames": n, "steps": log["steps_done"], "train_minutes_budget": args.train_minutes,
            "max_steps": args.max_steps, "batch": args.batch, "lr": args.lr, "seed": args.seed,
            "threads": args.threads, "splits": [s.key for s in train_splits(args.supersample, args.kitti_paths_worlds)],
            "supersample": args.supersample, "torch": torch.__version__,
            "render_minutes": round((t_render - t_start) / 60, 2),
            "train_minutes": round((t_train - t_render) / 60, 2),
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "loss_log": log,
        }
    print("evaluating on held-out cities through the adapters ...", flush=True)
    metrics.update(evaluate(args.out_dir, args.cache_dir, args.threads, args.supersample))
    if "training" in metrics:
        if not args.eval_only:
            metrics["training"]["total_minutes"] = round((time.perf_counter() - t_start) / 60, 2)
        prep = uncached_prepare_minutes(args.cache_dir, args.supersample, args.kitti_paths_worlds)
        metrics["training"]["render_minutes_uncached"] = prep if prep is not None else metrics["training"].get(
            "render_minutes_uncached")
    write_report(metrics, args.out_dir)
    print(json.dumps({k: metrics[k] for k in ("heldout", "inference_ms_640x192")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
