"""Class-mapping tables from model label spaces to Cityscapes train ids."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.errors import ModelError
from shgm_slam.labels import CITYSCAPES_CLASSES, IGNORE_ID, Label
from shgm_slam.perception.card import LabelSpace
from shgm_slam.perception.labels import ADE20K_CLASSES, ADE20K_TO_TRAIN_ID, class_lut, label_space_classes


def test_cityscapes_classes_map_to_themselves() -> None:
    lut = class_lut(CITYSCAPES_CLASSES)
    assert lut.dtype == np.uint8
    np.testing.assert_array_equal(lut, np.arange(19))


def test_ade20k_table_is_complete_and_sensible() -> None:
    assert len(ADE20K_CLASSES) == 150 and len(set(ADE20K_CLASSES)) == 150
    assert set(ADE20K_TO_TRAIN_ID) <= set(ADE20K_CLASSES)
    lut = class_lut(label_space_classes(LabelSpace.ADE20K), space=LabelSpace.ADE20K)
    assert lut.shape == (150,)
    by_name = dict(zip(ADE20K_CLASSES, lut.tolist(), strict=True))
    assert by_name["building"] == Label.BUILDING and by_name["sky"] == Label.SKY
    assert by_name["road"] == Label.ROAD and by_name["car"] == Label.CAR and by_name["person"] == Label.PERSON
    assert by_name["tree"] == Label.VEGETATION and by_name["traffic light"] == Label.TRAFFIC_LIGHT
    assert by_name["bed"] == IGNORE_ID and by_name["floor"] == IGNORE_ID


def test_explicit_mapping_by_index_name_and_target_kinds() -> None:
    classes = ["Ground", "house", "tree", "thing", "car"]
    lut = class_lut(classes, {"ground": 0, 1: "building", "tree": "Vegetation", "3": "ignore"})
    # "car" is a Cityscapes name and maps by name without an entry
    np.testing.assert_array_equal(lut, [Label.ROAD, Label.BUILDING, Label.VEGETATION, IGNORE_ID, Label.CAR])


def test_explicit_mapping_overrides_label_space_defaults() -> None:
    lut = class_lut(ADE20K_CLASSES, {"floor": 0, "wall": 2}, LabelSpace.ADE20K)
    assert lut[ADE20K_CLASSES.index("floor")] == Label.ROAD
    assert lut[ADE20K_CLASSES.index("wall")] == Label.BUILDING


@pytest.mark.parametrize(
    ("mapping", "needle"),
    [
        ({}, r"misses 2 model class\(es\) \(1:house, 2:tree\)"),
        ({"house": 2, "tree": 8, 7: 1}, "class index 7 is outside"),
        ({"house": 2, "tree": 8, "boat": 1}, "'boat' is not one of the model's classes"),
        ({"house": 2, "tree": 19}, "not a Cityscapes train id"),
        ({"house": 2, "tree": "shrub"}, "'shrub' is not a Cityscapes class"),
    ],
)
def test_mapping_errors_are_actionable(mapping: dict, needle: str) -> None:
    with pytest.raises(ModelError, match=needle):
        class_lut(["road", "house", "tree"], mapping)
