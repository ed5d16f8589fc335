"""Segmentation adapter: logits vs label maps, layouts, class mapping to train ids, resize-back."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.errors import ModelError
from shgm_slam.labels import IGNORE_ID, Label
from shgm_slam.perception.card import parse_card
from shgm_slam.perception.labels import ADE20K_CLASSES
from shgm_slam.perception.segmentation import SegmentationModel, argmax_classes
from tests.perception.onnx_builders import label_map_model, onehot_logits_model

_ids = itertools.count()


def class_image(class_idx: np.ndarray) -> np.ndarray:
    """RGB image whose red channel is the class index the test models read back."""
    img = np.zeros((*class_idx.shape, 3), dtype=np.uint8)
    img[:, :, 0] = class_idx
    return img


def stripes(width: int = 57, height: int = 20, num_classes: int = 19) -> np.ndarray:
    """(H, W) class indices in vertical stripes 3 px wide, cycling through the classes."""
    return np.broadcast_to((np.arange(width) // 3) % num_classes, (height, width)).astype(np.uint8)


def seg_model(
    tmp_path: Path, builder, output: dict, input_card: dict | None = None, **kwargs
) -> SegmentationModel:
    path = builder(tmp_path / f"s{next(_ids)}.onnx", **kwargs)
    card = {"task": "segmentation", "input": {"scale": 1, **(input_card or {})}, "output": output}
    return SegmentationModel(path, parse_card(card), threads=1)


@pytest.mark.parametrize("nhwc", [False, True])
def test_logits_argmax_gives_cityscapes_ids(tmp_path: Path, nhwc: bool) -> None:
    layout = "NHWC" if nhwc else "NCHW"
    model = seg_model(
        tmp_path, onehot_logits_model, {"kind": "logits"}, {"size": [57, 20], "layout": layout},
        num_classes=19, nhwc=nhwc,
    )  # fmt: skip
    truth = stripes()
    labels = model.predict(class_image(truth))
    assert labels.dtype == np.uint8 and labels.shape == truth.shape
    np.testing.assert_array_equal(labels, truth)


def test_label_map_output_and_out_of_range_indices(tmp_path: Path) -> None:
    model = seg_model(tmp_path, label_map_model, {"kind": "label_map"}, {"size": [57, 20]})
    truth = stripes()
    truth[:5] = 200  # no such class -> ignore
    labels = model.predict(class_image(truth))
    np.testing.assert_array_equal(labels[5:], truth[5:])
    assert (labels[:5] == IGNORE_ID).all()


def test_scores_declared_as_a_label_map_are_refused(tmp_path: Path) -> None:
    """Per-class scores under ``kind: label_map`` made silent garbage labels (0, 1 and ignore only)."""
    with pytest.raises(ModelError, match=r"no axis of size 1 holds the labels.*output.kind: logits"):
        seg_model(tmp_path, onehot_logits_model, {"kind": "label_map"}, {"size": [57, 20]}, num_classes=19,
                  shape=[1, 3, 20, 57])  # fmt: skip
    with pytest.raises(ModelError, match="no axis of size 1 holds the labels"):  # the card's size fixes H, W
        seg_model(tmp_path, onehot_logits_model, {"kind": "label_map"}, {"size": [57, 20]}, num_classes=19)
    scores = seg_model(tmp_path, label_map_model, {"kind": "label_map"}, {"size": [57, 20], "scale": 1 / 255},
                       as_float=True)  # fmt: skip
    with pytest.raises(ModelError, match="not whole class indices"):
        scores.predict(class_image(stripes()))
    whole = seg_model(tmp_path, label_map_model, {"kind": "label_map"}, {"size": [57, 20]}, as_float=True)
    np.testing.assert_array_equal(whole.predict(class_image(stripes())), stripes())  # float class indices: fine
    with pytest.raises(ModelError, match=r"has 19 channels.*output.kind: logits"):  # shapes known only at run time
        whole._label_map(np.zeros((19, 20, 57), dtype=np.float32))


def test_custom_classes_map_through_the_table(tmp_path: Path) -> None:
    output = {
        "kind": "logits",
        "classes": ["ground", "house", "tree", "thing"],
        "mapping": {"ground": "road", 1: 2, "tree": "vegetation", "3": 255},
    }
    model = seg_model(tmp_path, onehot_logits_model, output, {"size": [57, 20]}, num_classes=4)
    truth = stripes(num_classes=4)
    labels = model.predict(class_image(truth))
    lut = np.array([Label.ROAD, Label.BUILDING, Label.VEGETATION, IGNORE_ID], dtype=np.uint8)
    np.testing.assert_array_equal(labels, lut[truth])


def test_ade20k_label_space(tmp_path: Path) -> None:
    model = seg_model(
        tmp_path,
        onehot_logits_model,
        {"kind": "logits", "classes": "ade20k"},
        {"size": [8, 4]},
        num_classes=150,
    )
    expected = {"building": Label.BUILDING, "person": Label.PERSON, "floor": IGNORE_ID, "car": Label.CAR}
    for name, train_id in expected.items():
        idx = np.full((4, 8), ADE20K_CLASSES.index(name), dtype=np.uint8)
        assert (model.predict(class_image(idx)) == train_id).all(), name


def test_unmapped_classes_and_class_count_mismatch_are_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match=r"misses 1 model class\(es\) \(2:gizmo\)"):
        seg_model(
            tmp_path, onehot_logits_model, {"kind": "logits", "classes": ["road", "car", "gizmo"]},
            {"size": [8, 4]}, num_classes=3,
        )  # fmt: skip
    with pytest.raises(ModelError, match=r"4 classes on axis 1 but the card lists 19"):
        seg_model(tmp_path, onehot_logits_model, {"kind": "logits"}, {"size": [8, 4]}, num_classes=4)
    with pytest.raises(ModelError, match="logits must be rank 4"):
        seg_model(tmp_path, label_map_model, {"kind": "logits"}, {"size": [8, 4]})


def test_resized_labels_stay_on_their_pixels(tmp_path: Path) -> None:
    # 2x downscale and back with nearest interpolation: wide stripes survive away from their borders
    model = seg_model(tmp_path, onehot_logits_model, {"kind": "logits"}, {"size": [60, 20]}, num_classes=19)
    truth = np.broadcast_to((np.arange(120) // 12) % 19, (40, 120)).astype(np.uint8)
    labels = model.predict(class_image(truth))
    interior = (np.arange(120) % 12 >= 2) & (np.arange(120) % 12 <= 9)
    np.testing.assert_array_equal(labels[:, interior], truth[:, interior])
    assert (labels == truth).mean() > 0.9


def test_cropped_borders_are_ignore(tmp_path: Path) -> None:
    model = seg_model(
        tmp_path, onehot_logits_model, {"kind": "logits"}, {"size": [20, 20], "resize": "keep_aspect_crop"},
        num_classes=19,
    )  # fmt: skip
    labels = model.predict(class_image(np.full((20, 60), Label.CAR, dtype=np.uint8)))
    assert (labels[:, 20:40] == Label.CAR).all()
    assert (labels[:, :20] == IGNORE_ID).all() and (labels[:, 40:] == IGNORE_ID).all()


def test_argmax_classes_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    logits = rng.standard_normal((19, 23, 31)).astype(np.float32)
    np.testing.assert_array_equal(argmax_classes(logits, 0), np.argmax(logits, axis=0))
    np.testing.assert_array_equal(argmax_classes(logits.transpose(1, 2, 0), 2), np.argmax(logits, axis=0))
    ties = np.zeros((5, 4, 4), dtype=np.float32)
    assert (argmax_classes(ties, 0) == 0).all()  # ties pick the first class, like np.argmax
    region = logits[:, 3:20, 5:25]  # non-contiguous views (cropped output regions) work too
    np.testing.assert_array_equal(argmax_classes(region, 0), np.argmax(region, axis=0))
