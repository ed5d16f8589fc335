"""tools/train_demo_models.py: its default recipe is the one the committed demo models were trained with.

The script records the cities it trained on (``training.splits`` in models/demo_models_metrics.json); the
defaults must name the same cities, so that running the script reproduces the committed models, while the
options studied for antialiased worlds (``--supersample``, ``--kitti-paths-worlds``) change the cities'
cache keys, so that their renders never mix with the default ones.
"""

from __future__ import annotations

import importlib.util
import json
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
    assert [s.key for s in tool.train_splits()] == trained


def test_the_studied_options_render_other_cities(tool) -> None:
    default = {s.key for s in tool.train_splits()}
    antialiased = tool.train_splits(supersample=2)
    assert all(s.supersample == 2 and s.key.endswith("-ss2") for s in antialiased)
    assert default.isdisjoint(s.key for s in antialiased)
    with_kitti = tool.train_splits(kitti_paths=True)
    kitti = [s for s in with_kitti if s.scenario == "kitti-paths"]
    assert len(kitti) == 3 and all(s.kitti_robots and s.frame_stride > 1 for s in kitti)
    held_out = {s.key for s in tool.heldout_splits()}
    assert held_out.isdisjoint(s.key for s in with_kitti)


def test_a_strided_split_keeps_every_nth_frame_and_its_scalars(tool) -> None:
    data = {"images": np.arange(10), "prepare_s": np.array(3.0)}
    out = tool._strided(data, 4)
    assert out["images"].tolist() == [0, 4, 8] and float(out["prepare_s"]) == 3.0
