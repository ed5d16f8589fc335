"""RerunLogger writes the documented entity tree (read back from an .rrd); NullLogger does nothing."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from shgm_slam.errors import ConfigError, DataError
from shgm_slam.geometry.se3 import make_pose, rot_y
from shgm_slam.labels import Label
from shgm_slam.types import GraphArrays, Intrinsics
from shgm_slam.viz.rerun_logger import (
    MATCH_ACCEPTED_RGB,
    MATCH_REJECTED_RGB,
    LogLevel,
    NullLogger,
    RerunLogger,
    RerunMode,
    Viz,
    depth_to_mm_u16,
    make_viz,
    node_radius_m,
    series_color,
)

ROBOTS = ["robot_a", "robot_b"]
INTR = Intrinsics(fx=40.0, fy=40.0, cx=31.5, cy=11.5, width=64, height=24)


@pytest.fixture(autouse=True)
def strict_rerun():
    """Bad logging calls raise instead of warning (restored afterwards)."""
    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)


def _graph(rng: np.random.Generator, n: int = 6) -> GraphArrays:
    edges = np.array([[i, i + 1] for i in range(n - 1)], dtype=np.int64)
    return GraphArrays(
        np.arange(10, 10 + n), rng.choice([Label.BUILDING, Label.POLE, Label.CAR], n).astype(np.int64),
        rng.uniform(-20, 20, (n, 3)), rng.uniform(100, 50_000, n), edges,
    )  # fmt: skip


def _log_everything(viz: Viz, num_frames: int = 3, num_points: int = 500) -> dict:
    """Drive every method of ``viz`` with small synthetic data; returns what was logged last."""
    rng = np.random.default_rng(0)
    viz.setup(dict.fromkeys(ROBOTS, INTR))
    last: dict = {}
    for k in range(num_frames):
        for i, robot in enumerate(ROBOTS):
            T = make_pose(rot_y(0.1 * k), np.array([i * 5.0, 0.0, 2.0 * k]))
            rgb = rng.integers(0, 255, (INTR.height, INTR.width, 3), dtype=np.uint8)
            depth = rng.uniform(1, 30, (INTR.height, INTR.width)).astype(np.float32)
            depth[0, 0] = np.nan
            labels = rng.integers(0, 19, (INTR.height, INTR.width)).astype(np.uint8)
            labels[0, :] = 255
            pts = rng.normal(size=(num_points, 3))
            pts_labels = rng.integers(0, 19, num_points)
            viz.set_time(robot, k, 0.1 * k)
            viz.log_frame(robot, T, rgb, depth, labels, pts, pts_labels)
            viz.log_frame(robot, T, None, None, None)  # everything optional
            viz.log_timings(robot, {"odometry": 10.0 + k, "graph": 2.0})
            viz.log_error(robot, 0.5 * k + i)
            traj = rng.normal(size=(k + 2, 3))
            viz.log_trajectories(robot, traj, traj + 0.1)
            graph = _graph(rng)
            viz.log_graph(robot, graph)
            last[robot] = {"T": T, "points": pts, "point_labels": pts_labels, "graph": graph}
    pa, pb = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    viz.log_matches("robot_a", "robot_b", pa, pb, True, 4, 0.8)
    viz.log_matches("robot_b", "robot_a", pb[:2], pa[:2], False, num_inliers=1)
    viz.log_text("robot_a<->robot_b: accepted", LogLevel.INFO)
    viz.log_text("plain string level", "WARN")
    viz.log_scalar("closures_accepted", 1.0)
    viz.log_scalar("/metrics/ate_m", 0.5)
    viz.close()
    return last


def _read(path: Path) -> dict[str, list]:
    """Entity path -> list of pyarrow record batches of its chunks."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches: list, column: str) -> list:
    """All logged values of ``column`` across the chunks of an entity, in chunk order."""
    return [v for rb in batches if column in rb.schema.names for v in rb.column(column).to_pylist()]


