"""The committed demo models (models/demo_depth.onnx, models/demo_seg.onnx) through the adapters.

They are checked the way the pipeline uses them: loaded with their cards, run on a 640x192 frame of a
simulated city they were not trained on, compared with the renderer's ground truth. Skips cleanly when
the model files are absent (e.g. a checkout without models/).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.labels import NUM_CLASSES, Label
from shgm_slam.perception import DepthModel, SegmentationModel
from shgm_slam.perception.card import DepthCard, SegmentationCard, load_card
from shgm_slam.perception.labels import output_class_names
from shgm_slam.sim.render import RenderedFrame, Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario

MODELS = Path(__file__).resolve().parents[2] / "models"
DEPTH_ONNX = MODELS / "demo_depth.onnx"
SEG_ONNX = MODELS / "demo_seg.onnx"
MAX_MODEL_BYTES = 4_000_000


def _require(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"{path} is absent (train it with tools/train_demo_models.py)")
    return path


@pytest.fixture(scope="module")
def views() -> list[RenderedFrame]:
    """Two 640x192 car views of a compact city (seed 99: not a training seed)."""
    plan = build_scenario("airsim-like", ScenarioOptions(seed=99, compact=True))
    car = plan.robots[0]
    with Renderer(plan.world, make_intrinsics(640, 192), max_depth_m=200.0) as renderer:
        return [renderer.render(car.T_world_cam[i]) for i in (10, len(car) // 2)]


@pytest.fixture(scope="module")
def depth_model() -> DepthModel:
    return DepthModel(_require(DEPTH_ONNX), threads=2)


@pytest.fixture(scope="module")
def seg_model() -> SegmentationModel:
    return SegmentationModel(_require(SEG_ONNX), threads=2)


def test_cards_and_files() -> None:
    depth_card = load_card(_require(DEPTH_ONNX))
    seg_card = load_card(_require(SEG_ONNX))
    assert isinstance(depth_card, DepthCard) and isinstance(seg_card, SegmentationCard)
    assert depth_card.input.size == seg_card.input.size == (320, 96)
    names = output_class_names(seg_card.output)
    assert names[Label.CAR] == "car" and len(names) == NUM_CLASSES
    for card in (depth_card, seg_card):
        assert "synthetic" in (card.license or "")
    for path in (DEPTH_ONNX, SEG_ONNX):
        assert path.stat().st_size <= MAX_MODEL_BYTES


def test_depth_on_unseen_city(depth_model: DepthModel, views: list[RenderedFrame]) -> None:
    view = views[0]
    depth = depth_model.predict(view.image_rgb)
    assert depth.shape == view.depth_m.shape and depth.dtype == np.float32
    assert np.all(np.isfinite(depth))
    card = depth_model.card.output
    valid = depth > 0
    assert np.all((depth[valid] >= card.min_depth_m) & (depth[valid] <= card.max_depth_m))
    gt = view.depth_m
    ok = (gt > 0) & (gt <= card.max_depth_m) & (view.label_ids != Label.SKY) & valid
    assert ok.mean() > 0.3  # the model gives depth on most surfaces
    absrel = float(np.mean(np.abs(depth[ok] - gt[ok]) / gt[ok]))
    assert absrel < 0.3, f"AbsRel {absrel:.3f}"
    trivial = float(np.mean(np.abs(np.median(gt[ok]) - gt[ok]) / gt[ok]))  # one constant depth
    assert absrel < trivial
    sky = view.label_ids == Label.SKY
    if sky.sum() > 500:
        assert np.mean(depth[sky] == 0) > 0.8  # the model marks sky invalid


def test_segmentation_on_unseen_city(seg_model: SegmentationModel, views: list[RenderedFrame]) -> None:
    view = views[0]
    labels = seg_model.predict(view.image_rgb)
    assert labels.shape == view.label_ids.shape and labels.dtype == np.uint8
    assert labels.max() < NUM_CLASSES  # every pixel gets a train id, none is ignore
    accuracy = float(np.mean(labels == view.label_ids))
    majority = float(np.mean(view.label_ids == np.bincount(view.label_ids.ravel()).argmax()))
    assert accuracy > 0.7 and accuracy > majority, f"pixel accuracy {accuracy:.3f} (majority {majority:.3f})"


def test_batch_equals_single(
    depth_model: DepthModel, seg_model: SegmentationModel, views: list[RenderedFrame]
) -> None:
    images = [v.image_rgb for v in views]
    for model in (depth_model, seg_model):
        batch = model.predict_batch(images)
        assert len(batch) == 2
        for image, out in zip(images, batch, strict=True):
            np.testing.assert_allclose(out, model.predict(image), rtol=1e-4, atol=1e-3)
