"""Frames fed one by one (``shgm_slam.live``): the results a recorded run gives, poses as frames come, clear errors."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from shgm_slam import open_sequence
from shgm_slam.api import run
from shgm_slam.config import ShgmConfig
from shgm_slam.data.interleave import interleave
from shgm_slam.data.stream import FrameStream
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.live import LiveRun
from shgm_slam.types import DepthOrigin, Intrinsics
from shgm_slam.viz.rerun_logger import RerunMode

NAMES = ("car1", "car2")


def feed(live: LiveRun, sequences: dict, order: list[tuple[str, int]]) -> list:
    """Every frame of ``order`` given to ``live`` as a camera would give it; the poses it returned, in order."""
    poses = []
    for robot, i in order:
        f = sequences[robot][i]
        poses += live.add_frame(robot, f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                                T_world_cam=f.T_world_cam)  # fmt: skip
    return poses


@pytest.fixture(scope="module")
def live_and_recorded(tiny_scenario: Path, tmp_path_factory: pytest.TempPathFactory):
    """car1 and car2 of the tiny world: run from their folders, and fed frame by frame in the order the run takes."""
    tmp = tmp_path_factory.mktemp("live")
    sequences = {n: open_sequence(tiny_scenario / n) for n in NAMES}
    recorded = run(sequences, tmp / "recorded")
    order = list(interleave(sequences))
    live = LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp / "live")
    poses = feed(live, sequences, order)
    before_finish = {n: live.trajectory(n) for n in NAMES}
    return recorded, live, live.finish(), poses, order, sequences, before_finish


def test_frames_fed_one_by_one_give_the_recorded_runs_results(live_and_recorded) -> None:
    recorded, _, summary, _, _, _, _ = live_and_recorded
    assert (summary.matches_tried, summary.closures_accepted) == (recorded.matches_tried, recorded.closures_accepted)
    assert summary.robots[1].localized and summary.robots[1].ate_fused_m < 2.0
    compared = 0
    for robot in NAMES:
        for kind in ("fused_tum", "odometry_tum", "gt_tum"):
            name = f"{robot}_{kind}.txt"
            assert (recorded.out_dir / name).is_file() == (summary.out_dir / name).is_file(), name
            if (summary.out_dir / name).is_file():
                assert (recorded.out_dir / name).read_bytes() == (summary.out_dir / name).read_bytes(), name
                compared += 1
    assert compared == 6
    assert (recorded.out_dir / "config.yaml").read_text() == (summary.out_dir / "config.yaml").read_text()


def test_every_frame_gets_its_pose_once_in_order_and_placed_poses_are_the_fused_ones(live_and_recorded) -> None:
    """Held frames come back at the call that starts the run; then each call returns its own frame. A pose the map
    server had placed lies where the final fused trajectory puts it, within the corrections that came later."""
    _, live, summary, poses, order, sequences, _ = live_and_recorded
    assert [(p.robot, p.index) for p in poses] == order
    assert all(p.skipped is None for p in poses)
    for robot in NAMES:
        mine = [p for p in poses if p.robot == robot]
        odo = np.loadtxt(summary.out_dir / f"{robot}_odometry_tum.txt")
        T = np.stack([p.T_odom_cam for p in mine])
        np.testing.assert_allclose(T[:, :3, 3], odo[:, 1:4], atol=1e-5)  # the poses returned are the written ones
    placed = [p for p in poses if p.T_shared_cam is not None]
    # the reference is placed from its first frame on, for good (before, from the first match's correction on)
    assert placed and placed[0].robot == "car1" and placed[0].index == 0
    assert all(p.T_shared_cam is not None for p in poses if p.robot == "car1" and p.index >= placed[0].index)
    fused = np.loadtxt(summary.out_dir / "car1_fused_tum.txt")
    rows = {round(t, 6): xyz for t, xyz in zip(fused[:, 0], fused[:, 1:4], strict=True)}
    errors = [np.linalg.norm(p.T_shared_cam[:3, 3] - rows[round(p.timestamp_s, 6)])
              for p in placed if p.robot == "car1"]
    assert max(errors) < 1.0  # where car1 was said to be live is where the final estimate puts it, within corrections
    assert len(live.streams["car1"]._images) == len(sequences["car1"])
    assert all(image is None for image in live.streams["car1"]._images)  # every frame run was released


def late_car2(sequences: dict, live: LiveRun, *, add_camera: bool) -> tuple[list, object]:
    """car1 drives on its own for 40 frames; car2's camera (named at the start, or added then) comes 5 s late."""
    alone = feed(live, sequences, [("car1", i) for i in range(40)])
    assert live.started and live.warming == (() if add_camera else ("car2",))
    assert [p.index for p in alone] == list(range(40))  # held until car1 was warm, then every frame at once
    if add_camera:
        live.add_camera("car2", sequences["car2"].intrinsics)
        assert live.warming == ("car2",)
    late = [("car1", i) for i in range(40, len(sequences["car1"]))]
    late += [("car2", i) for i in range(len(sequences["car2"]))]
    late.sort(key=lambda ri: (sequences[ri[0]].timestamps_s[ri[1]] + (5.0 if ri[0] == "car2" else 0.0), ri[0]))
    poses = feed(live, sequences, late)
    assert sorted((p.robot, p.index) for p in poses) == sorted(late)  # every frame once
    first_car2 = next(k for k, p in enumerate(poses) if p.robot == "car2")
    assert poses[first_car2].index == 0 and not live.warming
    return poses, live.finish()