def _last(batches: list, column: str):
    """Last logged value of ``column`` (a pyarrow list scalar, as python) across the chunks of an entity."""
    rows = [(rb.column("step")[i].as_py(), rb.column(column)[i].as_py())
            for rb in batches if column in rb.schema.names and "step" in rb.schema.names
            for i in range(rb.num_rows)]  # fmt: skip
    return max(rows, key=lambda r: r[0])[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[dict[str, list], dict, Path]:
    rr.set_strict_mode(True)
    path = tmp_path_factory.mktemp("viz") / "sub" / "run.rrd"
    viz = make_viz(RerunMode.SAVE, robots=ROBOTS, save_path=path, recording_id="test-run")
    assert isinstance(viz, RerunLogger)
    viz.max_cloud_points = 200
    last = _log_everything(viz, num_points=500)
    return _read(path), last, path


def test_recording_has_the_documented_entity_tree(recording):
    entities, _, path = recording
    recs = RrdReader(path).recordings()
    assert [(r.application_id, r.recording_id) for r in recs] == [("shgm_slam", "test-run")]
    ok, bad = "/world/matches/robot_a__robot_b/accepted", "/world/matches/robot_a__robot_b/rejected"
    expected = {"/world", "/log", "/metrics/closures_accepted", "/metrics/ate_m",
                ok, f"{ok}/nodes", bad, f"{bad}/nodes"}  # fmt: skip
    for r in ROBOTS:
        expected |= {f"/world/{r}/cam", f"/world/{r}/cam/rgb", f"/world/{r}/cam/depth", f"/world/{r}/cam/seg",
                     f"/world/{r}/cloud", f"/world/{r}/trajectory/odometry/0", f"/world/{r}/trajectory/fused/0",
                     f"/world/{r}/graph/nodes/0", f"/world/{r}/graph/edges/0",
                     f"/timings/{r}/odometry", f"/timings/{r}/graph"}  # fmt: skip
    missing = expected - set(entities)
    assert not missing, f"missing entities: {sorted(missing)}"
    cam_cols = {c for rb in entities["/world/robot_a/cam"] for c in rb.schema.names}
    timelines = {"frame", "step", "sensor_time"}
    assert timelines | {"Pinhole:image_from_camera", "Transform3D:translation"} <= cam_cols
    assert "AnnotationContext:context" in {c for rb in entities["/world"] for c in rb.schema.names}


def test_logged_values_match_inputs(recording):
    entities, last, _ = recording
    for r in ROBOTS:
        T = last[r]["T"]
        # the later log_frame(robot, T, None...) re-logged the same pose: the last one is T
        assert np.allclose(_last(entities[f"/world/{r}/cam"], "Transform3D:translation"), T[:3, 3])
        assert np.allclose(
            np.array(_last(entities[f"/world/{r}/cam"], "Transform3D:mat3x3")).reshape(3, 3, order="F"),
            T[:3, :3],
            atol=1e-6,
        )
        # cloud: stride-subsampled to max_cloud_points (500 -> every 3rd point = 167), labels follow points
        pos = np.array(_last(entities[f"/world/{r}/cloud"], "Points3D:positions"))
        cls = np.array(_last(entities[f"/world/{r}/cloud"], "Points3D:class_ids"))
        assert pos.shape == (167, 3)
        assert np.allclose(pos, last[r]["points"][::3], atol=1e-5)
        assert np.array_equal(cls, last[r]["point_labels"][::3])
        graph = last[r]["graph"]
        nodes = entities[f"/world/{r}/graph/nodes/0"]
        assert np.allclose(_last(nodes, "Points3D:positions"), graph.positions_xyz, atol=1e-4)
        assert np.allclose(_last(nodes, "Points3D:radii"), node_radius_m(graph.sizes), atol=1e-5)
        assert _last(nodes, "node_id") == graph.node_ids.tolist()
        strips = np.array(_last(entities[f"/world/{r}/graph/edges/0"], "LineStrips3D:strips"))
        assert strips.shape == (graph.num_edges, 2, 3)
        assert np.allclose(strips, graph.positions_xyz[graph.edges], atol=1e-4)


def _rgba(packed: int) -> tuple[int, int, int]:
    return ((packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255)


def test_matches_are_green_when_accepted_and_red_when_rejected(recording):
    entities, _, _ = recording
    ok = entities["/world/matches/robot_a__robot_b/accepted"]
    bad = entities["/world/matches/robot_a__robot_b/rejected"]  # robot_b's query: the pair's one entity
    assert _rgba(_last(ok, "LineStrips3D:colors")[0]) == MATCH_ACCEPTED_RGB
    assert _rgba(_last(bad, "LineStrips3D:colors")[0]) == MATCH_REJECTED_RGB
    assert len(_last(ok, "LineStrips3D:strips")) == 4
    assert _last(ok, "num_inliers") == [4]
    assert "4 inliers" in _last(ok, "LineStrips3D:labels")[0]


def test_text_and_series(recording):
    entities, _, _ = recording
    log = entities["/log"]
    assert _column(log, "TextLog:text") == [["robot_a<->robot_b: accepted"], ["plain string level"]]
    assert _column(log, "TextLog:level") == [["INFO"], ["WARN"]]
    values = _column(entities["/timings/robot_a/odometry"], "Scalars:scalars")
    assert values == [[10.0], [11.0], [12.0]]  # one value per frame, robots do not collide
    assert _column(entities["/metrics/error_m/robot_b"], "Scalars:scalars") == [[1.0], [1.5], [2.0]]
    names = _column(entities["/metrics/error_m/robot_a"], "SeriesLines:names")
    assert names == [["robot_a"]]  # the series is named after its robot (and drawn in its colour)


def _floats(array) -> np.ndarray:
    """Every floating-point value inside a pyarrow array (lists and structs flattened)."""
    import pyarrow as pa

    t = array.type
    if pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        return _floats(array.flatten())
    if pa.types.is_struct(t):
        return np.concatenate([_floats(array.field(i)) for i in range(t.num_fields)] or [np.zeros(0)])
    if pa.types.is_floating(t):
        return array.to_numpy(zero_copy_only=False).astype(np.float64)
    return np.zeros(0)


def test_no_logged_value_is_nan_or_infinite(recording):
    """A match without a score was stored with score NaN (and an unknown inlier count as -1)."""
    entities, _, _ = recording
    for entity, batches in entities.items():
        for rb in batches:
            for name in rb.schema.names:
                values = _floats(rb.column(name))
                assert np.isfinite(values).all(), (entity, name)
    rejected = entities["/world/matches/robot_a__robot_b/rejected"]
    assert not any(_column(rejected, "score")) and _column(rejected, "num_inliers") == [[1]]  # no score: none stored


def test_depth_is_stored_as_millimetres_with_invalid_zero(recording):
    depth_m = np.array([[0.0, 1.25, np.nan, np.inf, -1.0, 65.5, 70.0]], dtype=np.float32)
    assert depth_to_mm_u16(depth_m).tolist() == [[0, 1250, 0, 0, 0, 65500, 0]]
    entities, _, _ = recording
    assert _last(entities["/world/robot_a/cam/depth"], "DepthImage:meter") == [1000.0]


def test_series_colors_differ_between_robots():
    stage = np.array([31, 119, 180], dtype=np.uint8)
    colors = {tuple(series_color(stage, i)) for i in range(5)}
    assert len(colors) == 5
    assert tuple(series_color(stage, 0)) == (31, 119, 180)


def test_null_logger_accepts_every_call_and_creates_nothing(tmp_path):
    viz = make_viz(RerunMode.OFF, robots=ROBOTS, save_path=tmp_path / "never.rrd")
    assert isinstance(viz, NullLogger)
    _log_everything(viz, num_frames=1)
    assert list(tmp_path.iterdir()) == []


def test_both_loggers_implement_the_whole_protocol():
    protocol = {n for n, _ in inspect.getmembers(Viz, inspect.isfunction) if not n.startswith("_")}
    assert {"setup", "set_time", "log_frame", "log_trajectories", "log_graph", "log_matches", "log_text",
            "log_timings", "log_scalar", "log_error", "close"} <= protocol  # fmt: skip
    for cls in (RerunLogger, NullLogger):
        for name in protocol:
            assert (
                inspect.signature(getattr(cls, name)).parameters.keys()
                == inspect.signature(getattr(Viz, name)).parameters.keys()
            ), (cls, name)


def test_bad_input_raises_data_error(tmp_path):
    viz = make_viz(RerunMode.SAVE, robots=ROBOTS, save_path=tmp_path / "bad.rrd")
    viz.setup(dict.fromkeys(ROBOTS, INTR))
    viz.set_time("robot_a", 0, 0.0)
    with pytest.raises(DataError, match="points_shared"):
        viz.log_frame("robot_a", np.eye(4), None, None, None, np.zeros((5, 2)))
    with pytest.raises(DataError, match="point_labels"):
        viz.log_frame("robot_a", np.eye(4), None, None, None, np.zeros((5, 3)), np.zeros(4))
    with pytest.raises(DataError, match="T_shared_cam"):
        viz.log_frame("robot_a", np.eye(3), None, None, None)
    with pytest.raises(DataError, match="pair up"):
        viz.log_matches("robot_a", "robot_b", np.zeros((3, 3)), np.zeros((2, 3)), True)
    viz.close()


def test_make_viz_mode_errors(tmp_path, monkeypatch):
    with pytest.raises(ConfigError, match="--rerun save"):
        make_viz(RerunMode.SAVE, robots=ROBOTS)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ConfigError, match="--rerun save"):
        make_viz(RerunMode.SPAWN, robots=ROBOTS)
    with pytest.raises(ValueError):
        RerunMode("sideways")
    assert RerunMode("save") is RerunMode.SAVE


def test_both_robots_queries_draw_one_pair_with_one_label(tmp_path):
    """car2's query against car1 and car1's against car2 were two entities with their labels on top of each other
    (three robots: six labels where three pairs meet); now one per pair, named in the robots' display order."""
    path = tmp_path / "pairs.rrd"
    viz = make_viz(RerunMode.SAVE, robots=["car1", "car2"], save_path=path)
    pa, pb = np.zeros((2, 3)), np.ones((2, 3))
    viz.log_matches("car2", "car1", pb, pa, True, 2)
    viz.log_matches("car1", "car2", pa, pb, True, 3)
    viz.log_matches("uav", "car1", pb, pa, False, 1)  # a robot the logger did not know joins the order after them
    viz.close()
    matches = {e for e in _read(path) if e.startswith("/world/matches/")}
    assert matches == {"/world/matches/car1__car2/accepted", "/world/matches/car1__car2/accepted/nodes",
                       "/world/matches/car1__car2/rejected", "/world/matches/car1__uav/rejected",
                       "/world/matches/car1__uav/rejected/nodes"}  # fmt: skip
    labels = _column(_read(path)["/world/matches/car1__car2/accepted"], "LineStrips3D:labels")
    assert labels == [["car1 ↔ car2, accepted, 2 inliers"], ["car1 ↔ car2, accepted, 3 inliers"]]


def test_robot_names_are_escaped_into_one_path_part(tmp_path):
    path = tmp_path / "odd.rrd"
    viz = make_viz(RerunMode.SAVE, robots=["car 1/left"], save_path=path)
    viz.setup({"car 1/left": INTR})
    viz.set_time("car 1/left", 0, 0.0)
    viz.log_frame("car 1/left", np.eye(4), None, None, None, np.zeros((3, 3)))
    viz.close()
    entities = _read(path)
    assert "/world/car\\ 1\\/left/cloud" in entities


def test_connect_without_a_viewer_saves_instead_and_does_not_hang(tmp_path, caplog):
    import socket
    import time

    from shgm_slam.viz.rerun_logger import NullLogger, RerunLogger, RerunMode, make_viz

    with socket.socket() as s:  # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    viz = make_viz(RerunMode.CONNECT, robots=["a"], save_path=tmp_path / "run.rrd",
                   connect_url=f"rerun+http://127.0.0.1:{port}/proxy")
    assert isinstance(viz, RerunLogger)
    viz.close()
    assert time.perf_counter() - t0 < 15.0
    assert (tmp_path / "run.rrd").is_file()
    assert "no Rerun viewer answers" in caplog.text
    assert isinstance(make_viz(RerunMode.CONNECT, robots=["a"], connect_url=f"rerun+http://127.0.0.1:{port}/proxy"),
                      NullLogger)


