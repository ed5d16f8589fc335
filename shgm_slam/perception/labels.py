"""Label spaces of segmentation models and their mapping onto Cityscapes train ids.

A segmentation model speaks its own class list (Cityscapes, ADE20K, a custom set); the rest of
the system speaks Cityscapes train ids (``shgm_slam.labels``). ``class_lut`` turns a card's
``classes`` + ``mapping`` into a lookup table ``model class index -> train id`` (255 = ignore).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from shgm_slam.errors import ModelError
from shgm_slam.labels import CITYSCAPES_CLASSES, IGNORE_ID, NUM_CLASSES, Label
from shgm_slam.perception.card import LabelSpace, SegOutputSpec

ADE20K_CLASSES: tuple[str, ...] = (
    "wall", "building", "sky", "floor", "tree", "ceiling", "road", "bed", "windowpane", "grass",
    "cabinet", "sidewalk", "person", "earth", "door", "table", "mountain", "plant", "curtain", "chair",
    "car", "water", "painting", "sofa", "shelf", "house", "sea", "mirror", "rug", "field", "armchair",
    "seat", "fence", "desk", "rock", "wardrobe", "lamp", "bathtub", "railing", "cushion", "base", "box",
    "column", "signboard", "chest of drawers", "counter", "sand", "sink", "skyscraper", "fireplace",
    "refrigerator", "grandstand", "path", "stairs", "runway", "case", "pool table", "pillow",
    "screen door", "stairway", "river", "bridge", "bookcase", "blind", "coffee table", "toilet",
    "flower", "book", "hill", "bench", "countertop", "stove", "palm", "kitchen island", "computer",
    "swivel chair", "boat", "bar", "arcade machine", "hovel", "bus", "towel", "light", "truck", "tower",
    "chandelier", "awning", "streetlight", "booth", "television receiver", "airplane", "dirt track",
    "apparel", "pole", "land", "bannister", "escalator", "ottoman", "bottle", "buffet", "poster",
    "stage", "van", "ship", "fountain", "conveyer belt", "canopy", "washer", "plaything",
    "swimming pool", "stool", "barrel", "basket", "waterfall", "tent", "bag", "minibike", "cradle",
    "oven", "ball", "food", "step", "tank", "trade name", "microwave", "pot", "animal", "bicycle",
    "lake", "dishwasher", "screen", "blanket", "sculpture", "hood", "sconce", "vase", "traffic light",
    "tray", "ashcan", "fan", "pier", "crt screen", "plate", "monitor", "bulletin board", "shower",
    "radiator", "glass", "clock", "flag",
)  # fmt: skip
"""The 150 SceneParse150 (ADE20K) classes in model output order (index 0 = wall)."""

ADE20K_TO_TRAIN_ID: dict[str, int] = {
    "wall": Label.WALL, "building": Label.BUILDING, "house": Label.BUILDING, "skyscraper": Label.BUILDING,
    "tower": Label.BUILDING, "hovel": Label.BUILDING, "booth": Label.BUILDING, "awning": Label.BUILDING,
    "sky": Label.SKY, "road": Label.ROAD, "runway": Label.ROAD, "dirt track": Label.ROAD,
    "sidewalk": Label.SIDEWALK, "path": Label.SIDEWALK, "tree": Label.VEGETATION, "plant": Label.VEGETATION,
    "palm": Label.VEGETATION, "flower": Label.VEGETATION, "grass": Label.TERRAIN, "earth": Label.TERRAIN,
    "field": Label.TERRAIN, "land": Label.TERRAIN, "sand": Label.TERRAIN, "hill": Label.TERRAIN,
    "person": Label.PERSON, "car": Label.CAR, "van": Label.CAR, "truck": Label.TRUCK, "bus": Label.BUS,
    "minibike": Label.MOTORCYCLE, "bicycle": Label.BICYCLE, "fence": Label.FENCE, "railing": Label.FENCE,
    "pole": Label.POLE, "streetlight": Label.POLE, "column": Label.POLE, "signboard": Label.TRAFFIC_SIGN,
    "trade name": Label.TRAFFIC_SIGN, "traffic light": Label.TRAFFIC_LIGHT,
}  # fmt: skip
"""ADE20K class -> Cityscapes train id for the classes with an outdoor-driving counterpart; every
other ADE20K class (indoor objects, water, mountains, ...) maps to 255 (ignore)."""


def label_space_classes(space: LabelSpace) -> tuple[str, ...]:
    """Class names of a named label space, in model output order."""
    return {LabelSpace.CITYSCAPES: CITYSCAPES_CLASSES, LabelSpace.ADE20K: ADE20K_CLASSES}[space]


def output_class_names(spec: SegOutputSpec) -> tuple[str, ...]:
    """A segmentation card's class names in model output order (its own list, or its label space's)."""
    return label_space_classes(spec.classes) if isinstance(spec.classes, LabelSpace) else spec.classes


def _default_table(space: LabelSpace | None) -> dict[str, int]:
    """Name -> train id defaults of a label space (Cityscapes names always map to themselves)."""
    table = {name: i for i, name in enumerate(CITYSCAPES_CLASSES)}
    table.update({"ignore": IGNORE_ID, "unlabeled": IGNORE_ID, "void": IGNORE_ID, "background": IGNORE_ID})
    if space is LabelSpace.ADE20K:
        table.update({name: ADE20K_TO_TRAIN_ID.get(name, IGNORE_ID) for name in ADE20K_CLASSES})
    return table


def _train_id(value: int | str, where: str) -> int:
    """A mapping target (train id, 255, Cityscapes class name or 'ignore') as an int train id."""
    if isinstance(value, str):
        name = value.strip().lower()
        if name in ("ignore", "255"):
            return IGNORE_ID
        if name.isdigit():
            value = int(name)
        elif name in CITYSCAPES_CLASSES:
            return CITYSCAPES_CLASSES.index(name)
        else:
            raise ModelError(
                f"{where}: target {value!r} is not a Cityscapes class; use a train id 0..18, 255, "
                f"or one of {', '.join(CITYSCAPES_CLASSES)}"
            )
    if not (0 <= int(value) < NUM_CLASSES or int(value) == IGNORE_ID):
        raise ModelError(f"{where}: target {value} is not a Cityscapes train id (0..18) or 255 (ignore)")
    return int(value)


def class_lut(
    classes: Sequence[str],
    mapping: Mapping[int | str, int | str] | None = None,
    space: LabelSpace | None = None,
    where: str = "model card output.mapping",
) -> np.ndarray:
    """Lookup table from model class index to Cityscapes train id.

    Resolution per model class: an explicit ``mapping`` entry (keyed by class index or name), else
    the label space's default table, else the class name when it is a Cityscapes class name.

    Args:
        classes: the model's class names in output order (length C).
        mapping: model class (index or name) -> train id, Cityscapes class name, 255 or 'ignore'.
        space: the named label space ``classes`` came from (its default table is used).
        where: text naming the card and field in error messages.

    Returns:
        (C,) uint8 train ids (255 = ignore).

    Raises:
        ModelError: a mapping key names no model class, a target is invalid, or classes stay unmapped.
    """
    names = [str(c).strip().lower() for c in classes]
    lut = np.full(len(names), -1, dtype=np.int64)
    for key, target in (mapping or {}).items():
        if isinstance(key, str) and key.strip().isdigit():
            key = int(key)
        if isinstance(key, int):
            if not 0 <= key < len(names):
                raise ModelError(f"{where}: class index {key} is outside the model's {len(names)} classes")
            idx = key
        else:
            if key.strip().lower() not in names:
                raise ModelError(f"{where}: {key!r} is not one of the model's classes ({', '.join(classes)})")
            idx = names.index(key.strip().lower())
        lut[idx] = _train_id(target, f"{where}[{key!r}]")
    defaults = _default_table(space)
    for i, name in enumerate(names):
        if lut[i] < 0 and name in defaults:
            lut[i] = defaults[name]
    missing = [f"{i}:{classes[i]}" for i in np.flatnonzero(lut < 0)]
    if missing:
        shown = ", ".join(missing[:10]) + (" ..." if len(missing) > 10 else "")
        raise ModelError(
            f"{where} misses {len(missing)} model class(es) ({shown}): add entries "
            "`class_name_or_index: cityscapes_train_id_or_255` for them"
        )
    return lut.astype(np.uint8)