def test_the_current_trajectory_is_the_fused_one_the_folder_gets(live_and_recorded) -> None:
    """``trajectory``: before ``finish``, every frame run in the shared frame within what the final matching
    corrected; after, the written fused trajectory itself."""
    _, live, summary, _, _, sequences, before_finish = live_and_recorded
    for robot in NAMES:
        fused = np.loadtxt(summary.out_dir / f"{robot}_fused_tum.txt")
        times, T_shared_cam = live.trajectory(robot)
        assert len(times) == len(sequences[robot]) and T_shared_cam.shape == (len(times), 4, 4)
        np.testing.assert_allclose(times, fused[:, 0], atol=1e-6)
        np.testing.assert_allclose(T_shared_cam[:, :3, 3], fused[:, 1:4], atol=1e-4)
        if before_finish[robot] is None:  # (placed by the final whole-graph matching)
            assert robot != "car1"  # the shared frame's robot is placed from the server's first correction on
            continue
        times_then, T_then = before_finish[robot]
        assert len(times_then) == len(times)
        assert np.nanmax(np.linalg.norm(T_then[:, :3, 3] - T_shared_cam[:, :3, 3], axis=1)) < 2.0
    with pytest.raises(ConfigError, match="no camera 'car3'"):
        live.trajectory("car3")


def test_a_camera_that_starts_late_joins_the_running_system(tiny_scenario: Path, tmp_path: Path) -> None:
    """car1 drives on its own (the run starts once its first frames are in); car2's camera comes 40 frames later
    and joins once its own first frames are in; the files list both in the fleet's order. A camera added to the
    run at that point (``add_camera``) gives the same files as one named at the start that sent late."""
    sequences = {n: open_sequence(tiny_scenario / n) for n in NAMES}
    named = LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp_path / "named")
    _, summary = late_car2(sequences, named, add_camera=False)
    assert [r.name for r in summary.robots] == ["car1", "car2"] and summary.robots[0].localized
    assert (summary.out_dir / "car2_odometry_tum.txt").is_file() and (summary.out_dir / "car2_gt_tum.txt").is_file()
    assert "car2" in (summary.out_dir / "config.yaml").read_text()

    added = LiveRun({"car1": sequences["car1"].intrinsics}, tmp_path / "added", viewer=RerunMode.SAVE)
    _, later = late_car2(sequences, added, add_camera=True)
    assert [r.name for r in later.robots] == ["car1", "car2"]
    assert [r.localized for r in later.robots] == [r.localized for r in summary.robots]
    for name in (f"{r}_{kind}.txt" for r in NAMES for kind in ("fused_tum", "odometry_tum", "gt_tum")):
        assert (summary.out_dir / name).is_file() == (later.out_dir / name).is_file(), name
        if (later.out_dir / name).is_file():
            assert (summary.out_dir / name).read_bytes() == (later.out_dir / name).read_bytes(), name
    assert (summary.out_dir / "config.yaml").read_text() == (later.out_dir / "config.yaml").read_text()
    assert (later.out_dir / "run.rrd").stat().st_size > 0


