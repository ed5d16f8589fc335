"""Configuration: one small pydantic model per stage, composed into ``ShgmConfig``.

Classes elsewhere take plain values; factories take these models. The effective config is written
into every results folder (``config.yaml``) and ``shgm-slam dump-config`` prints the defaults.
Defaults follow the paper and the authors' release (ARCHITECTURE.md, "The algorithm").
"""

from __future__ import annotations

import difflib
import hashlib
import json
import math
import re
from enum import Enum
from pathlib import Path
from typing import Any, ClassVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from shgm_slam.errors import ConfigError, parse_failure
from shgm_slam.labels import (
    DEFAULT_GRAPH_LABELS,
    NUM_CLASSES,
    THIN_OBJECT_DEPTH_PERCENTILES,
    VIEWPOINT_DEPENDENT_LABELS,
)


class _Stage(BaseModel):
    """A stage of the config: unknown keys, NaN / infinite numbers and ``true``/``false`` given for a number
    are refused (``distance_m: .inf`` kept one keyframe per robot; ``distance_m: true`` read as 1 m)."""

    model_config = ConfigDict(extra="forbid", use_enum_values=False, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if isinstance(value, bool) and field is not None and not _admits_bool(field.annotation):
                    raise ValueError(f"{name}: {str(value).lower()} is not a number; give a number")
        return data


def _admits_bool(annotation: Any) -> bool:
    """Whether a field annotation (a type, ``X | None``, a generic) takes a bool as itself."""
    if annotation is bool or annotation is Any:
        return True
    return any(_admits_bool(arg) for arg in getattr(annotation, "__args__", ()))


class ExtractionConfig(_Stage):
    """Object extraction from depth + labels (Sec. III-A; authors' release defaults).

    Fields that default to None are derived per robot from its first frames (``scene_scale``: the camera's
    height above the ground plane and the depth of the nearest ground in view); ``FLEET`` holds the values
    of a car camera ~1.6 m above the road (the authors' release), used as the rules' reference and as the
    fallback when a robot's scene cannot be measured. A value set in a config always wins.
    """

    FLEET: ClassVar[dict[str, float]] = {"max_depth_m": 30.0, "min_blob_fraction": 5000.0 / (1024 * 576)}

    max_depth_m: float | None = Field(
        None, gt=0, description="ignore pixels farther than this; None: max(30, 2 x the depth of the nearest "
        "ground in view), so a camera high above the ground keeps a footprint as deep as its nearest ground"
    )
    min_depth_m: float = Field(0.5, ge=0)
    depth_step_m: float = Field(1.0, gt=0, description="4-neighbours closer than this in depth join a region")
    min_blob_fraction: float | None = Field(
        None, gt=0, lt=1, description="minimum region size as a fraction of image area; None: "
        "5000/(1024*576) x (30 / max_depth_m)^1.5 (farther objects appear smaller)"
    )
    labels: tuple[int, ...] = Field(DEFAULT_GRAPH_LABELS, description="train ids that become nodes")
    predicted_depth_percentiles: dict[int, float] = Field(
        default_factory=lambda: dict(THIN_OBJECT_DEPTH_PERCENTILES),
        description="with predicted depth only (a depth model's, in the run or perceived): objects of these train "
        "ids take this percentile of their pixels' depths instead of the mean. A network blends a thin object's "
        "depth with the background behind it (the demo models put poles 1.4-3.8 m too far at 320x96); the near "
        "part of the blend is the object. Measured depth keeps the mean",
    )

    @model_validator(mode="after")
    def _consistent(self) -> ExtractionConfig:
        if not self.labels:
            raise ValueError("labels is empty: no object could become a graph node (e.g. [2, 5, 6, 7, 8, 13])")
        if any(not 0 <= k < NUM_CLASSES for k in self.labels):
            raise ValueError(f"labels must be Cityscapes train ids 0-18 (255 is 'ignore'), got {list(self.labels)}")
        percentiles = self.predicted_depth_percentiles
        bad = {k: q for k, q in percentiles.items() if not (0 <= k < NUM_CLASSES and 0 <= q <= 100)}
        if bad:
            raise ValueError(f"predicted_depth_percentiles maps train ids 0-18 to percentiles 0-100: {bad}")
        if self.max_depth_m is not None and self.min_depth_m >= self.max_depth_m:
            raise ValueError(f"min_depth_m {self.min_depth_m} must be below max_depth_m {self.max_depth_m}")
        return self

    def depth_percentiles(self, depth_predicted: bool) -> dict[int, float] | None:
        """What ``extract_objects`` takes as ``depth_percentiles``: this stage's ``predicted_depth_percentiles``
        when a depth model predicted the depth, None (the mean) when it was measured."""
        return self.predicted_depth_percentiles if depth_predicted else None

    def filled(self) -> ExtractionConfig:
        """This stage with every data-derived field still None set to its ``FLEET`` value."""
        return self.model_copy(update={k: v for k, v in self.FLEET.items() if getattr(self, k) is None})


class GraphConfig(_Stage):
    """Incremental semantic graph: node merging and edges."""

    merge_radius_m: float = Field(5.0, ge=0, description="same-label nodes closer than this merge")
    connectivity_m: float = Field(10.0, gt=0, description="edge between nodes closer than this (paper best: 10)")


class DescriptorKind(str, Enum):
    HISTOGRAM = "histogram"
    NEIGHBOR_VECTOR = "neighbor-vector"
    RANDOM_WALK = "random-walk"


class DescriptorConfig(_Stage):
    """Node descriptors (Alg. 1 and the baselines)."""

    kind: DescriptorKind = DescriptorKind.HISTOGRAM
    path_length: int = Field(3, ge=2, le=4, description="labels per histogram path (Alg. 1 uses 3)")
    count_backtracking: bool = Field(True, description="count i->m->i paths, as the authors' release does")
    num_walks: int = Field(400, ge=1, le=100_000, description="random-walk baseline: walks per node (X-view)")
    walk_length: int = Field(3, ge=1, le=64, description="random-walk baseline: steps per walk")
    seed: int = Field(0, ge=0, description="random generator seed")


class CandidateMode(str, Enum):
    ALL = "all"  # every pair above the score threshold (Alg. 2, first loop)
    BEST = "best"  # best per node of B (authors' release)
    MUTUAL = "mutual"  # mutual best
    TOP_K = "top-k"  # k best per node of B


class OutlierMode(str, Enum):
    RANSAC = "ransac"  # the paper's ICP-RANSAC (Alg. 2)
    CLIQUE = "clique"  # pairwise consistency + maximum clique (beyond the paper)


class MatchingConfig(_Stage):
    """Candidate matching (Eq. 1), outlier rejection (Alg. 2 / max clique) and the weighted pose (Eq. 2)."""

    score_threshold: float = Field(0.5, ge=0, le=1)
    same_label_only: bool = True
    candidate_mode: CandidateMode = CandidateMode.TOP_K
    top_k: int = Field(2, ge=1, le=1000, description="candidates per node of B (tuned: bench localization)")
    outlier_mode: OutlierMode = OutlierMode.CLIQUE
    ransac_iterations: int = Field(1000, ge=1, le=1_000_000)
    inlier_threshold_m: float = Field(10.0, gt=0, description="RANSAC inlier distance (authors: 10 m)")
    consistency_threshold_m: float = Field(
        3.0, gt=0, description="clique mode: |d_a - d_b| tolerance (tuned: bench localization)"
    )
    gravity_aligned: bool = Field(False, description="4-DoF (yaw + translation) fit for ground robots")
    min_inliers: int = Field(
        6, ge=3, description="absolute floor on supporting node pairs (degenerate geometry); the decision itself "
        "is the likelihood ratio against chance (false_alarm_rate)",
    )
    max_rmse_m: float = Field(3.0, gt=0, description="success needs a fit residual below this")
    weighted_pose: bool = Field(True, description="Eq. 2 weights from object size")
    refine_iterations: int = Field(3, ge=0)
    polish: bool = Field(
        True, description="refit an accepted alignment robustly (Tukey's biweight, no size weights) on its partners "
        "within twice the verification radius; the decision is not changed (matching/polish.py)",
    )
    seed: int = Field(0, ge=0, description="random generator seed")
    max_candidates: int = Field(
        600, ge=3, description="clique mode: search the clique among this many best-scoring candidates"
    )
    min_spread_m: float = Field(
        5.0, ge=0, description="success needs inliers spanning this much (2nd principal axis; 4-DoF: 1st)"
    )
    fill_candidates: bool = Field(
        True, description="fill the max_candidates budget with further same-label pairs, round-robin over B's "
        "nodes by score (sparse maps, whose descriptors barely agree)",
    )
    vote_hypotheses: int = Field(
        4, ge=0, description="gravity-aligned: also this many alignments most voted for by agreeing same-label node "
        "pairs (matching/pair_voting.py; no descriptors), added to the cliques' before screening (0: none)",
    )
    verified_hypotheses: int = Field(
        4, ge=1, description="hypotheses (most supporting nodes first) refined and scored by the likelihood ratio, "
        "plus the best one that places B elsewhere than all of them"
    )
    verification_radius_m: float = Field(
        3.0, gt=0, description="whole-overlap check: a same-label node this close under the hypothesis is a partner"
    )
    coverage_radius_m: float = Field(
        10.0, gt=0, description="whole-overlap check: a node this close to any node of the other graph lies in the "
        "area the other robot observed (it should find a partner)",
    )
    density_radius_m: float = Field(
        15.0, gt=0, description="chance model: radius of the local same-label density around each node"
    )
    partner_probability: float = Field(
        0.4, gt=0, lt=1, description="chance model: probability that an object inside the other robot's area was "
        "mapped by both robots (maps miss 30-60 % of objects)",
    )
    confusion_evidence: bool = Field(
        True, description="whole-overlap check: a node without a same-label partner but with another label's node "
        "within the verification radius (a confused label: a pole mapped as a sign) supports the alignment as far as "
        "such traces are beyond chance (matching/confusion.confusion_llrs); never counts against it",
    )
    viewpoint_dependent_labels: tuple[int, ...] = Field(
        VIEWPOINT_DEPENDENT_LABELS, description="whole-overlap check between robots whose cameras look from very "
        "different heights (view_height_ratio): train ids that then neither support nor contradict an alignment (they "
        "still pair up, and closures take the height of flat ground). Flat ground and buildings: their horizontal "
        "centroid depends on the part seen (a car's strip of sidewalk or facade, a UAV's whole block or roof); poles, "
        "traffic lights and signs: a few pixels from above, a UAV maps almost none (labels.VIEWPOINT_DEPENDENT_LABELS)",
    )
    view_height_ratio: float = Field(
        4.0, gt=1, description="two robots look from very different heights when one camera is more than this many "
        "times as high above its flat-ground nodes as the other's (cars 1.5-2 m, UAVs 30-60 m; "
        "server/viewpoints.py)",
    )
    false_alarm_rate: float = Field(
        3e-3, gt=0, lt=1, description="success needs a likelihood ratio (alignment vs chance) above "
        "hypotheses / false_alarm_rate (tuned: bench sparse, seeds 10-19), and a rival alignment beyond it too "
        "must trail the best by log(1 / false_alarm_rate)",
    )
    up_axis: tuple[float, float, float] = Field(
        (0.0, -1.0, 0.0), description="vertical axis of the world frames (KITTI camera frame: -y is up)"
    )

    @field_validator("up_axis")
    @classmethod
    def _nonzero_up(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(math.isfinite(v) for v in value) or not math.hypot(*value) > 0:
            raise ValueError(f"up_axis must be a finite non-zero vector (KITTI camera frame: [0, -1, 0]), got {value}")
        return value

    @field_validator("viewpoint_dependent_labels")
    @classmethod
    def _train_ids(cls, value: tuple[int, ...]) -> tuple[int, ...]:
        if any(not 0 <= k < 255 for k in value):
            raise ValueError(f"viewpoint_dependent_labels must be Cityscapes train ids 0-18 ([] for none), got {value}")
        return value


class Dof(str, Enum):
    """Rotation freedom of a graph match (``shgm-slam match --dof``; ``matching/gravity.py``)."""

    AUTO = "auto"  # 4-DoF about the vertical both graphs lie flat along, else as ``matching.gravity_aligned`` says
    FOUR = "4"  # gravity-aligned: yaw + translation about the shared vertical (or ``matching.up_axis``)
    SIX = "6"  # any rotation


class OdometryKind(str, Enum):
    """Where each frame's pose comes from. AUTO: GIVEN when the frames come with the robot's own odometry, else
    VISUAL when a depth model predicts the depth (ICP alone on predicted depth stalls, the hybrid was not clearly
    better; ``odometry.sources.choose_odometry``), KISS_ICP when the depth comes from files (a sensor or the
    simulator)."""

    AUTO = "auto"
    KISS_ICP = "kiss-icp"
    GT = "gt"
    FILE = "file"
    VISUAL = "visual"  # depth-assisted monocular visual odometry (KLT + PnP), for predicted depth
    HYBRID = "hybrid"  # KISS-ICP on trusted pseudo-LiDAR, seeded and held along the track by VISUAL
    GIVEN = "given"  # the robot's own odometry, given with each frame (``ArraySequence``/``add_frame`` T_odom_cam)


class OdometryConfig(_Stage):
    """Front-end odometry (KISS-ICP tuned for dense pseudo-LiDAR, REFERENCE.md §1.2).

    Fields that default to None are derived per robot from its first frames (``scene_scale``, as in
    ``ExtractionConfig``); ``FLEET`` holds a car camera's values, the rules' reference and the fallback.
    """

    FLEET: ClassVar[dict[str, float | bool]] = {
        "voxel_size_m": 1.0, "max_range_m": 100.0, "shuffle_points": False, "visual_max_depth_m": 40.0,
        "cloud_stride": 2, "depth_noise_rel": 0.0, "visual_ground_attitude": False, "image_step_blend": False,
    }

    kind: OdometryKind = OdometryKind.AUTO
    poses_file: Path | None = None
    voxel_size_m: float | None = Field(
        None, ge=0.01, description="KISS-ICP voxel (at least 1 cm); None: max(1, median depth of the first "
        "frames / 40, 3 x their measured relative depth noise x that median depth) (far, dense clouds register "
        "on a coarser map; noisy depth too)"
    )
    max_points_per_voxel: int = Field(10, ge=1, le=1000)
    min_range_m: float = Field(0.5, ge=0)
    max_range_m: float | None = Field(
        None, gt=0, description="outdoor scenes need far points to constrain forward motion; None: 100, or "
        "1.1 x the range of the farthest ground in view when the horizon is out of view and that is farther "
        "(at most 1.5 x the farthest range the first frames' depth holds: a very wide lens)"
    )
    cloud_stride: int | None = Field(
        None, ge=1, description="back-project every n-th pixel; None: derived from the image size (about "
        "30k pixels per frame: 640x192 -> 2, 320x96 -> 1, 1242x375 -> 4)"
    )
    max_spacing_m: float | None = Field(
        None,
        gt=0,
        description="drop points whose image-grid neighbours are farther apart (sparse far/grazing samples "
        "move with the camera and stall ICP at zero motion); None: SPACING_PER_VOXEL (0.6) x voxel_size_m, "
        "samples sparser than the map's voxels (a large value keeps every point)",
    )
    depth_noise_rel: float | None = Field(
        None, ge=0, le=1, description="random depth error relative to the depth (0.05 = 5 %): the spacing filter "
        "lets a point's neighbours lie 3 x this x its depth farther apart; None: measured on the first frames "
        "(scene_scale: 0 on noise-free depth)"
    )
    shuffle_points: bool | None = Field(
        None, description="seeded random point order before KISS-ICP's voxel subsampling (helps aerial "
        "start-up); None: on when the horizon is out of view (the camera sees only the ground)"
    )
    max_icp_iterations: int = Field(100, ge=1, le=10_000)
    icp_convergence: float = Field(
        3e-3, gt=0, le=1.0, description="KISS-ICP stops iterating once a step's 6-vector (metres, radians) is "
        "shorter than this; KISS-ICP's own 1e-4 took 1.8x the time on a UAV's clouds for poses a few mm away (README)"
    )
    icp_threads: int = Field(
        1, ge=0, le=1024, description="KISS-ICP's threads; 1: the same trajectory on every run (its parallel sums "
        "add in an order that depends on thread scheduling, and the image-motion check's choices turn those "
        "1e-14 m differences into different steps); 0: every core"
    )
    visual_max_features: int = Field(1000, ge=8, le=100_000, description="visual odometry: corners per reference frame")
    visual_max_depth_m: float | None = Field(
        None, gt=0, description="visual odometry: corners only where depth is below this (far monocular depth "
        "is poor); None: 40 x extraction.max_depth_m / 30 (as far as the robot takes objects)"
    )
    visual_min_track_fraction: float = Field(
        0.5, gt=0, le=1, description="visual odometry: new reference frame when fewer of its corners are tracked"
    )
    visual_reprojection_px: float = Field(2.0, gt=0, description="visual odometry: PnP RANSAC inlier threshold")
    visual_depth_window_px: int = Field(
        5, ge=1, description="visual odometry: a corner's depth is the largest in this window (networks blur "
        "depth edges toward the foreground), in pixels of the depth model's input: on images larger than that "
        "input it grows with them (odometry/visual.py depth_window_on_image); 1 for sensor depth"
    )
    visual_planar_motion: bool = Field(
        True, description="visual odometry: each frame's turn from the tracks under a ground vehicle's planar "
        "circular motion wherever they agree with it (odometry/planar_motion.py; a UAV's frames fall back to PnP)"
    )
    visual_road_steps: bool = Field(
        True, description="visual odometry: each frame's step from the road's image motion where a level road "
        "plane is in view (odometry/ground_speed.py: the plane-induced homography; tracks sliding along edges "
        "that run with the street shortened steps by 30-70 %); a UAV's frames keep the tracks' steps"
    )
    visual_road_height_m: float | None = Field(
        None, gt=0, le=10.0, description="visual odometry: the camera's height above the road, metres, that road "
        "steps take their length in; None: the road plane's height measured in each frame's depth. A robot whose "
        "predicted depth is scaled to perception.camera_height_m gets that height (the network's scale swings "
        "from frame to frame, the camera's mounting does not)"
    )
    visual_ground_attitude: bool | None = Field(
        None, description="visual odometry: hold each new reference frame's roll and pitch to the ground plane in "
        "view (level ground; odometry/visual.py, step 5: a UAV's tilt drifted 10-34 deg over 600 m without it); "
        "None: on when the horizon is out of view (the camera sees only the ground)"
    )
    hybrid_edge_rel_jump: float = Field(
        0.1, gt=0, description="hybrid: pixels where inverse depth bends by more than this share of itself "
        "(occlusion edges, which networks blur) and their neighbours are kept out of ICP's cloud"
    )
    image_rotation: bool = Field(
        True, description="measure each step's turn from image motion: it seeds KISS-ICP's rotation (sharp turns) "
        "and the health check compares every odometry's turn with it"
    )
    image_flow_check: bool = Field(
        True, description="KISS-ICP: check each step against the image motion (the previous frame's depth pixels "
        "tracked into this image); where ICP slipped (a plane-like cloud, e.g. a UAV over flat ground), keep the step "
        "solved from the tracks (odometry/flow_check.py)"
    )
    image_step_blend: bool | None = Field(
        None, description="KISS-ICP: blend each kept step with the one solved from the image tracks (PnP), by how "
        "noisy each one's turns have recently been (three-cornered hat with the images' own turn; "
        "odometry/step_fusion.py); needs image_flow_check and image_rotation. None: on where the depth's measured "
        "noise (depth_noise_rel) is not 0 and the horizon is in view: ICP's steps suffer from noisy depth, the "
        "tracks' bearings do not; a camera that sees only the ground keeps ICP's (PnP on one distant plane trades "
        "pitch for sideways motion)"
    )
    image_window_check: bool = Field(
        True, description="KISS-ICP: check its motion over every second against pixels tracked through it, where "
        "one frame's image motion is too small to show a slide (far ground, a high UAV); where ICP slid, keep the "
        "second's motion solved from the tracks and restart KISS-ICP's map from it (odometry/window_check.py)"
    )
    health_check: bool = Field(
        True, description="detect odometry divergence and restart as a new trajectory segment (odometry/health.py)"
    )
    max_speed_mps: float = Field(40.0, gt=0, description="health: faster steps are divergence (cars <= 144 km/h)")
    max_accel_mps2: float = Field(
        30.0, gt=0, description="health: acceleration limit incl. centripetal (sim cars reach 2 g in sharp turns)"
    )
    max_speed_change_mps2: float = Field(
        12.0, gt=0, description="health: how fast the speed itself can change (cars brake at about 1 g); an "
        "odometry whose speed jumps by more (plus its own measured noise) and stays until 3 m are lost or gained "
        "diverged"
    )
    max_turn_rate_dps: float = Field(180.0, gt=0, description="health: turn-rate limit (sim cars: up to 107 deg/s)")
    step_noise_m: float = Field(
        2.0, ge=0, description="health: per-step position noise of healthy odometry (acceleration slack; KISS-ICP "
        "on a UAV's far, sparse clouds jumps by up to 1.6 m per step without diverging)"
    )
    step_noise_deg: float = Field(2.0, ge=0, description="health: per-step rotation noise (turn-rate slack)")
    max_coast_s: float = Field(
        0.5, gt=0, description="health: longest stretch of predicted poses (no depth, ICP/PnP failed)"
    )
    max_frame_gap_s: float = Field(
        1.0, gt=0, description="health: frames farther apart than this (and than 5 times the usual interval) start "
        "a new trajectory segment: the motion between them was not observed (a paused camera, dropped frames)"
    )
    max_threshold_m: float = Field(15.0, gt=0, description="health: KISS-ICP adaptive threshold limit")
    max_image_rotation_deg: float = Field(
        5.0, gt=0, description="health: largest disagreement of a step's yaw with image motion (KISS-ICP)"
    )
    max_map_misfit: float = Field(
        0.5, gt=0, le=1, description="health: largest misfit of a frame's cloud against KISS-ICP's local map under "
        "the step kept, where a search measured it (mean of min(d, gate)^2 / gate^2 over the points the previous "
        "camera saw: 0 all on the map, 1 none within ICP's gate; healthy searched frames of the 3.3 frames/s "
        "tuning drives reach 0.26, a turn ICP missed 0.72-0.76); noise-free depth only (on 2 % noisy depth healthy "
        "UAV frames reach 0.71)"
    )

    @model_validator(mode="after")
    def _file_needs_path(self) -> OdometryConfig:
        if self.kind is OdometryKind.FILE and self.poses_file is None:
            raise ValueError("odometry kind 'file' needs poses_file")
        return self

    def filled(self) -> OdometryConfig:
        """This stage with every data-derived field still None set to its ``FLEET`` value (``max_spacing_m``:
        ``with_spacing``)."""
        return self.model_copy(update={k: v for k, v in self.FLEET.items() if getattr(self, k) is None}).with_spacing()

    def with_spacing(self) -> OdometryConfig:
        """This stage with ``max_spacing_m``, when None, at ``SPACING_PER_VOXEL`` times its voxel (None while the
        voxel is)."""
        if self.max_spacing_m is not None or self.voxel_size_m is None:
            return self
        return self.model_copy(update={"max_spacing_m": float(f"{SPACING_PER_VOXEL * self.voxel_size_m:.3g}")})


SPACING_PER_VOXEL = 0.6
"""The spacing filter's default (``OdometryConfig.max_spacing_m``) in KISS-ICP voxels: a point is kept when its
image-grid neighbours lie within this share of a voxel, so that the voxel map holds several samples of the
surface it came from. It was 0.6 m for every robot (chosen at the fleet's 1 m voxel: the start-up stall of
samples that move with the camera); a UAV at 85-95 m, whose nearest ground lies 77 m away (2.15 m voxels),
then kept 12-29 % of its points, the strip of the image nearest to it, and KISS-ICP slid along the ground by
3-6 m in most seconds (tuning seed 17, 600 frames: 3.6 m ATE, SE(3)-aligned; with 1.3 m spacing 0.07 m). Cars
(1 m voxels) keep 0.6 m; UAVs at 44-54 m (1.0-1.6 m voxels) change by noise, both ways (README)."""


class KeyframeConfig(_Stage):
    """Keyframe selection: a new keyframe every X metres or Y degrees."""

    distance_m: float = Field(2.0, gt=0)
    angle_deg: float = Field(15.0, gt=0)


class RobustKernel(str, Enum):
    """M-estimator on inter-robot closure factors (gtsam.noiseModel.mEstimator)."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"


MEASURED_DEPTH_DRIFT = (0.001, 0.01)
"""Odometry sigma growth (rad per metre, fraction of the distance) for KISS-ICP on measured depth (files:
a sensor or the simulator). A step sigma of 0.01 rad / 0.1 m whatever its length let closures bend
well-measured trajectories (held-out tuning seeds 10-14). The rotation rate is the prior of a robot whose
loop closures have not measured more (``backend/drift.py``): KISS-ICP on the tuning robots' rendered depth
turns 0.6 deg per 100 m (median of 100 robots; p90 1.1, worst 3-4 on KITTI 00's drives), and 0.001 rad/m
over 2 m keyframes with the 0.001 rad floor is 1.0 deg per 100 m at one sigma. Chosen on the files tuning
seeds 10-29 and 00+07 against 0.002 (docs/benchmarks.md); a robot that drifts more in heading (a systematic 0.05 deg/m)
has its rate raised by its own loop closures."""

PREDICTED_DEPTH_DRIFT = (0.002, 0.05)
"""The same for odometry on depth a network predicts: the depth-quality study measured 4-6 % drift of
the visual and hybrid odometry with the demo models (``bench depth-quality``; before road steps). The
rotation rate models the visual odometry with road steps: over 100 m of 2.4 m keyframe steps it gives a
1-sigma turn of 1.8 deg, between the median (1.4 deg) and the 90th percentile (2.5 deg) of the cars' odometry
over 100 m on the RGB tuning worlds 10-14 (0.005 before, 4.4 deg, let closures between a car's forward and
backward cameras bend both by 15 deg where no closure held the heading). Replayed side by side on the RGB
tuning seeds (recent-window matching on): fused ATE mean 3.85 -> 3.36 m (10-14), 4.20 -> 4.09 m (15-19),
0.003 between them."""

MATCHES_TO_ANCHOR = 2
"""Independent graph matches that must agree before a robot enters the shared frame, whatever the depth
source. One whole-graph match can pass the chance test on an alias that fits its whole overlap, and
nothing in that match alone reveals it. Graphs from predicted depth alias most: on the RGB tuning
worlds (seeds 10-16) two matches removed a 193 m false merge (airsim-like seed 16) and a 6.7 m wrong
placement and lost one right placement. From measured depth (files) one match used to be enough, but
on the files tuning worlds 10-29 five of 81 placements went through an alias (withdrawn later, each a
false merge while it lasted, and kept by a run stopped then); with two: none of 72, and 72 of 80
overlapping robots placed right instead of 74, 0 wrong instead of 1 (``bench heldout --replay-from``).
Independent means on mutually disjoint objects (``consistency.independent_sources``) and, for one robot's
queries, on other straight stretches of the two trajectories (``STRETCH_TURN_DEG``): matches at
consecutive steps that find the same aliased objects again count once; on the RGB tuning worlds
(seeds 10-14) that removed a 30.9 m and a 7.1 m wrong placement and lost one right one (kitti-paths
seed 12, where every match re-found the same short overlap)."""

STRETCH_TURN_DEG = 30.0
"""Heading change that ends a straight stretch of a robot's trajectory (``backend/stretches.py``): two
matches on the same straight stretches of both robots count as one piece of evidence, as matches on
shared objects do, because an aliased street keeps aliasing along its length with new objects. Set
a priori (a corner turns 90 deg; the direction of travel is measured over 10 m of path), not tuned; replayed
on the files tuning journals (airsim-like 10-19 at both UAV altitudes, synthia-like and kitti-paths 10-11,
disjoint 10-13) it changed no placement, and with solid objects at their centres (a tried change) it kept
car2 of airsim-like 14 out of a 413 m alias that two of car1's matches along one straight street confirmed."""


class BackendConfig(_Stage):
    """Map server: periodic cross-robot matching and the iSAM2 pose graph."""

    match_every_keyframes: int = Field(10, ge=1)
    local_closure_m: float = Field(40.0, gt=0, description="one graph match gives one closure per this much overlap")
    submap_keyframes: int = Field(30, ge=1, description="recent keyframes forming a robot's submap")
    loop_closure: bool = Field(
        True, description="also match each robot's submap against its own older graph (intra-robot loop closure)"
    )
    attitude_factors: bool = Field(
        True, description="hold each keyframe's roll and pitch to its measured ground normal (level ground assumed)"
    )
    attitude_warmup_keyframes: int = Field(
        20, ge=2, le=10_000, description="keyframes with a ground fit a robot needs before its normals' sigma "
        "is measured (from their scatter) and its attitude factors start"
    )
    odometry_sigma_rot_rad: float = Field(
        0.001, gt=0, description="odometry step sigma when it did not move (the floor of the drift model)"
    )
    odometry_sigma_trans_m: float = Field(
        0.01, gt=0, description="odometry step sigma when it did not move (the floor of the drift model)"
    )
    odometry_drift_rot_rad_per_m: float | None = Field(
        None, ge=0, le=1, description="odometry step rotation sigma growth per metre driven; None: from where "
        "the depth comes from (``MEASURED_DEPTH_DRIFT``, ``PREDICTED_DEPTH_DRIFT``)"
    )
    odometry_drift_trans_per_m: float | None = Field(
        None, ge=0, le=1, description="odometry step translation sigma growth per metre driven (0.01 = 1 %); "
        "None: from where the depth comes from"
    )
    closure_sigma_rot_rad: float = Field(0.1, gt=0, description="rotation sigma of an inter-robot or loop closure")
    closure_sigma_trans_m: float = Field(3.0, gt=0, description="translation sigma of a closure at its keyframe")
    closure_sigma_per_elevation: float = Field(
        2.6, ge=0, description="a closure's translation sigma grows by this fraction per radian between the two "
        "robots' elevation angles onto its objects (a car and a UAV 50 m up: ~0.7 rad, x2.8): the visible part of "
        "an object moves with the viewpoint. Measured on nine airsim-like tuning worlds (seeds "
        "10-23): car-UAV closures 1.12 m median error, car-car 0.40 m (server/viewpoints.py closure_information)",
    )
    robust_kernel: RobustKernel = Field(RobustKernel.CAUCHY, description="huber | cauchy | tukey | none")
    min_closures_to_anchor: int = Field(
        MATCHES_TO_ANCHOR, ge=1, description="a robot enters the shared frame only when a robot pair's consistent "
        "set has closures from this many independent matches (closures of one match, matches on shared "
        "objects, matches on the same straight stretches of both robots, and matches too close to chance for the "
        "number the pair has tried count once; 1 = trust the first "
        "accepted match). A robot also enters through one match with each of this many placed robots when they "
        "rest on other objects and straight stretches of its own drive and agree on its place "
        "(backend/cross_evidence.py)"
    )
    decisive_match: bool = Field(
        True, description="one graph match whose log likelihood ratio is min_closures_to_anchor times the bar a piece "
        "of evidence clears (its chance threshold plus the log of the matches the pair tried) places a robot by "
        "itself, provisionally until an independent match confirms it (false: only independent matches place)"
    )
    stretch_turn_deg: float | None = Field(
        STRETCH_TURN_DEG, gt=0, le=180, description="matches on the same straight stretches of both robots count "
        "as one piece of evidence; a stretch ends where the direction of travel turns more than this (degrees). "
        "None: only shared objects make matches dependent"
    )
    consistency_trans_m: float = Field(5.0, gt=0, description="pairwise closure consistency, translation")
    consistency_rot_deg: float = Field(10.0, gt=0, description="pairwise closure consistency, rotation")
    consistency_trans_per_m: float = Field(
        0.05, ge=0, description="consistency translation tolerance growth per metre of odometry in the loop"
    )
    consistency_rot_deg_per_m: float = Field(
        0.05, ge=0, description="consistency rotation tolerance growth, degrees per metre of odometry in the loop"
    )



    @field_validator("min_closures_to_anchor", mode="before")
    @classmethod
    def _null_anchor_is_default(cls, value: Any) -> Any:
        """``null`` (configs written before it stopped depending on the depth source) means the default."""
        return MATCHES_TO_ANCHOR if value is None else value

    def for_depth(self, predicted_depth: bool) -> BackendConfig:
        """This stage with the values still None set from where the depth comes from (any robot's depth
        predicted by a model, or all measured): the odometry drift rates (``PREDICTED_DEPTH_DRIFT`` or
        ``MEASURED_DEPTH_DRIFT``)."""
        rot, trans = PREDICTED_DEPTH_DRIFT if predicted_depth else MEASURED_DEPTH_DRIFT
        derived = {
            "odometry_drift_rot_rad_per_m": rot,
            "odometry_drift_trans_per_m": trans,
        }
        return self.model_copy(update={k: v for k, v in derived.items() if getattr(self, k) is None})


class ServerConfig(_Stage):
    """Map server as a process: crash-recovery snapshots and the corrections it sends robots."""

    snapshot_every_messages: int = Field(
        200, ge=0, le=10_000_000, description="write a state snapshot after this many new journal records "
        "(0: no snapshots; a restarted server then replays its whole journal, matching included)"
    )
    snapshot_every_s: float = Field(
        30.0, gt=0, le=86_400, description="also write one when this many seconds passed since the last and new "
        "records arrived"
    )
    snapshots_kept: int = Field(
        2, ge=1, le=100, description="newest snapshots kept (an unreadable newest falls back to the one before)"
    )
    correction_tolerance_m: float = Field(
        0.05, ge=0, le=100, description="a keyframe's fused pose is sent to its robot again once it moved more than "
        "this since the robot last got it (the final correction sends every change)"
    )
    correction_tolerance_rad: float = Field(
        0.005, ge=0, le=3.2, description="... or turned more than this"
    )


class PerceptionConfig(_Stage):
    """ONNX perception (optional): depth and segmentation models."""

    depth_model: Path | None = None
    seg_model: Path | None = None
    threads: int = Field(2, ge=0, le=256, description="onnxruntime intra-op threads (0 = all cores), as --threads")
    camera_height_m: float | None = Field(
        1.65,
        gt=0.0,
        le=10.0,
        description="the camera's height above the road, metres (KITTI and the simulator's cars: 1.65): a depth "
        "model's output is scaled so that the road plane lies this far below the camera "
        "(perception/ground_scale.py); frames without a level road plane at a plausible height (a UAV) "
        "keep the predicted depth; null turns it off. Depth from files is never scaled",
    )


class RobotOverrides(_Stage):
    """Front-end settings of one robot that differ from the fleet's (e.g. a UAV sees farther).

    Each field is a partial mapping of that stage's fields, e.g. ``extraction: {max_depth_m: 100}``.
    """

    extraction: dict | None = None
    odometry: dict | None = None
    keyframes: dict | None = None
    perception: dict | None = None


FRONT_END_STAGES = ("extraction", "graph", "keyframes", "odometry")
"""The stages that shape a robot's keyframes and graph nodes (``ShgmConfig.front_end_digest``)."""

PER_PROCESS_FIELDS = frozenset({("odometry", "kind"), ("odometry", "poses_file"), ("odometry", "icp_threads")})
"""Front-end fields a robot process sets for itself (``--odometry``, its machine's threads): not compared."""

DIGEST_CHARS = 16
"""Hex characters of ``ShgmConfig.front_end_digest`` (64 bits)."""


class ShgmConfig(_Stage):
    """The whole system's configuration."""

    extraction: ExtractionConfig = ExtractionConfig()
    graph: GraphConfig = GraphConfig()
    descriptor: DescriptorConfig = DescriptorConfig()
    matching: MatchingConfig = MatchingConfig()
    odometry: OdometryConfig = OdometryConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    backend: BackendConfig = BackendConfig()
    server: ServerConfig = ServerConfig()
    perception: PerceptionConfig = PerceptionConfig()
    robots: dict[str, RobotOverrides] = Field(
        default_factory=dict, description="per-robot overrides of front-end stages, by robot name"
    )

    @model_validator(mode="after")
    def _overrides_are_valid(self) -> ShgmConfig:
        for name in self.robots:
            try:
                self.for_robot(name)
            except ValidationError as exc:
                first = exc.errors()[0]
                where = ".".join(str(p) for p in first["loc"])
                raise ValueError(f"robots.{name}.{where}: {first['msg']}") from None
        return self

    def for_robot(self, name: str) -> ShgmConfig:
        """The configuration one robot's front end uses: this config with ``robots[name]`` merged in."""
        override = self.robots.get(name)
        if override is None:
            return self
        data = self.model_dump()
        for stage, fields in override.model_dump(exclude_none=True).items():
            data[stage] = {**data[stage], **fields}
        data["robots"] = {}
        return ShgmConfig.model_validate(data)

    def front_end_digest(self, name: str) -> str:
        """A short hex digest of the settings that shape what robot ``name`` sends the map server: its
        extraction, graph, keyframe and odometry stages (``for_robot``, before data-derived values), less
        ``PER_PROCESS_FIELDS``. A robot started with another ``--config`` than its server has another digest
        (``server.node`` refuses it: its graphs would silently differ from what the server's settings say)."""
        data = self.for_robot(name).model_dump(mode="json")
        stages = {s: {k: v for k, v in data[s].items() if (s, k) not in PER_PROCESS_FIELDS} for s in FRONT_END_STAGES}
        text = json.dumps(stages, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:DIGEST_CHARS]

    def with_robot_values(self, values: dict[str, dict[str, dict[str, Any]]]) -> ShgmConfig:
        """This config with robots' resolved values (``{robot: {stage: {field: value}}}``, e.g. the data-derived
        ones, ``scene_scale.effective_fields``) merged into their ``robots`` overrides: loading it reproduces
        those front ends' settings."""
        robots = dict(self.robots)
        for name, stages in values.items():
            base = robots[name].model_dump() if name in robots else {}
            for stage, fields in stages.items():
                base[stage] = {**(base.get(stage) or {}), **fields}
            robots[name] = RobotOverrides.model_validate(base)
        return self.model_copy(update={"robots": robots})

    def to_yaml(self) -> str:
        """The config as YAML text (enums as plain strings, file paths made absolute: ``PATH_FIELDS``, also in
        the robots' overrides). A relative path is read from the working directory, so a results folder's
        ``config.yaml`` given back with ``--config`` from another folder named no such model or poses file."""
        data = self.model_dump(mode="json")
        for stages in (data, *(data["robots"] or {}).values()):
            _absolute_paths(stages)
        return yaml.safe_dump(data, sort_keys=False)


PATH_FIELDS = (("perception", "depth_model"), ("perception", "seg_model"), ("odometry", "poses_file"))
"""(stage, field) of the config's file paths, relative to the working directory when read."""


def _absolute_paths(stages: dict[str, Any]) -> None:
    """Make the ``PATH_FIELDS`` in a dumped config (or one robot's overrides), ``{stage: {field: value}}``,
    absolute in place (from the working directory; symlinks and ``{robot}`` kept as written)."""
    for stage, name in PATH_FIELDS:
        fields = stages.get(stage)
        if isinstance(fields, dict) and isinstance(fields.get(name), str):
            fields[name] = str(Path(fields[name]).absolute())


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (plain YAML keeps the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, str | int | float | bool) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice in one mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


def _yaml_problem(exc: yaml.MarkedYAMLError) -> str:
    """One line: what is wrong and where (1-based line and column)."""
    mark = exc.problem_mark or exc.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return where + " ".join(str(exc.problem or exc.context or exc).split())


def _read_config_text(path: Path) -> str:
    """The text of config file ``path``.

    Raises:
        ConfigError: ``path`` is a folder, does not exist, or cannot be read (no permission, an I/O error: a
            traceback before, e.g. ``/proc/self/mem``'s EIO); the OS error is named.
        UnicodeDecodeError: the file is not UTF-8 text (``load_config`` says so).
    """
    try:  # (is_dir and is_file raise too: a name too long, a parent folder without permission)
        if path.is_dir():
            raise ConfigError(f"config file {path} is a folder; give a YAML file "
                              "(`shgm-slam dump-config > config.yaml`)")  # fmt: skip
        if not path.is_file():
            raise ConfigError(f"config file {path} does not exist (write one with `shgm-slam dump-config > {path}`)")
        return path.read_text()
    except OSError as exc:
        raise ConfigError(f"config file {path} cannot be read: {exc.strerror or exc}; give a readable YAML file "
                          "(`shgm-slam dump-config > config.yaml`)") from None  # fmt: skip


def load_config(path: Path | str | None) -> ShgmConfig:
    """Load a YAML config (partial configs fill in defaults); ``None`` gives the defaults.

    Raises:
        ConfigError: the file is missing, cannot be read (the OS error named), is not YAML, or holds unknown or
            invalid fields.
    """
    if path is None:
        return ShgmConfig()
    path = Path(path)
    try:
        text = _read_config_text(path)
        data = yaml.load(text, Loader=_UniqueKeyLoader) or {}
    except yaml.MarkedYAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {_yaml_problem(exc)}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {' '.join(str(exc).split())}") from None
    except (ValueError, RecursionError) as exc:  # an integer of thousands of digits, nesting too deep
        raise ConfigError(f"config file {path} cannot be read: {parse_failure(exc)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of stages, got {type(data).__name__}")
    return config_from_mapping(data, f"config file {path}")


def config_from_mapping(data: dict, source: str) -> ShgmConfig:
    """``data``, a mapping of stages (what a YAML config file holds), as an ``ShgmConfig``.

    Raises:
        ConfigError: unknown or invalid fields, the first named with its place, after ``source`` (e.g. "config
            file PATH"), and a near miss for a misspelt key or choice.
    """
    try:
        return ShgmConfig.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        hint = ""
        if first["type"] == "extra_forbidden":
            hint = _unknown_key_hint(str(first["loc"][-1]), _fields_at(first["loc"][:-1]))
        elif first["type"] == "enum":  # a misspelt choice (kiss_icp): say what was read and the nearest one
            choices = re.findall(r"'([^']*)'", first.get("ctx", {}).get("expected", ""))
            close = difflib.get_close_matches(str(first["input"]), choices, n=1)
            hint = f", got {first['input']!r}" + (f"; did you mean {close[0]!r}?" if close else "")
        where = f"{where}: " if where else ""  # a whole-config check (robots' overrides) names its own place
        raise ConfigError(f"{source}: {where}{first['msg']}{hint} ({exc.error_count()} error(s))") from None


def _unknown_key_hint(key: str, known: list[str]) -> str:
    """'; did you mean X?' for a near miss, else the keys allowed there (or where to see them)."""
    close = difflib.get_close_matches(key, known, n=1)
    if close:
        return f"; did you mean {close[0]}?"
    if known and len(known) <= 12:
        return f"; known here: {', '.join(known)}"
    return "; `shgm-slam dump-config` lists every key" if known else ""


def _fields_at(loc: tuple) -> list[str]:
    """The field names a config location (``("robots", "uav")``, ``("matching",)``) takes; [] if unknown."""
    model: Any = ShgmConfig
    keyed = False  # the next part is a key of a dict of models (robots.<name>)
    for part in loc:
        if keyed:
            keyed = False
            continue
        field = model.model_fields.get(part) if isinstance(model, type) and issubclass(model, BaseModel) else None
        if field is None:
            return []
        model = field.annotation
        if getattr(model, "__origin__", None) is dict:
            model, keyed = model.__args__[1], True
    return list(model.model_fields) if isinstance(model, type) and issubclass(model, BaseModel) else []
