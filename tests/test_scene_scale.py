"""Scene scale: camera height from the ground plane, derived per-robot values, config precedence."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import (
    SPACING_PER_VOXEL,
    ExtractionConfig,
    OdometryConfig,
    OdometryKind,
    ShgmConfig,
    load_config,
)
from shgm_slam.geometry import se3
from shgm_slam.geometry.camera import pixel_rays
from shgm_slam.labels import Label
from shgm_slam.runner import run_slam
from shgm_slam.scene_scale import (
    BLOB_RANGE_EXPONENT,
    CLOUD_TARGET_POINTS,
    cloud_stride_for,
    derived_values,
    measure_scene_scale,
    relative_depth_noise,
    resolve_robot_config,
    sample_scene_scale,
)
from shgm_slam.types import Frame, Intrinsics

INTR = Intrinsics(184.06, 184.06, 159.5, 47.5, 320, 96)  # the simulator's 320x96, 82 deg horizontal


def ground_view(height_m: float, pitch_down_deg: float, noise_m: float = 0.0, seed: int = 0):
    """Depth (H, W) and labels of an infinite flat road seen from ``height_m`` with the optical axis
    ``pitch_down_deg`` below the horizon; rays above the horizon see sky (depth 0)."""
    t = np.radians(pitch_down_deg)
    n_cam = np.array([0.0, -np.cos(t), -np.sin(t)])  # ground normal (up) in the camera frame
    down = pixel_rays(INTR) @ n_cam
    depth = np.where(down < -1e-9, -height_m / np.minimum(down, -1e-9), 0.0)
    depth = np.where(depth < 500.0, depth, 0.0)
    if noise_m:
        depth = np.where(depth > 0, depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape), 0.0)
    labels = np.where(depth > 0, Label.ROAD, Label.SKY).astype(np.uint8)
    return depth.astype(np.float32), labels


def nearest_ground_depth(height_m: float, pitch_down_deg: float) -> float:
    """Analytic z-depth of the ground at the lower image edge."""
    below_axis = np.arctan((INTR.height - 1 - INTR.cy) / INTR.fy)
    elevation = np.radians(pitch_down_deg) + below_axis
    return height_m / np.sin(elevation) * np.cos(below_axis)


def scale_of(height_m: float, pitch_down_deg: float, frames: int = 3, labels: bool = True):
    views = [ground_view(height_m, pitch_down_deg, noise_m=0.02 * height_m / 10, seed=i) for i in range(frames)]
    return measure_scene_scale([d for d, _ in views], [lab if labels else None for _, lab in views], INTR)


@pytest.mark.parametrize(("height", "pitch"), [(1.6, 0.0), (50.0, 50.0), (30.0, 90.0), (3.0, 10.0)])
@pytest.mark.parametrize("labels", [True, False])
def test_camera_height_and_nearest_ground_from_a_flat_ground(height, pitch, labels):
    s = scale_of(height, pitch, labels=labels)
    assert s.camera_height_m == pytest.approx(height, rel=0.1)
    assert s.pitch_down_deg == pytest.approx(pitch, abs=2.0)
    assert s.nearest_ground_depth_m == pytest.approx(nearest_ground_depth(height, pitch), rel=0.1)
    assert s.horizon_in_view == (pitch < np.degrees(np.arctan(INTR.cy / INTR.fy)))


def test_predicted_depth_noise_still_gives_the_plane():
    views = [ground_view(50.0, 50.0, noise_m=2.0, seed=i) for i in range(3)]  # ~3 % of the depth, as a network
    s = measure_scene_scale([d for d, _ in views], [lab for _, lab in views], INTR)
    assert s.camera_height_m == pytest.approx(50.0, rel=0.1)
    assert not s.horizon_in_view


def test_car_camera_keeps_the_fleet_values():
    fleet = {"extraction": ExtractionConfig.FLEET, "odometry": {**OdometryConfig.FLEET, "cloud_stride": 1}}
    assert derived_values(scale_of(1.6, 0.0)) == fleet  # 320x96: every pixel, as many as 640x192 at stride 2


@pytest.mark.parametrize(("image_px", "stride"), [((320, 96), 1), ((640, 192), 2), ((1242, 375), 4), ((50, 20), 1)])
def test_cloud_stride_keeps_about_the_same_number_of_points(image_px, stride):
    assert cloud_stride_for(image_px) == stride
    points = (image_px[0] // stride) * (image_px[1] // stride)
    assert points <= 1.6 * CLOUD_TARGET_POINTS


def test_uav_camera_takes_objects_farther_smaller_and_shuffles():
    s = scale_of(50.0, 50.0)
    v = derived_values(s)
    ex, od = v["extraction"], v["odometry"]
    near = nearest_ground_depth(50.0, 50.0)  # ~54 m: beyond the car's whole range
    assert ex["max_depth_m"] == pytest.approx(2 * near, rel=0.02)
    assert ex["max_depth_m"] > s.depth_percentiles_m[2]  # the whole footprint is kept
    fleet = ExtractionConfig.FLEET
    ratio = ex["max_depth_m"] / fleet["max_depth_m"]
    assert ex["min_blob_fraction"] == pytest.approx(fleet["min_blob_fraction"] / ratio**BLOB_RANGE_EXPONENT)
    assert od["shuffle_points"] is True
    assert od["visual_max_depth_m"] == pytest.approx(OdometryConfig.FLEET["visual_max_depth_m"] * ratio, rel=0.01)
    assert 1.2 < od["voxel_size_m"] < 2.5
    assert od["max_range_m"] >= s.farthest_ground_range_m  # the farthest ground stays in the cloud


def test_higher_camera_sees_farther():
    low, high = derived_values(scale_of(40.0, 50.0)), derived_values(scale_of(60.0, 50.0))
    assert high["extraction"]["max_depth_m"] > low["extraction"]["max_depth_m"]
    assert high["extraction"]["min_blob_fraction"] < low["extraction"]["min_blob_fraction"]


def test_no_valid_depth_gives_none_and_the_fleet_values():
    assert measure_scene_scale([np.zeros((96, 320), np.float32)], [None], INTR) is None
    cfg = resolve_robot_config(ShgmConfig(), None)
    assert cfg.extraction.max_depth_m == ExtractionConfig.FLEET["max_depth_m"]
    assert cfg.odometry.voxel_size_m == OdometryConfig.FLEET["voxel_size_m"]


def test_no_planar_ground_falls_back_to_the_depth_percentiles():
    depth = np.random.default_rng(0).uniform(60.0, 90.0, (96, 320)).astype(np.float32)  # a rough, far scene
    s = measure_scene_scale([depth], [None], INTR)
    assert s.camera_height_m is None and s.horizon_in_view
    assert s.nearest_ground_depth_m == pytest.approx(61.5, abs=1.0)  # 5th percentile of U(60, 90)
    assert derived_values(s)["extraction"]["max_depth_m"] > ExtractionConfig.FLEET["max_depth_m"]


def _relative_noise(depth: np.ndarray, sigma: float, correlation_px: float, seed: int = 0) -> np.ndarray:
    """``depth`` times (1 + sigma e), e unit Gaussian noise smoothed over ``correlation_px`` (a sensor's)."""
    import cv2

    e = np.random.default_rng(seed).standard_normal(depth.shape).astype(np.float32)
    if correlation_px:
        e = cv2.GaussianBlur(e, (0, 0), correlation_px)
        e /= e.std()
    return np.where(depth > 0, depth * (1.0 + sigma * e), 0.0).astype(np.float32)


def _two_walls() -> tuple[np.ndarray, np.ndarray]:
    """A wall 12 m ahead turned 30 deg, beside a parallel one 30 m ahead: planes of different labels, an edge."""
    rays = pixel_rays(INTR)
    n = np.array([np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))])
    depth = 12.0 / (rays @ n)
    far = rays[..., 0] > 0.2
    depth[far] = 30.0
    labels = np.where(far, Label.BUILDING, Label.WALL).astype(np.uint8)
    return depth.astype(np.float32), labels


