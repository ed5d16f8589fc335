"""Model cards: parsing, defaults, enums, and clear errors naming the file and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from shgm_slam.errors import ModelError
from shgm_slam.perception.card import (
    ColorOrder,
    DepthCard,
    DepthKind,
    InputDtype,
    LabelSpace,
    Layout,
    ResizeMode,
    SegmentationCard,
    SegOutputKind,
    card_to_yaml,
    default_card_path,
    load_card,
    parse_card,
    write_card,
)
from shgm_slam.perception.labels import output_class_names


def test_depth_card_defaults_and_fraction_scale() -> None:
    card = parse_card({"task": "depth", "input": {"size": [640, 192], "scale": "1/255"}})
    assert isinstance(card, DepthCard)
    assert card.input.size == (640, 192)
    assert card.input.scale == pytest.approx(1 / 255)
    assert card.input.layout is Layout.NCHW and card.input.color_order is ColorOrder.RGB
    assert card.input.resize is ResizeMode.STRETCH and card.input.dtype is InputDtype.FLOAT32
    assert card.output.kind is DepthKind.METRIC


def test_effective_scale_depends_on_dtype() -> None:
    assert parse_card({"task": "depth"}).input.effective_scale == pytest.approx(1 / 255)
    assert parse_card({"task": "depth", "input": {"dtype": "uint8"}}).input.effective_scale == 1.0


def test_enums_parse_case_insensitively() -> None:
    inp = {"layout": "nhwc", "color_order": "bgr", "resize": "KEEP_ASPECT_PAD"}
    output = {"kind": "label_map", "classes": "ADE20K"}
    card = parse_card({"task": "Segmentation", "input": inp, "output": output})
    assert isinstance(card, SegmentationCard)
    assert card.input.layout is Layout.NHWC and card.input.color_order is ColorOrder.BGR
    assert card.input.resize is ResizeMode.KEEP_ASPECT_PAD
    assert card.output.kind is SegOutputKind.LABEL_MAP and card.output.classes is LabelSpace.ADE20K
    assert len(output_class_names(card.output)) == 150


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ({"input": {}}, "task"),
        ({"task": "depht"}, "task"),
        ({"task": "depth", "input": {"layout": "NCWH"}}, "input.layout"),
        ({"task": "depth", "inptu": {}}, "inptu"),
        ({"task": "depth", "input": {"size": [640, 0]}}, "input.size"),
        ({"task": "depth", "input": {"dtype": "uint8", "mean": [0.5, 0.5, 0.5]}}, "uint8"),
        ({"task": "depth", "input": {"std": [1, 0, 1]}}, "std"),
        ({"task": "depth", "output": {"kind": "disparity"}}, "focal_x_baseline"),
        ({"task": "depth", "output": {"min_depth_m": 50, "max_depth_m": 10}}, "max_depth_m"),
        ({"task": "segmentation", "output": {"kind": "probabilities"}}, "output.kind"),
        ({"task": "segmentation", "output": {"classes": []}}, "classes"),
        # accepted before, and silently ignored or garbage
        ({"task": "depth", "output": {"kind": "metric", "scale": 2.0}}, "would be ignored"),
        ({"task": "depth", "output": {"kind": "relative", "scale": float("nan")}}, "finite number"),
        ({"task": "segmentation", "input": {"mean": [1e30, 0, 0]}}, "check them"),
        ({"task": "segmentation", "input": {"std": [1e-9, 1, 1]}}, "check them"),
    ],
)
def test_invalid_cards_name_the_field(data: dict, needle: str) -> None:
    with pytest.raises(ModelError, match=needle.replace(".", r"\.")):
        parse_card(data, where="model card x.yaml")


def test_load_card_next_to_model_and_errors(tmp_path: Path) -> None:
    model = tmp_path / "net.onnx"
    with pytest.raises(ModelError, match=r"net\.yaml not found.*--card"):
        load_card(model)
    (tmp_path / "net.yaml").write_text("task: depth\ninput: {size: [64, 32]}\n")
    assert load_card(model).input.size == (64, 32)
    assert default_card_path(model) == tmp_path / "net.yaml"
    (tmp_path / "broken.yaml").write_text("task: [depth\n")
    with pytest.raises(ModelError, match=r"broken\.yaml is not valid YAML"):
        load_card(model, tmp_path / "broken.yaml")
    (tmp_path / "list.yaml").write_text("- task\n")
    with pytest.raises(ModelError, match="mapping"):
        load_card(model, tmp_path / "list.yaml")
    (tmp_path / "bad.yaml").write_text("task: depth\noutput: {kind: metrc}\n")
    with pytest.raises(ModelError, match=r"bad\.yaml: field 'output\.kind'"):
        load_card(model, tmp_path / "bad.yaml")


def test_yml_suffix_is_found(tmp_path: Path) -> None:
    (tmp_path / "net.yml").write_text("task: segmentation\n")
    assert isinstance(load_card(tmp_path / "net.onnx"), SegmentationCard)


def test_card_yaml_round_trip(tmp_path: Path) -> None:
    output = {"kind": "logits", "classes": ["ground", "house"], "mapping": {"ground": 0, 1: "building"}}
    inp = {"size": [320, 96], "mean": [0.4, 0.5, 0.6]}
    card = parse_card({"task": "segmentation", "name": "demo", "input": inp, "output": output})
    path = write_card(card, tmp_path / "demo.yaml")
    again = load_card(tmp_path / "demo.onnx", path)
    assert again == card
    assert "task: segmentation" in card_to_yaml(card)
