"""Cityscapes train-id label space, the one label space every stage speaks.

Segmentation models map into it (``perception/``), the simulator renders it (``sim/``), the graph
keeps a configurable subset of it (``graph/``) and the viewer colours it (``viz/``).
"""

from __future__ import annotations

import numpy as np

IGNORE_ID = 255
"""Label id of pixels that carry no class (unlabelled, invalid)."""

CITYSCAPES_CLASSES: tuple[str, ...] = (
    "road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
    "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
    "motorcycle", "bicycle",
)  # fmt: skip
"""Class names indexed by Cityscapes train id (0..18)."""

NUM_CLASSES = len(CITYSCAPES_CLASSES)

CITYSCAPES_COLORS_RGB = np.array(
    [
        (128, 64, 128), (244, 35, 232), (70, 70, 70), (102, 102, 156), (190, 153, 153),
        (153, 153, 153), (250, 170, 30), (220, 220, 0), (107, 142, 35), (152, 251, 152),
        (70, 130, 180), (220, 20, 60), (255, 0, 0), (0, 0, 142), (0, 0, 70), (0, 60, 100),
        (0, 80, 100), (0, 0, 230), (119, 11, 32),
    ],
    dtype=np.uint8,
)  # fmt: skip
"""Official Cityscapes palette, (19, 3) uint8 RGB, indexed by train id."""


class Label:
    """Named Cityscapes train ids (plain ints, usable as array indices)."""

    ROAD = 0
    SIDEWALK = 1
    BUILDING = 2
    WALL = 3
    FENCE = 4
    POLE = 5
    TRAFFIC_LIGHT = 6
    TRAFFIC_SIGN = 7
    VEGETATION = 8
    TERRAIN = 9
    SKY = 10
    PERSON = 11
    RIDER = 12
    CAR = 13
    TRUCK = 14
    BUS = 15
    TRAIN = 16
    MOTORCYCLE = 17
    BICYCLE = 18


DEFAULT_GRAPH_LABELS: tuple[int, ...] = tuple(
    i for i in range(NUM_CLASSES) if i not in (Label.SKY, Label.PERSON, Label.RIDER)
)
"""Train ids that become graph nodes by default: everything except sky, person and rider."""

FLAT_GROUND_LABELS: tuple[int, ...] = (Label.ROAD, Label.SIDEWALK, Label.TERRAIN)
"""Classes of flat ground: the height of their visible centroid is the ground's from any viewpoint
(matched pairs seen by a car and by a UAV 50 m up differ by 0.04 m RMS in height on the airsim-like
tuning worlds, where compact objects differ by 0.3 m (cars) to 2.1 m (trees): a car sees a tree's side,
a UAV its crown), while their horizontal centroid depends on which part of a large patch was seen: a
car sees the strip of sidewalk beside it, a UAV the whole block's. Closure refits take their height
(``server/closures.py``); between robots that look from very different heights the match verification
takes no evidence from them (``MatchingConfig.viewpoint_dependent_labels``, ``server/viewpoints.py``)."""

VIEWPOINT_DEPENDENT_LABELS: tuple[int, ...] = (
    *FLAT_GROUND_LABELS, Label.BUILDING, Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN,
)  # fmt: skip
"""Classes whose node a car and a UAV 30-90 m up do not map alike, so that between robots that look from
very different heights they give no evidence for or against an alignment (``MatchingConfig.viewpoint_dependent_labels``,
``server/viewpoints.py``): flat ground (its horizontal centroid depends on the part of the patch seen, above);
buildings (a car sees a facade, its centroid on the street side; a UAV the roof, its centroid mid-block, half
the building's depth away); poles, traffic lights and signs (thin and upright: a few pixels seen from above,
so a UAV maps almost none of them). Measured on the airsim-like tuning worlds 10-19 (final graphs, true
alignment, a 3 m partner radius; odometry drift lowers every share alike): of the car's overlap nodes with a
UAV partner, cars 48 %, trees 32 %, walls 32 %, trucks 35 %, buses 30 %, against sidewalk 27 %, road 25 %,
terrain 29 % (and the UAV's terrain 9 %), buildings 11 %, poles 4 % (534 nodes; the UAV mapped 49 in the same
area), traffic lights and signs 0 %. Counted, they contradicted the true car-UAV alignments: one UAV of ten
was never placed (seed 17: 150-160 partners out of ~200 / ~175 overlap nodes, yet -5 to -10 nats), and of
the hypotheses within 2 m of the truth 26 % passed the threshold, against 77 % without them, while the best
hypothesis more than 20 m off stayed 4.2 nats below it either way (``docs/benchmarks.md``)."""

THIN_OBJECT_DEPTH_PERCENTILES: dict[int, float] = {
    Label.POLE: 25.0, Label.TRAFFIC_LIGHT: 25.0, Label.TRAFFIC_SIGN: 25.0,
}  # fmt: skip
"""Objects a few pixels wide whose predicted depth blends with the background behind them: with a depth
model's depth their node takes this percentile of its pixels' depths (``ExtractionConfig``); chosen on
tuning worlds (airsim-like 10-14: the 25th percentile raised the likelihood ratio of the true alignment
between the cars' RGB graphs in 4 of 5 worlds; the 10th, or the median for cars, trees and walls too, did not
do better)."""


MAP_CLASS_NAMES: dict[str, int] = {
    "tree": Label.VEGETATION, "trees": Label.VEGETATION, "bush": Label.VEGETATION, "hedge": Label.VEGETATION,
    "street light": Label.POLE, "streetlight": Label.POLE, "street lamp": Label.POLE, "lamp": Label.POLE,
    "lamp post": Label.POLE, "lamppost": Label.POLE, "light pole": Label.POLE, "utility pole": Label.POLE,
    "sign": Label.TRAFFIC_SIGN, "road sign": Label.TRAFFIC_SIGN, "street sign": Label.TRAFFIC_SIGN,
    "signboard": Label.TRAFFIC_SIGN, "traffic signal": Label.TRAFFIC_LIGHT, "traffic signals": Label.TRAFFIC_LIGHT,
    "house": Label.BUILDING, "buildings": Label.BUILDING, "vehicle": Label.CAR, "parked car": Label.CAR,
    "van": Label.CAR, "grass": Label.TERRAIN, "pedestrian": Label.PERSON, "bike": Label.BICYCLE,
    "motorbike": Label.MOTORCYCLE,
}  # fmt: skip
"""Names map layers and object detectors use for Cityscapes classes (lower case, single spaces): a graph file
may name its classes so (``io/graph_json.py``). Only names with one obvious class; anything else must be
renamed by whoever made the file."""


def label_name(label_id: int) -> str:
    """Human-readable class name of a train id (``"ignore"`` for 255, ``"class<id>"`` otherwise)."""
    if 0 <= label_id < NUM_CLASSES:
        return CITYSCAPES_CLASSES[label_id]
    return "ignore" if label_id == IGNORE_ID else f"class{label_id}"


def colorize_labels(label_ids: np.ndarray) -> np.ndarray:
    """Map an (H, W) uint8 train-id image to an (H, W, 3) uint8 RGB image (ignore -> black)."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[:NUM_CLASSES] = CITYSCAPES_COLORS_RGB
    return lut[np.asarray(label_ids, dtype=np.uint8)]