def test_depth_noise_is_zero_on_planes_seen_at_any_angle():
    for depth, labels in (ground_view(1.6, 0.0), ground_view(50.0, 50.0), _two_walls()):
        assert relative_depth_noise(depth, labels) < 1e-4


@pytest.mark.parametrize("sigma", [0.01, 0.03, 0.05, 0.1])
@pytest.mark.parametrize("correlation_px", [0.0, 2.0, 4.0])
def test_depth_noise_measures_relative_sensor_noise(sigma, correlation_px):
    depth, labels = _two_walls()
    measured = relative_depth_noise(_relative_noise(depth, sigma, correlation_px), labels)
    assert 0.7 * sigma < measured < 1.3 * sigma


def test_depth_noise_leaves_out_object_edges():
    """A row of poles 12 m ahead, 5 px wide every 11 px, before a wall 30 m ahead: most triples cross an edge."""
    columns = np.arange(INTR.width) % 11 < 5
    depth = np.where(columns, 12.0, 30.0) * np.ones((INTR.height, 1))
    labels = np.where(columns, Label.POLE, Label.BUILDING).astype(np.uint8) * np.ones((INTR.height, 1), np.uint8)
    assert relative_depth_noise(depth, None) > 0.1  # one surface assumed: the edges read as noise
    assert relative_depth_noise(depth, labels) < 1e-4