def test_add_camera_refuses_a_taken_name_bad_intrinsics_and_a_finished_run(tiny_scenario: Path, tmp_path: Path,
                                                                            caplog) -> None:  # fmt: skip
    seq = open_sequence(tiny_scenario / "car1")
    live = LiveRun({"car1": seq.intrinsics}, tmp_path / "out")
    with pytest.raises(ConfigError, match="in this run already"):
        live.add_camera("car1", seq.intrinsics)
    with pytest.raises(ConfigError, match="robot name"):
        live.add_camera("car 2/x", seq.intrinsics)
    with pytest.raises(DataError, match="intrinsics"):
        live.add_camera("car2", "not intrinsics")  # type: ignore[arg-type]
    assert list(live.streams) == ["car1"]  # the refusals added nothing
    feed(live, {"car1": seq}, [("car1", i) for i in range(30)])
    with caplog.at_level("WARNING"):
        live.add_camera("uav", seq.intrinsics, depth_origin=DepthOrigin.PREDICTED)
    assert "measured depth's odometry drift rates" in caplog.text
    summary = live.finish()
    assert [r.name for r in summary.robots] == ["car1"]  # the camera added never sent a frame: left out
    with pytest.raises(ConfigError, match="finished"):
        live.add_camera("car3", seq.intrinsics)


def test_frames_held_for_a_first_camera_that_never_sends_are_said_once_and_run_at_finish(
    tiny_scenario: Path, tmp_path: Path, caplog
) -> None:
    seq = open_sequence(tiny_scenario / "car2")
    live = LiveRun({"car1": seq.intrinsics, "car2": seq.intrinsics}, tmp_path / "out")
    with caplog.at_level("WARNING"):
        got = feed(live, {"car2": seq}, [("car2", i) for i in range(len(seq))])
    assert got == [] and not live.started
    assert caplog.text.count("the run starts with the first camera, car1") == 1
    summary = live.finish()  # car2 becomes the shared frame's robot
    assert [r.name for r in summary.robots] == ["car2"] and summary.robots[0].localized


def test_a_camera_that_never_sends_is_left_out(tiny_scenario: Path, tmp_path: Path, caplog) -> None:
    seq = open_sequence(tiny_scenario / "car1")
    live = LiveRun({"car1": seq.intrinsics, "car2": seq.intrinsics}, tmp_path / "out")
    got = feed(live, {"car1": seq}, [("car1", i) for i in range(len(seq))])
    assert len(got) == len(seq) and live.warming == ("car2",)
    with caplog.at_level("WARNING"):
        summary = live.finish()
    assert [r.name for r in summary.robots] == ["car1"] and summary.robots[0].localized
    assert "car2: no frame was given" in caplog.text
    assert (summary.out_dir / "metrics.json").is_file()
    with pytest.raises(ConfigError, match="finished"):
        feed(live, {"car1": seq}, [("car1", 0)])


def test_bad_frames_are_refused_at_the_call_that_brought_them(tiny_scenario: Path, tmp_path: Path) -> None:
    seq = open_sequence(tiny_scenario / "car1")
    f0, f1 = seq[0], seq[1]
    with LiveRun({"car1": seq.intrinsics}, tmp_path / "out") as live:
        live.add_frame("car1", f0.image_rgb, f0.timestamp_s, depth_m=f0.depth_m, label_ids=f0.label_ids)
        with pytest.raises(DataError, match="later than the last"):
            live.add_frame("car1", f1.image_rgb, f0.timestamp_s, depth_m=f1.depth_m, label_ids=f1.label_ids)
        with pytest.raises(DataError, match="no depth_m given"):
            live.add_frame("car1", f1.image_rgb, f1.timestamp_s, label_ids=f1.label_ids)
        with pytest.raises(DataError, match="frame 1: depth_m has shape"):
            live.add_frame("car1", f1.image_rgb, f1.timestamp_s, depth_m=f1.depth_m[:-1], label_ids=f1.label_ids)
        with pytest.raises(ConfigError, match="no camera 'car3'"):
            live.add_frame("car3", f1.image_rgb, f1.timestamp_s)
        live.add_frame("car1", f1.image_rgb, f1.timestamp_s, depth_m=f1.depth_m, label_ids=f1.label_ids)
        assert len(live.streams["car1"]) == 2  # the refused frames left nothing behind
    assert (tmp_path / "out" / "metrics.json").is_file()  # leaving the block finished the run