@pytest.mark.parametrize("url", ["localhost:9876", "rerun+http://[::1/proxy", "http://127.0.0.1/proxy", "nonsense"])
def test_a_malformed_viewer_url_is_a_config_error(url):
    from shgm_slam.viz.rerun_logger import RerunMode, make_viz

    with pytest.raises(ConfigError, match="rerun-url"):
        make_viz(RerunMode.CONNECT, robots=["a"], connect_url=url)


def test_saving_into_a_read_only_folder_is_a_config_error(tmp_path):
    import os

    from shgm_slam.viz.rerun_logger import RerunMode, make_viz

    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who can write anywhere (root)")
        with pytest.raises(ConfigError, match="cannot write the recording"):
            make_viz(RerunMode.SAVE, robots=["a"], save_path=ro / "run.rrd")
    finally:
        ro.chmod(0o700)


class _FakeServer:
    """A TCP server on a free local port that answers each connection with ``reply`` and then only reads."""

    def __init__(self, reply: bytes) -> None:
        import socket
        import threading

        self.reply = reply
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]
        self.conns: list = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        import threading

        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn) -> None:
        try:
            conn.sendall(self.reply)
            while conn.recv(65536):
                pass
        except OSError:
            pass

    @property
    def url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.port}/proxy"


@pytest.mark.parametrize("reply", [b"", b"HTTP/1.0 400 Bad Request\r\n\r\n"], ids=["silent", "web-server"])
def test_connect_to_something_that_is_not_a_viewer_saves_instead(tmp_path, caplog, reply):
    """A port that accepts TCP but is no gRPC server (a web server, a socket that never answers) is no viewer:
    streaming to it failed at the end of the run (RuntimeError) or blocked it for ever."""
    import time

    from shgm_slam.viz.rerun_logger import RerunLogger, RerunMode, make_viz

    server = _FakeServer(reply)
    t0 = time.perf_counter()
    viz = make_viz(RerunMode.CONNECT, robots=["a"], save_path=tmp_path / "run.rrd", connect_url=server.url)
    viz.close()
    assert isinstance(viz, RerunLogger) and viz.remote_url is None
    assert time.perf_counter() - t0 < 10.0
    assert (tmp_path / "run.rrd").is_file()
    assert "no Rerun viewer answers" in caplog.text