def test_noisy_depth_gets_a_coarser_odometry_voxel_and_noise_free_depth_keeps_it():
    views = [ground_view(1.6, 0.0) for _ in range(3)]
    clean = measure_scene_scale([d for d, _ in views], [lab for _, lab in views], INTR)
    noisy = measure_scene_scale([_relative_noise(d, 0.05, 4.0, i) for i, (d, _) in enumerate(views)],
                                [lab for _, lab in views], INTR)  # fmt: skip
    assert clean.depth_noise_rel < 1e-4 and noisy.depth_noise_rel == pytest.approx(0.05, rel=0.3)
    assert derived_values(clean)["odometry"]["voxel_size_m"] == OdometryConfig.FLEET["voxel_size_m"]
    voxel = derived_values(noisy)["odometry"]["voxel_size_m"]
    assert voxel == pytest.approx(3.0 * noisy.depth_noise_rel * noisy.depth_percentiles_m[1], rel=0.01)
    assert voxel > OdometryConfig.FLEET["voxel_size_m"]
    spacing = resolve_robot_config(ShgmConfig(), noisy).odometry.max_spacing_m
    assert spacing == pytest.approx(SPACING_PER_VOXEL * voxel, rel=0.01)  # the spacing filter follows
    # ICP's steps are blended with the image tracks' on the noisy depth only; a config's value wins
    assert derived_values(noisy)["odometry"]["image_step_blend"] is True
    assert derived_values(clean)["odometry"]["image_step_blend"] is False
    assert derived_values(None)["odometry"]["image_step_blend"] is False
    off = ShgmConfig.model_validate({"odometry": {"image_step_blend": False}})
    assert resolve_robot_config(off, noisy).odometry.image_step_blend is False
    down = [ground_view(50.0, 60.0) for _ in range(3)]  # a UAV: the ground only, the horizon out of view
    uav = measure_scene_scale([_relative_noise(d, 0.05, 4.0, i) for i, (d, _) in enumerate(down)],
                              [lab for _, lab in down], INTR)  # fmt: skip
    assert not uav.horizon_in_view and uav.depth_noise_rel > 0.01
    assert derived_values(uav)["odometry"]["image_step_blend"] is False  # PnP on one distant plane: ICP's steps


def test_config_values_win_over_derived_ones():
    cfg = ShgmConfig.model_validate({
        "extraction": {"max_depth_m": 55.0},
        "robots": {"uav": {"odometry": {"voxel_size_m": 0.7, "shuffle_points": False}}},
    })
    resolved = resolve_robot_config(cfg.for_robot("uav"), scale_of(50.0, 50.0))
    assert resolved.extraction.max_depth_m == 55.0
    assert resolved.odometry.voxel_size_m == 0.7 and resolved.odometry.shuffle_points is False
    assert resolved.odometry.visual_max_depth_m > OdometryConfig.FLEET["visual_max_depth_m"]  # still derived
    assert resolved.extraction.min_blob_fraction < ExtractionConfig.FLEET["min_blob_fraction"]