def test_refusals_before_any_frame(tmp_path: Path) -> None:
    K = Intrinsics(100.0, 100.0, 64.0, 32.0, 128, 64)
    with pytest.raises(ConfigError, match="no cameras"):
        LiveRun({}, tmp_path / "a")
    with pytest.raises(ConfigError, match="odometry 'file'"):
        LiveRun({"car1": K}, tmp_path / "b",
                config=ShgmConfig.model_validate({"odometry": {"kind": "file", "poses_file": "x.txt"}}))
    with pytest.raises(DataError, match="intrinsics"):
        LiveRun({"car1": "not intrinsics"}, tmp_path / "c")  # type: ignore[dict-item]
    with pytest.raises(ConfigError, match=r"settings for robot\(s\) uav .*name such a camera when making the LiveRun"):
        LiveRun({"car1": K}, tmp_path / "d", config=ShgmConfig.model_validate({"robots": {"uav": {}}}))
    assert not any((tmp_path / d).exists() for d in "abcd")


def test_a_stream_drops_released_frames_and_says_so() -> None:
    K = Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4)
    stream = FrameStream(K, name="cam")
    for i in range(3):
        stream.append(np.full((4, 8), i, np.uint8), 0.1 * i, depth_m=np.full((4, 8), np.nan, np.float32))
    assert len(stream) == 3 and stream.has_depth and not stream.has_labels and stream.gt_poses is None
    assert stream[2].image_rgb.shape == (4, 8, 3) and (stream[2].depth_m == 0).all()  # grey replicated, NaN -> 0
    np.testing.assert_allclose(stream.timestamps_s, [0.0, 0.1, 0.2])
    stream.release(1)
    with pytest.raises(DataError, match="frame 1 was processed and released"):
        stream[1]
    assert stream[2].image_rgb[0, 0, 0] == 2
    with pytest.raises(DataError, match="not a finite time"):
        stream.append(np.zeros((4, 8), np.uint8), float("nan"), depth_m=np.ones((4, 8), np.float32))