def test_closing_does_not_wait_for_a_viewer_that_stops_reading(tmp_path, caplog, monkeypatch):
    """A gRPC peer that takes the connection but never the data: close() warns and returns, never raises or hangs."""
    import time

    from shgm_slam.viz import rerun_logger
    from shgm_slam.viz.rerun_logger import RerunLogger, RerunMode, make_viz

    monkeypatch.setattr(rerun_logger, "FLUSH_TIMEOUT_S", 1.0)
    server = _FakeServer(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))  # an HTTP/2 SETTINGS frame, then silence
    viz = make_viz(RerunMode.CONNECT, robots=["a"], save_path=tmp_path / "run.rrd", connect_url=server.url)
    assert isinstance(viz, RerunLogger) and viz.remote_url == server.url
    points = np.random.default_rng(0).random((20_000, 3))
    for _ in range(20):
        viz.rec.log("world/cloud", rr.Points3D(points))
    t0 = time.perf_counter()
    viz.close()
    assert time.perf_counter() - t0 < 8.0
    assert "did not take" in caplog.text
    del viz  # dropping the stream must not wait for the viewer either


_LATER_RECORDINGS = """
import gc, sys
from pathlib import Path
import numpy as np, rerun as rr
from tests.viz.test_rerun_logger import _FakeServer
from shgm_slam.viz import default_blueprint, rerun_logger
from shgm_slam.viz.rerun_logger import RerunMode, make_viz
rerun_logger.FLUSH_TIMEOUT_S = 1.0
out = Path(sys.argv[1])
server = _FakeServer(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))
viz = make_viz(RerunMode.CONNECT, robots=["a"], save_path=out / "run.rrd", connect_url=server.url)
for _ in range(20):
    viz.rec.log("world/cloud", rr.Points3D(np.random.default_rng(0).random((20_000, 3))))
viz.close()
del viz
gc.collect()
for i in range(2):
    rec = rr.RecordingStream("later")
    rec.save(out / f"later{i}.rrd", default_blueprint=default_blueprint(["a", "b"]))
    rec.log("/world", rr.ViewCoordinates.RDF, static=True)
    rec.flush()
    rec.disconnect()
    del rec
    gc.collect()
print("done")
"""


def test_a_viewer_that_stopped_reading_never_blocks_a_later_recording(tmp_path):
    """Dropping any recording sweeps the process's orphaned streams and flushes them: once a stream to a viewer that
    stopped reading was given up, the next recording saved to a file (a later run in the same process, the blueprint
    stream that ``save`` drops) waited for that viewer for ever."""
    root = Path(__file__).resolve().parents[2]
    try:
        done = subprocess.run([sys.executable, "-c", _LATER_RECORDINGS, str(tmp_path)], cwd=root,
                              capture_output=True, text=True, timeout=60)  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail("a later recording waited for the viewer that stopped reading")
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-2000:]
    assert all((tmp_path / f"later{i}.rrd").stat().st_size > 0 for i in range(2))