def test_spacing_filter_follows_the_voxel_a_robot_gets():
    """Points are kept where their image-grid neighbours lie within ``SPACING_PER_VOXEL`` of a voxel: a car keeps
    the fleet's 0.6 m, a high UAV (far ground, coarse voxels) a wider spacing, a voxel from the config moves it
    too, and a spacing from the config wins."""
    car = resolve_robot_config(ShgmConfig(), scale_of(1.6, 0.0)).odometry
    assert car.max_spacing_m == pytest.approx(0.6)
    high = resolve_robot_config(ShgmConfig(), scale_of(90.0, 45.0)).odometry
    assert high.voxel_size_m > 2.0
    assert high.max_spacing_m == pytest.approx(SPACING_PER_VOXEL * high.voxel_size_m, rel=0.01)
    cfg = ShgmConfig.model_validate({"robots": {"uav": {"odometry": {"voxel_size_m": 3.0}}}}).for_robot("uav")
    assert resolve_robot_config(cfg, scale_of(1.6, 0.0)).odometry.max_spacing_m == pytest.approx(1.8)
    cfg = ShgmConfig.model_validate({"odometry": {"max_spacing_m": 0.4}})
    assert resolve_robot_config(cfg, scale_of(90.0, 45.0)).odometry.max_spacing_m == 0.4
    assert OdometryConfig().filled().max_spacing_m == pytest.approx(0.6)  # nothing measured: the fleet's


@dataclass
class GroundSequence:
    """An in-memory sequence over a flat road at a fixed height, driving along the camera's x axis."""

    name: str
    height_m: float
    pitch_down_deg: float
    frames: int = 12

    intrinsics: Intrinsics = INTR

    def __len__(self) -> int:
        return self.frames

    def __getitem__(self, index: int) -> Frame:
        depth, labels = ground_view(self.height_m, self.pitch_down_deg)
        return Frame(index, index / 10.0, INTR, None, depth, labels, self.gt_poses[index], index)

    @property
    def timestamps_s(self) -> np.ndarray:
        return np.arange(self.frames) / 10.0

    @property
    def gt_poses(self) -> np.ndarray:
        poses = np.tile(np.eye(4), (self.frames, 1, 1))
        poses[:, :3, :3] = se3.rot_x(-np.radians(self.pitch_down_deg))
        poses[:, 0, 3] = np.arange(self.frames) * 1.0
        return poses

    has_depth = True
    has_labels = True


def test_sample_scene_scale_skips_frames_without_depth():
    seq = GroundSequence("uav", 50.0, 50.0, frames=30)
    calls = []

    def perceive(frame):
        calls.append(frame.index)
        return (np.zeros_like(frame.depth_m) if frame.index == 0 else frame.depth_m), frame.label_ids

    s = sample_scene_scale(seq, perceive)
    assert s is not None and s.frames == 5 and 0 in calls
    assert s.camera_height_m == pytest.approx(50.0, rel=0.1)
    assert sample_scene_scale(seq, lambda f: (np.zeros_like(f.depth_m), None)) is None


