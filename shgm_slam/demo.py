"""The built-in demo: the airsim-like world (car, car, UAV) simulated once into a cache, then the system.

``shgm-slam demo`` = ``prepare_world`` + ``demo_config`` + ``runner.run_slam``. No robot needs its own
settings: each robot's extraction range, blob size and odometry voxel follow from its first frames
(``scene_scale``), so the UAV at 44-54 m gets its far, fine-grained settings as any new robot would.
"""

from __future__ import annotations

import json
import site
import sys
import sysconfig
from collections.abc import Callable
from pathlib import Path

from shgm_slam.config import ShgmConfig
from shgm_slam.errors import DataError

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
"""Where the trained demo ONNX models live in a source checkout (``models/`` beside the package)."""

INSTALLED_MODELS_SUBDIR = Path("share") / "shgm-slam" / "models"
"""Where an install from a wheel or ``pip install .`` puts them, under the environment's data prefix
(``pyproject.toml``: ``tool.setuptools.data-files``)."""

DEMO_DEPTH_MODEL, DEMO_SEG_MODEL = "demo_depth.onnx", "demo_seg.onnx"
"""File names of the demo depth and segmentation models."""

RESULTS_DIR = Path("results/demo")
RGB_ONLY_RESULTS_DIR = Path("results/demo-rgb")
"""Default results folders: the plain and the ``--rgb-only`` demo never overwrite each other."""

RGB_ONLY_MATCH_EVERY_KEYFRAMES = 5
"""The RGB-only demo matches twice as often (its graphs from predicted depth are noisier)."""


def prepare_world(
    cache: Path, seed: int, simulate_fn: Callable[[Path], object] | None = None
) -> tuple[Path, dict[str, str]]:
    """The cached airsim-like world for ``seed``: ``(folder, {robot: kind})``.

    Args:
        cache: cache folder; the world goes to ``cache/airsim-like-seed<seed>``.
        seed: world seed.
        simulate_fn: called with the folder when the world is not cached yet (renders it).
    """
    world = Path(cache) / f"airsim-like-seed{seed}"
    scenario = world / "scenario.json"
    if not scenario.is_file():
        if simulate_fn is None:
            raise DataError(f"{scenario} is missing: simulate the world first")
        simulate_fn(world)
    try:
        robots = json.loads(scenario.read_text())["robots"]
        kinds = {r["name"]: r.get("kind", "car") for r in robots}
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise DataError(f"{scenario} is unreadable ({exc}); delete {world} to simulate it again") from None
    return world, kinds


def model_dirs() -> list[Path]:
    """Folders that may hold the demo models, in the order searched: the source checkout's ``models/``, then
    ``share/shgm-slam/models`` under this environment's data prefix and under the user base (``pip install
    --user``)."""
    prefixes = (sysconfig.get_path("data"), sys.prefix, site.getuserbase())
    return list(dict.fromkeys([MODELS_DIR, *(Path(p) / INSTALLED_MODELS_SUBDIR for p in prefixes)]))


def demo_model_paths(dirs: list[Path] | None = None) -> tuple[Path, Path]:
    """``(depth, segmentation)``: the demo ONNX models from the first of ``dirs`` (default ``model_dirs()``)
    that holds both.

    Raises:
        DataError: no folder holds both (the message names every folder looked in and what to do).
    """
    dirs = model_dirs() if dirs is None else dirs
    for folder in dirs:
        depth, seg = folder / DEMO_DEPTH_MODEL, folder / DEMO_SEG_MODEL
        if depth.is_file() and seg.is_file():
            return depth, seg
    looked = ", ".join(str(d) for d in dirs)
    raise DataError(
        f"the demo models ({DEMO_DEPTH_MODEL}, {DEMO_SEG_MODEL}) are in none of {looked}: reinstall the package "
        "(`pip install .` from the source checkout ships them), train them in a checkout with `python "
        "tools/train_demo_models.py`, or give your own with --depth-model and --seg-model (`shgm-slam run`)"
    )


def demo_results_dir(*, rgb_only: bool = False) -> Path:
    """``results/demo`` or, for the RGB-only demo, ``results/demo-rgb`` (relative to the working folder)."""
    return RGB_ONLY_RESULTS_DIR if rgb_only else RESULTS_DIR


def demo_config(*, rgb_only: bool = False, base: ShgmConfig | None = None) -> ShgmConfig:
    """The demo's configuration: the defaults, and the demo ONNX models when ``rgb_only``.

    Raises:
        DataError: ``rgb_only`` but the demo models are found nowhere (``demo_model_paths``).
    """
    cfg = (base or ShgmConfig()).model_copy(deep=True)
    if rgb_only:
        cfg.perception.depth_model, cfg.perception.seg_model = demo_model_paths()
        # graphs from predicted depth and labels are noisier and alias more often (repeated city
        # blocks): match twice as often (two agreeing matches to anchor is the default for predicted depth)
        cfg.backend.match_every_keyframes = RGB_ONLY_MATCH_EVERY_KEYFRAMES
    return ShgmConfig.model_validate(cfg.model_dump())
