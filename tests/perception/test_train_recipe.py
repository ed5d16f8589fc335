"""tools/train_demo_models.py: its default recipe is the one the committed demo models were trained with.

The script records the cities it trained on (``training.splits`` in models/demo_models_metrics.json); the
defaults must name the same cities, so that running the script reproduces the committed models' recipe, while
cities rendered another way (``--supersample``) get other cache keys, so that their renders never mix.
"""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
TOOL = REPO / "tools" / "train_demo_models.py"
METRICS = REPO / "models" / "demo_models_metrics.json"


@pytest.fixture(scope="module")
def tool():
    sys.path.insert(0, str(TOOL.parent))
    try:
        spec = importlib.util.spec_from_file_location("train_demo_models", TOOL)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # its dataclasses look their module up while being built
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(TOOL.parent))
    return module


def test_the_defaults_name_the_committed_models_cities(tool) -> None:
    if not METRICS.is_file():
        pytest.skip(f"{METRICS} is absent")
    trained = json.loads(METRICS.read_text())["training"]["splits"]
    # the models were trained when kitti-paths rendered KITTI's 10 Hz frames whatever fps said (named f1 then):
    # the very frames the f10 splits render now
    trained = [re.sub(r"^(kitti-paths-s\d+)-f1\b", r"\1-f10", key) for key in trained]
    assert [s.key for s in tool.train_splits()] == trained


def test_cities_rendered_differently_are_cached_apart(tool) -> None:
    one_ray = tool.train_splits(supersample=1)
    antialiased = tool.train_splits(supersample=2)
    assert all(s.supersample == 2 and s.key.endswith("-ss2") for s in antialiased)
    assert {s.key for s in one_ray}.isdisjoint(s.key for s in antialiased)
    with_kitti = tool.train_splits(kitti_paths=True)
    kitti = [s for s in with_kitti if s.scenario == "kitti-paths"]
    assert len(kitti) == 3 and all(s.kitti_robots and s.frame_stride > 1 for s in kitti)
    assert not any(s.scenario == "kitti-paths" for s in tool.train_splits(kitti_paths=False))
    held_out = {s.key for s in tool.heldout_splits()}
    assert held_out.isdisjoint(s.key for s in with_kitti)


def test_a_strided_split_keeps_every_nth_frame_and_its_scalars(tool) -> None:
    data = {"images": np.arange(10), "prepare_s": np.array(3.0)}
    out = tool._strided(data, 4)
    assert out["images"].tolist() == [0, 4, 8] and float(out["prepare_s"]) == 3.0


def test_several_supersample_factors_go_to_the_cities_in_turn(tool) -> None:
    splits = tool.train_splits(supersample=(1, 2), kitti_paths=True)
    assert [s.supersample for s in splits] == [(1, 2)[i % 2] for i in range(len(splits))]
    assert len({s.key for s in splits}) == len(splits)
    held = tool.heldout_splits((1, 2))
    assert [(s.seed, s.supersample) for s in held] == [(100, 1), (101, 1), (100, 2), (101, 2)]


def test_extra_training_seeds_stay_clear_of_every_benchmark_seed(tool) -> None:
    from shgm_slam.bench.heldout import REPORT_SEEDS, TUNING_SEEDS

    splits = tool.train_splits(extra_seeds=10)
    extra = {s.seed for s in splits} - {s.seed for s in tool.train_splits(extra_seeds=0)}
    assert extra == set(range(tool.EXTRA_SEED0, tool.EXTRA_SEED0 + 10))
    # tuning 10-39 (README), report 200-219 and 300-309, the models' own held-out 100-101, the demo's 0
    benchmark = {*TUNING_SEEDS, *range(30, 40), *REPORT_SEEDS, *range(200, 210), *range(300, 310), 100, 101, 0}
    assert extra.isdisjoint(benchmark)
    assert sum(s.scenario == "airsim-like" for s in splits) == sum(s.scenario == "airsim-like" for s in
                                                                   tool.train_splits(extra_seeds=0)) + 10


def test_a_bad_supersample_list_is_refused(tool) -> None:
    import argparse

    assert tool._supersample_list("1,2") == (1, 2)
    for bad in ("0", "1,9", "a"):
        with pytest.raises((argparse.ArgumentTypeError, ValueError)):
            tool._supersample_list(bad)


def test_both_network_sizes_map_an_image_to_depth_and_labels(tool) -> None:
    torch = pytest.importorskip("torch")
    for size in tool.NetSize:
        net = tool.build_network(tool.NETS[size]).eval()
        with torch.no_grad():
            log_depth, logits = net(torch.zeros(2, 3, 96, 320))
        assert log_depth.shape == (2, 1, 96, 320) and logits.shape == (2, 19, 96, 320)
    small, base = (sum(p.numel() for p in tool.build_network(tool.NETS[s]).parameters()) for s in tool.NetSize)
    assert small == 83620 and base > 4 * small  # the small one is the first demo models' network, unchanged


def test_the_scale_term_is_each_images_mean_log_error(tool) -> None:
    """``--scale-weight``: a prediction 10 % long everywhere costs log(1.1) per unit weight on top of the
    other terms (which the scale-invariant part barely notices); a right prediction costs nothing more."""
    torch = pytest.importorskip("torch")
    gen = torch.Generator().manual_seed(0)
    depth = torch.rand(2, 16, 16, generator=gen) * 50.0 + 1.0
    labels = torch.zeros(2, 16, 16, dtype=torch.long)
    weight = torch.ones(256)
    long_log = torch.log(depth * 1.1)
    with_scale = tool.log_depth_loss(long_log, depth, labels, weight, 1.0)
    extra = with_scale - tool.log_depth_loss(long_log, depth, labels, weight)
    assert float(extra) == pytest.approx(np.log(1.1), rel=1e-5)
    right = torch.log(depth)
    assert float(tool.log_depth_loss(right, depth, labels, weight, 1.0)) == pytest.approx(0.0, abs=1e-4)


def test_airsim_fps_renders_only_the_airsim_like_cities_more_often(tool) -> None:
    base, more = tool.train_splits(), tool.train_splits(airsim_fps=2.0)
    assert len(base) == len(more)
    for a, b in zip(base, more, strict=True):
        if a.scenario == "airsim-like" and not a.compact:
            assert b.fps == 2.0 and a.key != b.key  # cached apart
        else:
            assert a == b