def _facade(distance_m: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """A building's wall filling the view ``distance_m`` ahead: no labelled ground, its lowest rows a plane."""
    depth = np.full((INTR.height, INTR.width), distance_m, np.float32)
    return depth, np.full(depth.shape, Label.BUILDING, np.uint8)


def test_sample_scene_scale_measures_where_the_ground_comes_into_view():
    """A UAV that takes off beside a tower sees only its facade for the first seconds: measured there, it got a
    car's scale (objects up to 30 m, from 50 m up). The frames whose labels show the ground decide; without
    labels, or where no frame shows ground, the first frames decide as before."""
    seq = GroundSequence("uav", 50.0, 50.0, frames=80)
    tower_until = 32

    def perceive(frame):
        return _facade() if frame.index < tower_until else (frame.depth_m, frame.label_ids)

    s = sample_scene_scale(seq, perceive)
    assert s.frame_indices == (35, 40, 45, 50, 55)
    assert s.camera_height_m == pytest.approx(50.0, rel=0.05)
    assert derived_values(s)["extraction"]["max_depth_m"] > 2.0 * 50.0  # the nearest ground is ~60 m away
    first_only = derived_values(measure_scene_scale([_facade()[0]] * 5, [_facade()[1]] * 5, INTR))
    assert first_only["extraction"]["max_depth_m"] == ExtractionConfig.FLEET["max_depth_m"]  # the old fault

    unlabelled = sample_scene_scale(seq, lambda f: (perceive(f)[0], None))
    assert unlabelled.frame_indices == (0, 5, 10, 15, 20)  # the ground cannot be told apart: the first frames
    never = sample_scene_scale(GroundSequence("uav", 50.0, 50.0, frames=200), lambda f: _facade())
    assert never.frame_indices == (0, 5, 10, 15, 20)
    car = sample_scene_scale(GroundSequence("car", 1.6, 0.0, frames=80), lambda f: (f.depth_m, f.label_ids))
    assert car.frame_indices == (0, 5, 10, 15, 20)


def test_results_config_holds_each_robots_resolved_values(tmp_path: Path):
    robots = {"car": GroundSequence("car", 1.6, 0.0), "uav": GroundSequence("uav", 50.0, 50.0)}
    cfg = ShgmConfig.model_validate({"odometry": {"kind": OdometryKind.GT.value}})
    summary = run_slam(robots, cfg, tmp_path / "out")
    saved = load_config(summary.out_dir / "config.yaml")
    car, uav = saved.for_robot("car"), saved.for_robot("uav")
    assert car.extraction.max_depth_m == ExtractionConfig.FLEET["max_depth_m"]
    assert car.odometry.shuffle_points is False
    assert uav.extraction.max_depth_m == pytest.approx(2 * nearest_ground_depth(50.0, 50.0), rel=0.02)
    assert uav.odometry.shuffle_points is True
    assert car.odometry.max_spacing_m == pytest.approx(0.6)
    assert uav.odometry.max_spacing_m == pytest.approx(SPACING_PER_VOXEL * uav.odometry.voxel_size_m, rel=0.01)
    # re-running with the saved file reproduces the values: nothing is left to derive
    for robot in (car, uav):
        assert resolve_robot_config(robot, None) == robot


def test_very_wide_camera_keeps_the_odometry_range_near_its_depth():
    """A 150 deg camera 50 m up, 50 deg down: every corner ray meets the ground, the top ones ~3.7 km away, but the
    depth (rendered to 200 m of z) ends far sooner; KISS-ICP's range (its adaptive threshold grows with it) stayed
    at 1.1 x 3.7 km and the airsim-like UAV's odometry failed on every frame."""
    wide = Intrinsics(42.87, 42.87, 159.5, 47.5, 320, 96)  # 150 deg horizontal
    t = np.radians(50.0)
    down = pixel_rays(wide) @ np.array([0.0, -np.cos(t), -np.sin(t)])
    depth = np.where(down < -1e-9, -50.0 / np.minimum(down, -1e-9), 0.0)
    depth = np.where(depth <= 200.0, depth, 0.0).astype(np.float32)
    labels = np.where(depth > 0, Label.ROAD, Label.SKY).astype(np.uint8)
    s = measure_scene_scale([depth] * 3, [labels] * 3, wide)
    assert s.camera_height_m == pytest.approx(50.0, rel=0.01)
    assert s.farthest_ground_range_m > 3000.0  # every corner meets the ground
    u = (np.arange(320) - wide.cx) / wide.fx
    v = (np.arange(96) - wide.cy) / wide.fy
    ranges = depth * np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    assert s.farthest_depth_range_m == pytest.approx(ranges.max())
    max_range = derived_values(s)["odometry"]["max_range_m"]
    assert s.farthest_depth_range_m < max_range <= 1.1 * 1.5 * s.farthest_depth_range_m * 1.01


def test_farthest_depth_leaves_the_tuned_uav_range_as_it_was():
    """At 82 deg the UAV's farthest depth is its farthest ground: max_range_m is 1.1 x that ground's range."""
    s = scale_of(50.0, 50.0)
    assert s.farthest_depth_range_m == pytest.approx(s.farthest_ground_range_m, rel=0.05)
    assert derived_values(s)["odometry"]["max_range_m"] == pytest.approx(1.1 * s.farthest_ground_range_m, rel=0.01)