def test_the_readme_live_example_runs(tiny_scenario: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """The README's *Frames as cameras deliver them* example, where ``make demo``'s world is the tiny world."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = text[text.index("#### Frames as cameras deliver them"):]
    found = re.search(r"```python\n(.*?)```", section, re.S)
    assert found, "README: *Frames as cameras deliver them* has no python block"
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "airsim-like-seed0").symlink_to(tiny_scenario)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "readme_live_example"}
    exec(compile(found.group(1), "README.md", "exec"), namespace)
    summary = namespace["summary"]
    assert summary.out_dir == Path("results/live") and [r.name for r in summary.robots] == ["car1", "car2"]
    assert "car1" in namespace["joined"] and (summary.out_dir / "metrics.json").is_file()
    assert "car1 joined at frame" in capsys.readouterr().out


def test_the_viewer_gets_the_live_run(tiny_scenario: Path, tmp_path: Path) -> None:
    seq = open_sequence(tiny_scenario / "car1")
    with LiveRun({"car1": seq.intrinsics}, tmp_path / "out", viewer=RerunMode.SAVE) as live:
        feed(live, {"car1": seq}, [("car1", i) for i in range(30)])
    assert (tmp_path / "out" / "run.rrd").stat().st_size > 10_000
    with pytest.raises(ConfigError, match="viewer 'nowhere'"):
        LiveRun({"car1": seq.intrinsics}, tmp_path / "other", viewer="nowhere")  # type: ignore[arg-type]


def test_a_live_robot_refuses_a_bad_endpoint_and_a_poses_file(tmp_path: Path) -> None:
    from shgm_slam.live import LiveRobot

    K = Intrinsics(100.0, 100.0, 64.0, 32.0, 128, 64)
    with pytest.raises(ConfigError):
        LiveRobot("car1", K, connect="not an endpoint")
    with pytest.raises(ConfigError, match="odometry 'file'"):
        LiveRobot("car1", K, config=ShgmConfig.model_validate({"odometry": {"kind": "file", "poses_file": "x.txt"}}))
    with pytest.raises(ConfigError):
        LiveRobot("server", K)  # a reserved name


def test_cameras_on_their_own_threads_feed_one_run(tiny_scenario: Path, tmp_path: Path) -> None:
    """Each camera's driver calls ``add_frame`` from its own thread: frames run one at a time, each once."""
    import threading

    sequences = {n: open_sequence(tiny_scenario / n) for n in NAMES}
    live = LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp_path / "out")
    poses: dict[str, list] = {n: [] for n in NAMES}
    errors: list[BaseException] = []

    def camera(name: str) -> None:
        try:
            poses[name] += feed(live, sequences, [(name, i) for i in range(len(sequences[name]))])
        except BaseException as exc:  # reported below, not lost in the thread
            errors.append(exc)

    threads = [threading.Thread(target=camera, args=(n,)) for n in NAMES]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors and not any(t.is_alive() for t in threads)
    returned = sorted((p.robot, p.index) for got in poses.values() for p in got)
    assert returned == sorted((n, i) for n in NAMES for i in range(len(sequences[n])))
    summary = live.finish()
    assert [r.name for r in summary.robots] == list(NAMES) and summary.robots[0].localized


def test_predicted_depth_fed_one_by_one_gives_the_recorded_run(tiny_scenario: Path, tmp_path: Path) -> None:
    """The demo models' depth is scaled to the camera height over a window of frames: the recorded run's checks of
    frames across the sequence do not prime that window (it starts from the run's first frame), so frames fed one
    by one give the recorded run's trajectory, byte for byte."""
    models = Path(__file__).resolve().parents[1] / "models"
    cfg = ShgmConfig.model_validate({"perception": {"depth_model": str(models / "demo_depth.onnx"),
                                                    "seg_model": str(models / "demo_seg.onnx")}})  # fmt: skip
    seq = open_sequence(tiny_scenario / "car1")
    recorded = run({"car1": seq}, tmp_path / "recorded", config=cfg)
    with LiveRun({"car1": seq.intrinsics}, tmp_path / "live", config=cfg) as live:
        for f in seq:
            live.add_frame("car1", f.image_rgb, f.timestamp_s, T_world_cam=f.T_world_cam)
    name = "car1_odometry_tum.txt"
    assert (recorded.out_dir / name).read_bytes() == (tmp_path / "live" / name).read_bytes()
    assert recorded.robots[0].keyframes > 5


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"timestamp_s": None}, "not a finite time"),
        ({"timestamp_s": "soon"}, "not a finite time"),
        ({"T_world_cam": np.eye(3)}, r"give a \(4, 4\)"),
        ({"T_world_cam": np.diag([2.0, 1.0, 1.0, 1.0])}, "not a rigid transform"),
        ({"T_odom_cam": np.full((4, 4), np.nan)}, "frame 0: T_odom_cam is not finite"),
        ({"T_odom_cam": np.zeros(16)}, r"T_odom_cam is float64 \(16,\); give a \(4, 4\) camera -> odometry"),
        ({"image_rgb": np.zeros((4, 8, 3), np.float32)}, "uint8"),
        ({"label_ids": np.full((4, 8), 300, np.int32)}, "outside 0-255"),
    ],
)
def test_a_malformed_frame_is_a_data_error_naming_it(change: dict, message: str) -> None:
    stream = FrameStream(Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4), name="cam")
    good = {"image_rgb": np.zeros((4, 8, 3), np.uint8), "timestamp_s": 0.0, "label_ids": np.zeros((4, 8), np.uint8),
            "T_world_cam": np.eye(4)}  # fmt: skip
    with pytest.raises(DataError, match=message):
        stream.append(**{**good, **change})
    assert len(stream) == 0
    stream.append(**good)
    assert len(stream) == 1 and stream.gt_poses.shape == (1, 4, 4) and stream.odometry_poses is None
    with pytest.raises(DataError, match="T_odom_cam given, but the first frame had none"):
        stream.append(**{**good, "timestamp_s": 0.1, "T_odom_cam": np.eye(4)})


