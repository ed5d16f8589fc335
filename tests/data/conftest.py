"""Small synthetic sequences for the data tests (random images, depth, labels, poses)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.data import SequenceWriter
from shgm_slam.geometry.se3 import make_pose, so3_exp
from shgm_slam.types import Frame, Intrinsics

INTRINSICS = Intrinsics(fx=50.0, fy=52.0, cx=15.5, cy=11.25, width=32, height=24)


def make_frames(n: int, seed: int = 0, with_pose: bool = True) -> list[Frame]:
    """``n`` random frames at INTRINSICS: noisy RGB, depth 0..80 m with invalid pixels, labels, poses."""
    rng = np.random.default_rng(seed)
    h, w = INTRINSICS.height, INTRINSICS.width
    frames = []
    for i in range(n):
        depth = rng.uniform(0.5, 80.0, (h, w)).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 0.0
        depth[0, 0], depth[0, 1], depth[0, 2] = np.nan, np.inf, -3.0
        labels = rng.integers(0, 19, (h, w), dtype=np.uint8)
        labels[1, :4] = 255
        pose = make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 0.5) if with_pose else None  # ~10 m/s
        frames.append(
            Frame(
                index=i,
                timestamp_s=1.0e3 + 0.1 * i + rng.uniform(0, 1e-3),
                intrinsics=INTRINSICS,
                image_rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                depth_m=depth,
                label_ids=labels,
                T_world_cam=pose,
            )
        )
    return frames


def write_frames(root: Path, frames: list[Frame], **kwargs: bool) -> Path:
    with SequenceWriter(root, INTRINSICS, **kwargs) as writer:
        for frame in frames:
            writer.write(frame)
    return root


@pytest.fixture
def frames() -> list[Frame]:
    return make_frames(8)


@pytest.fixture
def seq_dir(tmp_path: Path, frames: list[Frame]) -> Path:
    """A written 8-frame sequence in our layout (image_2, depth, semantic, calib, times, poses)."""
    return write_frames(tmp_path / "seq", frames)
