"""Depth scale from the road plane: exact heights on analytic roads, robustness, what it refuses, the
perception source applying it to model depth only, and rendered car and UAV frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.config import PerceptionConfig
from shgm_slam.data import open_sequence
from shgm_slam.labels import Label
from shgm_slam.perception import OnnxPerception, make_perception
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.ground_scale import MAX_FACTOR, MIN_FACTOR, GroundScale, road_plane, usual_factor
from shgm_slam.types import Frame, Intrinsics
from tests.perception.onnx_builders import channel_model, write_card

INTR = Intrinsics(180.0, 180.0, 159.5, 47.5, 320, 96)


def flat_road(height_m: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth and labels of a camera ``height_m`` above an infinite flat road (sky above the horizon).

    The camera is pitched down by ``pitch_deg`` and rolled by ``roll_deg``; returns (H, W) float32 depth
    (0 where the ray misses the road) and uint8 labels (road where it hits, sky elsewhere).
    """
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], axis=-1)
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    R_pitch = np.array([[1, 0, 0], [0, np.cos(p), np.sin(p)], [0, -np.sin(p), np.cos(p)]])
    R_roll = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    down_cam = (R_pitch @ R_roll).T @ np.array([0.0, 1.0, 0.0])  # the world's down in the camera frame
    along = rays @ down_cam  # how fast each ray descends per unit z
    hit = along > 1e-6
    depth = np.where(hit, height_m / np.where(hit, along, 1.0), 0.0).astype(np.float32)
    labels = np.where(hit, Label.ROAD, Label.SKY).astype(np.uint8)
    return depth, labels


@pytest.mark.parametrize("height_m", [1.2, 1.65, 2.4])
def test_level_road_gives_the_camera_height(height_m: float) -> None:
    depth, labels = flat_road(height_m)
    plane = road_plane(depth, labels, INTR)
    assert plane is not None
    assert plane.height == pytest.approx(height_m, rel=1e-6)
    np.testing.assert_allclose(plane.normal_cam, [0.0, -1.0, 0.0], atol=1e-6)  # up = image up


def test_a_slightly_pitched_and_rolled_camera_still_measures_its_height() -> None:
    depth, labels = flat_road(1.65, pitch_deg=6.0, roll_deg=3.0)
    plane = road_plane(depth, labels, INTR)
    assert plane is not None and plane.height == pytest.approx(1.65, rel=1e-6)


def test_scaled_depth_gives_the_inverse_factor() -> None:
    depth, labels = flat_road(1.65)
    scale = GroundScale(1.65)
    for _ in range(3):
        factor = scale.update(depth * 1.12, labels, INTR)
    assert factor == pytest.approx(1 / 1.12, rel=1e-6)
    assert (scale.frames, scale.planes, scale.rejected) == (3, 3, 0)


def test_a_reset_scale_forgets_the_frames_it_was_shown() -> None:
    """What it saw before a run (frames probed across the sequence) does not reach into the run's first frames."""
    depth, labels = flat_road(1.65)
    scale = GroundScale(1.65)
    for _ in range(5):
        scale.update(depth * 2.0, labels, INTR)  # probed frames, far along the sequence: another scale
    scale.reset()
    assert (scale.frames, scale.planes, scale.rejected) == (0, 0, 0)
    assert scale.update(depth * 1.12, labels, INTR) == pytest.approx(1 / 1.12, rel=1e-6)  # its own frame alone