@pytest.mark.parametrize("scale", [1e3, 1e9, 1e-4])
def test_times_not_in_seconds_are_refused_once_a_few_frames_show_it(scale: float) -> None:
    stream = FrameStream(Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4), name="cam")
    image = np.zeros((4, 8, 3), np.uint8)
    for k in range(3):
        stream.append(image, 0.1 * k * scale)
    with pytest.raises(DataError, match=r"frame 3: frames are .* apart \(median\).*must be in seconds"):
        stream.append(image, 0.3 * scale)
    assert len(stream) == 3


def test_a_camera_that_pauses_once_is_not_taken_for_wrong_units() -> None:
    stream = FrameStream(Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4), name="cam")
    for t in (0.0, 0.1, 90.0, 90.1, 90.2, 600.0, 600.1):
        stream.append(np.zeros((4, 8, 3), np.uint8), t)
    assert len(stream) == 7


def test_a_robots_own_odometry_given_with_its_frames_is_run_as_its_odometry(tiny_scenario: Path, tmp_path: Path,
                                                                            caplog) -> None:  # fmt: skip
    """car2's frames come with its own odometry (here its ground truth moved into another frame): with the default
    configuration the robot runs it (``auto`` chooses ``given``), and the files are those of a recorded run on
    ground-truth odometry; asked for ``given`` without it, the run ends with a clear error."""
    sequences = {n: open_sequence(tiny_scenario / n) for n in NAMES}
    gt = ShgmConfig.model_validate({"robots": {"car2": {"odometry": {"kind": "gt"}}}})
    recorded = run(sequences, tmp_path / "recorded", config=gt)
    T_elsewhere = np.eye(4)
    T_elsewhere[:3, 3] = [100.0, -20.0, 3.0]  # the robot's odometry frame is not the world's
    with caplog.at_level("INFO"), LiveRun({n: s.intrinsics for n, s in sequences.items()}, tmp_path / "live") as live:
        for robot, i in interleave(sequences):
            f = sequences[robot][i]
            own = T_elsewhere @ f.T_world_cam if robot == "car2" else None
            live.add_frame(robot, f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                           T_world_cam=f.T_world_cam, T_odom_cam=own)  # fmt: skip
    assert "car2: odometry given (auto: the frames come with the robot's own odometry" in caplog.text
    for name in ("car1_odometry_tum.txt", "car2_odometry_tum.txt", "car2_fused_tum.txt", "car2_gt_tum.txt"):
        assert (recorded.out_dir / name).read_bytes() == (tmp_path / "live" / name).read_bytes(), name

    f = sequences["car1"][0]
    given = ShgmConfig.model_validate({"odometry": {"kind": "given"}})
    live = LiveRun({"car1": f.intrinsics}, tmp_path / "refused", config=given)
    with pytest.raises(ConfigError, match=r"robot 'car1': odometry 'given' runs the robot's own odometry"):
        live.add_frame("car1", f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids)
    assert (tmp_path / "refused" / "incomplete.txt").is_file()


def test_a_camera_without_depth_or_model_ends_the_run_with_a_clear_error(tmp_path: Path) -> None:
    """Frames without depth and no depth model: refused at the first frame, naming the robot and the fix; the
    folder is marked incomplete and the run takes no more frames."""
    K = Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4)
    live = LiveRun({"car1": K}, tmp_path / "out")
    with pytest.raises(DataError, match=r"robot 'car1'.*no depth.*perception\.depth_model"):
        live.add_frame("car1", np.zeros((4, 8, 3), np.uint8), 0.0, label_ids=np.zeros((4, 8), np.uint8))
    assert (tmp_path / "out" / "incomplete.txt").is_file()
    with pytest.raises(ConfigError, match="ended with an error"):
        live.add_frame("car1", np.zeros((4, 8, 3), np.uint8), 0.1, label_ids=np.zeros((4, 8), np.uint8))


def test_a_stop_or_an_error_while_the_results_are_written_marks_the_folder(tiny_scenario: Path, tmp_path: Path,
                                                                            monkeypatch) -> None:  # fmt: skip
    """A Ctrl-C that landed while ``finish`` (or leaving the ``with`` block) wrote the results left a folder without
    metrics.json and without incomplete.txt (``eval`` measured the checkpoint as the run's results) and its lock
    held; so did an error (a full disk) in the finish that a Ctrl-C inside the block started."""
    from shgm_slam.api import read_fused
    from shgm_slam.io.export import LOCK_FILE, ResultsWriter

    seq = open_sequence(tiny_scenario / "car1")
    real = ResultsWriter.write_json

    def failing_at_metrics(error: BaseException):
        def write_json(self, name, data, **kwargs):
            if name == "metrics.json":
                raise error
            return real(self, name, data, **kwargs)

        return write_json

    stopped = LiveRun({"car1": seq.intrinsics}, tmp_path / "stopped")
    feed(stopped, {"car1": seq}, [("car1", i) for i in range(24)])
    monkeypatch.setattr(ResultsWriter, "write_json", failing_at_metrics(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        stopped.finish()
    monkeypatch.setattr(ResultsWriter, "write_json", real)
    marker = tmp_path / "stopped" / "incomplete.txt"
    assert "stopped while its results were being written" in marker.read_text()
    assert not (tmp_path / "stopped" / LOCK_FILE).exists()
    with pytest.raises(ConfigError, match="ended with an error"):
        stopped.finish()
    with pytest.raises(DataError, match="holds no results"):
        read_fused(tmp_path / "stopped", "car1")

    with pytest.raises(DataError, match="No space left"):
        with LiveRun({"car1": seq.intrinsics}, tmp_path / "full") as live:
            feed(live, {"car1": seq}, [("car1", i) for i in range(24)])
            monkeypatch.setattr(ResultsWriter, "write_json", failing_at_metrics(DataError("No space left on device")))
            raise KeyboardInterrupt
    assert "No space left" in (tmp_path / "full" / "incomplete.txt").read_text()
    assert not (tmp_path / "full" / LOCK_FILE).exists()


def test_a_live_run_refused_for_its_viewer_leaves_its_folder_free(tmp_path: Path, monkeypatch) -> None:
    """A LiveRun whose viewer could not start (no display to spawn one on) kept its folder locked: the next LiveRun
    on it in the same process was refused as "in use"."""
    from shgm_slam.viz import rerun_logger

    monkeypatch.setattr(rerun_logger, "_has_display", lambda: False)
    K = Intrinsics(100.0, 100.0, 16.0, 8.0, 32, 16)
    with pytest.raises(ConfigError, match="needs a display"):
        LiveRun({"car1": K}, tmp_path / "out", viewer=RerunMode.SPAWN)
    live = LiveRun({"car1": K}, tmp_path / "out")
    assert live.out_dir == tmp_path / "out"


def test_add_camera_refuses_a_name_that_differs_only_in_case(tiny_scenario: Path, tmp_path: Path) -> None:
    """``car1`` and ``CAR1`` were taken as two robots, whose files (``car1_fused_tum.txt``, ...) are one file on
    macOS or Windows; refused when the camera is added or named, nothing added."""
    K = open_sequence(tiny_scenario / "car1").intrinsics
    live = LiveRun({"car1": K}, tmp_path / "out")
    with pytest.raises(ConfigError, match="'car1' and 'CAR1' differ only in case"):
        live.add_camera("CAR1", K)
    assert list(live.streams) == ["car1"]
    with pytest.raises(ConfigError, match="differ only in case"):
        LiveRun({"uav": K, "UAV": K}, tmp_path / "named")


def test_add_camera_refuses_a_camera_the_pose_graph_has_no_agent_left_for(tiny_scenario: Path, tmp_path: Path,
                                                                          monkeypatch) -> None:  # fmt: skip
    """A robot alone may start all of the pose graph's agents as trajectory segments (its odometry failing);
    a camera added then was accepted and its first keyframe refused by the map server, a ProtocolError that ended
    the whole run. It is refused at ``add_camera`` (here with a pose graph of 4 agents) and the run goes on."""
    import shgm_slam.backend.keys as keys

    seq = open_sequence(tiny_scenario / "car1")
    live = LiveRun({"car1": seq.intrinsics}, tmp_path / "out")
    for i in range(len(seq)):
        f, T_odom_cam = seq[i], np.eye(4)
        T_odom_cam[0, 3] = 50.0 * (i // 3) + 0.5 * i  # a 50 m jump every third frame: a new segment each
        give = dict(depth_m=f.depth_m, label_ids=f.label_ids, T_odom_cam=T_odom_cam)
        live.add_frame("car1", f.image_rgb, f.timestamp_s, **give)
    monkeypatch.setattr(keys, "MAX_AGENTS", 4)
    with pytest.raises(ConfigError, match=r"camera 'car2' cannot be added: .* at most 4 agents .* started \d+ \(car1"):
        live.add_camera("car2", seq.intrinsics)
    assert list(live.streams) == ["car1"]
    assert [r.name for r in live.finish().robots] == ["car1"]


def test_a_camera_added_keeps_its_agents_while_the_running_robot_keeps_failing(tiny_scenario: Path, tmp_path: Path,
                                                                                monkeypatch) -> None:  # fmt: skip
    """The running robots kept the share of the pose graph they had before a camera was added, so one whose
    odometry kept failing could start every agent left before the newcomer's first keyframe, which the map server
    then refused, ending the whole run. Adding the camera shares the pose graph anew at once (here 16 agents: 8
    each): the failing robot stops at its share and the newcomer runs."""
    import shgm_slam.backend.keys as keys
    import shgm_slam.server.node as server_node

    for module in (keys, server_node):
        monkeypatch.setattr(module, "MAX_AGENTS", 16)
    car1, car2 = open_sequence(tiny_scenario / "car1"), open_sequence(tiny_scenario / "car2")
    live = LiveRun({"car1": car1.intrinsics}, tmp_path / "out")

    def give_car1(frames: range) -> None:
        for i in frames:
            f, T_odom_cam = car1[i], np.eye(4)
            T_odom_cam[0, 3] = 50.0 * (i // 3) + 0.5 * i  # a 50 m jump every third frame: a new segment each
            live.add_frame("car1", f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                           T_odom_cam=T_odom_cam)  # fmt: skip

    give_car1(range(21))  # (the first 20 frames set its settings, then it runs them)
    assert live.started and 1 < len(live._fleet.fronts["car1"].segments) < 8
    live.add_camera("car2", car2.intrinsics)
    give_car1(range(21, len(car1)))
    assert len(live._fleet.fronts["car1"].segments) == 8  # its share, not the 16 it was allowed alone
    for i in range(len(car2)):
        f = car2[i]
        live.add_frame("car2", f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids)
    reports = {r.name: r for r in live.finish().robots}
    assert reports["car2"].segments >= 1 and reports["car1"].segments == 8


@pytest.mark.parametrize("what", ["T_odom_cam", "T_world_cam"])
def test_poses_not_in_metres_are_refused_at_their_frame(what: str) -> None:
    """The robot's own odometry in millimetres cut every step as a failure; ground truth in millimetres ran to the
    end and reported the fused ATE in kilometres."""
    K = Intrinsics(100.0, 100.0, 4.0, 2.0, 8, 4)
    stream = FrameStream(K, name="cam")
    T = np.eye(4)
    for i in range(3):
        T[0, 3] = 1000.0 * i  # 1 m a frame, in millimetres
        stream.append(np.zeros((4, 8), np.uint8), 0.1 * i, depth_m=np.ones((4, 8), np.float32), **{what: T})
    T[0, 3] = 3000.0
    with pytest.raises(DataError, match=rf"'cam' frame 3: {what} moves at 1e\+04 m/s .*in millimetres"):
        stream.append(np.zeros((4, 8), np.uint8), 0.3, depth_m=np.ones((4, 8), np.float32), **{what: T})
    assert len(stream) == 3