def test_outliers_labelled_road_do_not_move_the_plane() -> None:
    depth, labels = flat_road(1.65)
    rng = np.random.default_rng(3)
    noisy = depth * rng.normal(1.0, 0.005, depth.shape).astype(np.float32)  # network noise
    road = np.argwhere(labels == Label.ROAD)
    wrong = road[rng.choice(len(road), len(road) // 4, replace=False)]
    noisy[wrong[:, 0], wrong[:, 1]] *= rng.uniform(0.3, 0.8, len(wrong)).astype(np.float32)  # a car called road
    plane = road_plane(noisy, labels, INTR)
    assert plane is not None and plane.height == pytest.approx(1.65, rel=0.02)


def test_few_road_points_with_repeated_samples_still_fit() -> None:
    """A small road patch: some of the RANSAC triples repeat a point (no plane); the others still fit it."""
    depth, labels = flat_road(1.65)
    patch = np.full_like(labels, Label.SKY)
    patch[80:86, 100:120] = Label.ROAD  # 120 pixels: repeated draws among the 64 triples are likely
    plane = road_plane(depth, patch, INTR)
    assert plane is not None and plane.height == pytest.approx(1.65, rel=1e-3)


def test_no_road_or_a_steep_view_gives_no_plane() -> None:
    depth, labels = flat_road(1.65)
    assert road_plane(depth, np.full_like(labels, Label.BUILDING), INTR) is None
    few = np.full_like(labels, Label.SKY)
    few[-1, :40] = Label.ROAD
    assert road_plane(depth, few, INTR) is None
    steep, steep_labels = flat_road(50.0, pitch_deg=50.0)  # a UAV's oblique camera
    assert road_plane(steep, steep_labels, INTR) is None


def test_a_road_at_the_wrong_height_is_refused_and_counted() -> None:
    low = 1.65 / (MAX_FACTOR * 1.2)
    depth, labels = flat_road(low)  # a camera far lower than configured
    scale = GroundScale(1.65)
    assert scale.update(depth, labels, INTR) is None
    assert (scale.planes, scale.rejected) == (0, 1) and scale.rejected_height == pytest.approx(low)
    good, good_labels = flat_road(1.5)
    assert scale.update(good, good_labels, INTR) == pytest.approx(1.1)
    assert scale.update(depth, labels, INTR) == pytest.approx(1.1)  # the refused frame keeps the median


def test_a_road_far_higher_than_configured_is_refused() -> None:
    """A camera 6x higher than configured (a low UAV's level camera) whose road is in range: refused."""
    height = 1.65 / (MIN_FACTOR * 0.8)
    depth, labels = flat_road(height, pitch_deg=12.0)  # pitched down: road within ROAD_RANGE_M
    assert road_plane(depth, labels, INTR).height == pytest.approx(height, rel=1e-6)
    scale = GroundScale(1.65)
    assert scale.update(depth, labels, INTR) is None and scale.rejected == 1


@pytest.mark.parametrize("off", [0.3, 2.5, 3.5])
def test_a_network_several_times_off_scale_is_still_scaled(off: float) -> None:
    """A depth network off by several times on unfamiliar images (the demo models on real KITTI 07 read the
    road 2-10 m below the camera) is scaled to the road like any other, and reported as unusual."""
    depth, labels = flat_road(1.65)
    scale = GroundScale(1.65)
    factor = scale.update(depth * np.float32(off), labels, INTR)
    assert factor == pytest.approx(1 / off, rel=1e-5) and scale.rejected == 0
    assert not usual_factor(factor)
    assert usual_factor(1 / 1.12) and usual_factor(1.12)


def test_the_factor_is_a_running_median() -> None:
    scale = GroundScale(1.65, window=5)
    road_labels = flat_road(1.65)[1]
    factors = [scale.update(flat_road(h)[0], road_labels, INTR) for h in (1.5, 1.5, 1.65, 1.818, 1.65)]
    assert factors[-1] == pytest.approx(1.0)  # median of 1.1, 1.1, 1.0, 0.9075, 1.0


def _frame(depth: np.ndarray | None, labels: np.ndarray, red: int) -> Frame:
    img = np.zeros((INTR.height, INTR.width, 3), dtype=np.uint8)
    img[:, :, 0] = red
    return Frame(index=0, timestamp_s=0.0, intrinsics=INTR, image_rgb=img, depth_m=depth, label_ids=labels)


def test_perception_scales_model_depth_only(tmp_path: Path) -> None:
    model = channel_model(tmp_path / "depth.onnx")  # depth = the red value everywhere
    write_card(tmp_path / "depth.yaml", {"task": "depth", "input": {"size": [32, 16], "scale": 1}})
    _, labels = flat_road(1.65)
    labels[:] = Label.ROAD
    depth_model = DepthModel(model, threads=1)
    # a constant depth is no plane: nothing scaled, reported as None
    out = OnnxPerception(depth_model, ground_scale=GroundScale(1.65)).process(_frame(None, labels, 9))
    assert out.depth_scale is None and float(out.depth_m.max()) == pytest.approx(9.0)
    # files: never scaled, even with a ground scale configured
    files = make_perception(PerceptionConfig(), True, True)
    road_depth, road_labels = flat_road(2.0)
    out = files.process(_frame(road_depth, road_labels, 9))
    assert out.depth_scale is None and np.array_equal(out.depth_m, road_depth)


class _RoadModel:
    """Stands in for a depth model: returns a fixed depth image (what ``OnnxPerception`` calls)."""

    def __init__(self, depth: np.ndarray) -> None:
        self.depth = depth
        self.last_timings = type("T", (), {"as_dict": staticmethod(lambda prefix: {})})()

    def predict(self, image_rgb: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        return self.depth.copy()


def test_perception_puts_the_road_at_the_configured_height() -> None:
    depth, labels = flat_road(1.65)
    source = OnnxPerception(_RoadModel(depth * 0.9), ground_scale=GroundScale(1.65))  # type: ignore[arg-type]
    out = source.process(_frame(None, labels, 0))
    assert out.depth_scale == pytest.approx(1 / 0.9)
    np.testing.assert_allclose(out.depth_m, depth, rtol=1e-5)


def test_rendered_car_and_uav_frames(tiny_scenario: Path) -> None:
    """Simulator cameras: cars 1.65 m above the road (depth scaled by 1.1 comes back within 2 %), the
    UAV's oblique view from 30-60 m never gives a factor."""
    car = open_sequence(tiny_scenario / "car1")
    scale = GroundScale(1.65)
    factor = None
    for i in range(0, len(car), 4):
        frame = car[i]
        factor = scale.update(frame.depth_m * 1.1, frame.label_ids, frame.intrinsics)
    assert scale.planes >= 0.7 * scale.frames
    assert factor is not None and factor == pytest.approx(1 / 1.1, rel=0.02)
    uav = open_sequence(tiny_scenario / "uav")
    scale = GroundScale(1.65)
    for i in range(0, len(uav), 4):
        frame = uav[i]
        assert scale.update(frame.depth_m, frame.label_ids, frame.intrinsics) is None


# --- depth files a model wrote (``shgm-slam perceive``) count as predicted depth -----------------------


def _perceived_copy(src: Path, dst: Path, manifest: str | None) -> Path:
    import shutil

    shutil.copytree(src, dst)
    if manifest is not None:
        (dst / "perceive.json").write_text(manifest)
    return dst


def test_depth_model_of_reads_the_perceive_manifest(tiny_scenario: Path, tmp_path: Path) -> None:
    from shgm_slam.data.base import SequenceView
    from shgm_slam.perception.perceive import depth_model_of

    model = '{"format": "shgm-perceive/1", "depth_model": {"path": "/m/depth.onnx"}, "seg_model": null}'
    seq = open_sequence(_perceived_copy(tiny_scenario / "car1", tmp_path / "a", model))
    assert depth_model_of(seq) == {"path": "/m/depth.onnx"}
    assert depth_model_of(SequenceView(seq, 2, 9)) == {"path": "/m/depth.onnx"}  # a frame range of it
    labels_only = '{"format": "shgm-perceive/1", "depth_model": null, "seg_model": {"path": "s.onnx"}}'
    assert depth_model_of(open_sequence(_perceived_copy(tiny_scenario / "car1", tmp_path / "b", labels_only))) is None
    assert depth_model_of(open_sequence(_perceived_copy(tiny_scenario / "car1", tmp_path / "c", "{not json"))) is None
    assert depth_model_of(open_sequence(tiny_scenario / "car1")) is None  # rendered depth: measured


def test_a_perceived_sequence_runs_as_predicted_depth(tiny_scenario: Path, tmp_path: Path) -> None:
    """Auto picks the visual odometry, the depth is scaled to the road (rendered depth: by ~1), and the
    UAV's oblique view is reported as not scaled; a plain rendered sequence keeps KISS-ICP and its depth."""
    from shgm_slam.config import OdometryKind, ShgmConfig
    from shgm_slam.runner import make_frontend

    model = '{"format": "shgm-perceive/1", "depth_model": {"path": "/m/depth.onnx"}, "seg_model": null}'
    cfg = ShgmConfig()
    car = make_frontend("car1", open_sequence(_perceived_copy(tiny_scenario / "car1", tmp_path / "car", model)), cfg)
    assert car.depth_predicted and car.ground_scale_on
    assert car.odometry_choice is not None and car.odometry_choice.kind is OdometryKind.VISUAL
    for i in range(8):
        car.process(i)
    assert len(car.depth_scales) >= 6 and np.median(car.depth_scales) == pytest.approx(1.0, abs=0.02)
    uav = make_frontend("uav", open_sequence(_perceived_copy(tiny_scenario / "uav", tmp_path / "uav", model)), cfg)
    for i in range(4):
        uav.process(i)
    assert uav.ground_scale_on and uav.depth_scales == []
    plain = make_frontend("car1", open_sequence(tiny_scenario / "car1"), cfg)
    assert not plain.depth_predicted and not plain.ground_scale_on
    assert plain.odometry_choice is not None and plain.odometry_choice.kind is OdometryKind.KISS_ICP
    assert car.cfg.odometry.visual_depth_window_px == 5  # no model input size on record: as configured
    half = '{"depth_model": {"path": "/m/depth.onnx", "input_wh": [160, 48]}}'  # a model at half the width
    grown = make_frontend("car1", open_sequence(_perceived_copy(tiny_scenario / "car1", tmp_path / "half", half)), cfg)
    assert grown.cfg.odometry.visual_depth_window_px == 9  # its edge blur is upsampled with its output
    no_height = cfg.model_copy(update={"perception": PerceptionConfig(camera_height_m=None)})
    off = make_frontend("car1", open_sequence(tmp_path / "car"), no_height)
    assert off.depth_predicted and not off.ground_scale_on
    # road steps at the height the depth is scaled to (the config's own value wins); measured where not scaled
    assert car.cfg.odometry.visual_road_height_m == cfg.perception.camera_height_m == 1.65
    assert plain.cfg.odometry.visual_road_height_m is None and off.cfg.odometry.visual_road_height_m is None
    own = cfg.model_copy(update={"odometry": cfg.odometry.model_copy(update={"visual_road_height_m": 1.5})})
    assert make_frontend("car1", open_sequence(tmp_path / "car"), own).cfg.odometry.visual_road_height_m == 1.5


def test_a_road_never_at_the_configured_height_is_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    from shgm_slam.perception.ground_scale import WARN_AFTER_REJECTED

    depth, labels = flat_road(0.275)  # a sixth of the configured height: every frame refused
    scale = GroundScale(1.65)
    with caplog.at_level("WARNING", logger="shgm_slam.perception.ground_scale"):
        for _ in range(WARN_AFTER_REJECTED + 5):
            assert scale.update(depth, labels, INTR) is None
    warnings = [r for r in caplog.records if "camera_height_m" in r.getMessage()]
    assert len(warnings) == 1 and "0.3 m below the camera" in warnings[0].getMessage()
