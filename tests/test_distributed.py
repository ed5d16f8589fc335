"""Robots and the map server as separate processes over Eclipse Zenoh on loopback (bounded in time):
the server finishes by itself, also when a robot or the server is killed mid-run and started again."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from shgm_slam.io.trajectories import read_tum

CLI = [sys.executable, "-m", "shgm_slam"]
TIMEOUT_S = 150


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


MATCH_OFTEN = "backend:\n  match_every_keyframes: 3\n"
"""The tiny world's cars meet once, briefly: matched every 3 keyframes they usually get the two independent
matches a robot needs to enter the shared frame during the run (every 10, the default, all find the same
objects and only the server's last look at the end places car2); which ones depends on the order in which
keyframes arrive, and the last look makes the end result independent of it."""


def _server(out: Path, port: int, *extra: str, expect: int = 2) -> subprocess.Popen:
    rerun = () if "--rerun" in extra else ("--rerun", "off")
    if "--config" not in extra:
        out.mkdir(parents=True, exist_ok=True)
        (config := out / "test-server.yaml").write_text(MATCH_OFTEN)
        extra = (*extra, "--config", str(config))
    return subprocess.Popen(
        [*CLI, "server", "--out", str(out), "--expect", str(expect), "--listen", f"tcp/127.0.0.1:{port}",
         "--reference", "car1", *rerun, *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip


def _robot(name: str, seq: Path, port: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [*CLI, "robot", f"{name}={seq}", "--connect", f"tcp/127.0.0.1:{port}", "--odometry", "gt",
         "--wait", "90", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip


def _wait(p: subprocess.Popen, what: str) -> str:
    try:
        out, _ = p.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate()
        pytest.fail(f"{what} did not finish within {TIMEOUT_S} s:\n{out[-3000:]}")
    assert p.returncode == 0, f"{what} exited {p.returncode}:\n{out[-3000:]}"
    return out


def _check_results(out: Path, tiny_scenario: Path) -> dict:
    s = json.loads((out / "server.json").read_text())
    assert s["finished"]
    assert set(s["robots"]) == {"car1", "car2"}
    assert all(r["done"] for r in s["robots"].values())
    assert "car2" in s["robots"]["car2"]["placed"]
    _, T = read_tum(out / "car2_fused_tum.txt")
    gt = np.loadtxt(tiny_scenario / "car2" / "poses.txt").reshape(-1, 3, 4)
    gt0 = np.vstack([np.loadtxt(tiny_scenario / "car1" / "poses.txt").reshape(-1, 3, 4)[0], [0, 0, 0, 1]])
    assert len(T) == len(gt)
    gt_shared = np.linalg.inv(gt0)[None] @ np.concatenate([gt, np.tile([[[0, 0, 0, 1.0]]], (len(gt), 1, 1))], 1)
    err = np.linalg.norm(T[:, :3, 3] - gt_shared[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(err**2)) < 2.0, err
    for f in ("matches.json", "pose_graph.g2o", "config.yaml", "car1_fused_tum.txt", "journal.bin"):
        assert (out / f).exists(), f
    return s



def test_server_and_two_robot_processes_finish_and_fuse(tiny_scenario: Path, tmp_path: Path) -> None:
    port = _free_port()
    robots = [_robot("car2", tiny_scenario / "car2", port)]  # a robot may start before the server
    time.sleep(0.5)
    server = _server(tmp_path, port)
    robots.append(_robot("car1", tiny_scenario / "car1", port))
    _wait(server, "server")
    for r in robots:
        _wait(r, "robot")
    s = _check_results(tmp_path, tiny_scenario)
    assert s["traffic"]["bytes_per_keyframe"] < 5000
    assert s["traffic"]["refused"] == 0


def _wait_for_keyframes(out: Path, server: subprocess.Popen, robot: str, nbytes: int = 20_000) -> None:
    """Until the server journal has grown (keyframes arrived) and holds messages of ``robot``, bounded."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        j = out / "journal.bin"
        if j.exists() and j.stat().st_size > nbytes and j.read_bytes().count(robot.encode()) >= 3:
            return
        assert server.poll() is None, server.communicate()[0][-3000:]
        time.sleep(0.2)
    pytest.fail(f"no keyframes of {robot} arrived in 60 s")


def _wait_for_server(out: Path, server: subprocess.Popen) -> None:
    """Until the server listens and has subscribed (it writes ``config.yaml`` then), bounded: a robot with a short
    ``--wait`` started next to it gives up before a server that starts slowly (a loaded machine) is there."""
    deadline = time.monotonic() + TIMEOUT_S
    while not (out / "config.yaml").is_file():
        assert server.poll() is None, server.communicate()[0][-3000:]
        assert time.monotonic() < deadline, f"the server did not start within {TIMEOUT_S} s"
        time.sleep(0.1)


def test_robot_killed_mid_run_and_restarted_resumes(tiny_scenario: Path, tmp_path: Path) -> None:
    port = _free_port()
    server = _server(tmp_path, port)
    car1 = _robot("car1", tiny_scenario / "car1", port)
    car2 = _robot("car2", tiny_scenario / "car2", port, "--realtime")
    _wait_for_keyframes(tmp_path, server, "car2")
    os.kill(car2.pid, signal.SIGKILL)
    car2.communicate()
    car2 = _robot("car2", tiny_scenario / "car2", port)
    _wait(server, "server")
    for r in (car1, car2):
        _wait(r, "robot")
    _check_results(tmp_path, tiny_scenario)


def test_server_killed_mid_run_and_restarted_recovers(tiny_scenario: Path, tmp_path: Path) -> None:
    config = tmp_path / "snapshots.yaml"
    config.write_text(MATCH_OFTEN + "server:\n  snapshot_every_messages: 10\n")  # snapshots this short run does reach
    out_dir = tmp_path / "out"
    port = _free_port()
    server = _server(out_dir, port, "--config", str(config))
    robots = [_robot(n, tiny_scenario / n, port, "--realtime") for n in ("car1", "car2")]
    _wait_for_keyframes(out_dir, server, "car1")
    os.kill(server.pid, signal.SIGKILL)
    server.communicate()
    assert list(out_dir.glob("snapshot-*.bin"))
    time.sleep(1.0)
    server = _server(out_dir, port, "--config", str(config))
    out = _wait(server, "restarted server")
    for r in robots:
        _wait(r, "robot")
    s = _check_results(out_dir, tiny_scenario)
    assert s["recovery"]["snapshot_records"] > 0, out[-2000:]  # from a snapshot, then the journal after it
    assert "resumed from its journal" in " ".join(out.split())  # and it said so when it started


def test_stale_robot_resumes_and_bad_input_and_name_clash_are_refused(tiny_scenario: Path, tmp_path: Path) -> None:
    from shgm_slam.transport.factory import NodeRole, make_transport
    from shgm_slam.transport.keys import hello_key, keyframe_key

    port = _free_port()
    server = _server(tmp_path, port, "--stale-after", "1.5")
    car1 = [_robot("car1", tiny_scenario / "car1", port, "--realtime") for _ in range(2)]  # one name, two processes
    car2 = _robot("car2", tiny_scenario / "car2", port, "--realtime")
    _wait_for_keyframes(tmp_path, server, "car2", 3_000)
    os.kill(car2.pid, signal.SIGSTOP)  # silent for longer than --stale-after
    with make_transport(NodeRole.ROBOT, f"tcp/127.0.0.1:{port}") as stranger:
        for _ in range(3):  # the first may go out before the stranger is connected
            time.sleep(0.5)
            stranger.publish(keyframe_key("car2"), b"\x00garbage")
            stranger.publish(hello_key("car9"), msgpack.packb({"v": 99, "k": 1, "r": "car9", "s": "x", "n": 1}))
        time.sleep(2.0)
    os.kill(car2.pid, signal.SIGCONT)
    server_out = _wait(server, "server")
    _wait(car2, "robot car2")
    outs = []
    for p in car1:
        out, _ = p.communicate(timeout=TIMEOUT_S)
        outs.append((p.returncode, out))
    assert sorted(rc for rc, _ in outs) == [0, 2], outs  # the newcomer was refused and told
    assert any("in use by another running robot" in " ".join(out.split()) for rc, out in outs if rc == 2), outs
    s = _check_results(tmp_path, tiny_scenario)
    assert s["robots"]["car2"]["went_stale"] >= 1 and s["robots"]["car2"]["done"], server_out  # kept, resumed
    reasons = " ".join(s["traffic"]["refusal_reasons"])
    assert "msgpack" in reasons and "version 99" in reasons and "in use" in reasons, reasons


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # a streamed collection has none
def test_live_view_streams_to_a_viewer_while_robots_run(tiny_scenario: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    from shgm_slam.viz.rerun_logger import viewer_reachable

    def collector_up() -> bool:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not viewer_reachable("127.0.0.1", view_port, 1.0):
            time.sleep(0.3)
        return viewer_reachable("127.0.0.1", view_port, 1.0)

    port, view_port = _free_port(), _free_port()
    live = tmp_path / "live.rrd"
    # its own process group: the `rerun` launcher runs the collector as a child, and both must stop
    viewer = subprocess.Popen([str(Path(sys.executable).parent / "rerun"), "--save", str(live), "--port",
                               str(view_port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)  # fmt: skip
    try:
        assert collector_up(), "the headless Rerun collector did not start"
        config = tmp_path / "single.yaml"  # car2 placed by its first match: what is streamed, not when
        config.write_text(MATCH_OFTEN + "  min_closures_to_anchor: 1\n")
        server = _server(tmp_path / "out", port, "--rerun", "connect", "--rerun-url",
                         f"rerun+http://127.0.0.1:{view_port}/proxy", "--config", str(config))  # fmt: skip
        deadline = time.monotonic() + 60
        while not (live.is_file() and live.stat().st_size) and time.monotonic() < deadline:
            time.sleep(0.2)  # the server is up and connected to the viewer (its blueprint arrived)
        robots = [_robot(n, tiny_scenario / n, port, "--realtime") for n in ("car1", "car2")]
        streamed_while_running = False
        while any(r.poll() is None for r in robots) and not streamed_while_running:
            streamed_while_running = live.is_file() and live.stat().st_size > 50_000
            time.sleep(0.2)
        assert streamed_while_running, "nothing reached the viewer before the robots finished"
        _wait(server, "server")
        for r in robots:
            _wait(r, "robot")
    finally:
        os.killpg(viewer.pid, signal.SIGINT)  # Ctrl-C to the launcher and the collector: it closes the file
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(viewer.pid, signal.SIGKILL)
            viewer.wait()
    chunks = list(RrdReader(live).stream().to_chunks())

    def rows(entity: str) -> int:  # the entity and its stretches (``.../odometry/<chunk>``)
        return sum(c.to_record_batch().num_rows for c in chunks
                   if c.entity_path.endswith(entity) or f"{entity}/" in c.entity_path)  # fmt: skip

    assert rows("car1/trajectory/odometry") >= 3  # logged as its keyframes came in (every second), not once
    assert rows("car2/trajectory/fused") >= 1  # and the fused map once car2 was placed


def test_bad_endpoint_is_a_clear_error(tmp_path: Path) -> None:
    p = subprocess.run([*CLI, "server", "--out", str(tmp_path), "--listen", "127.0.0.1:7447", "--rerun", "off"],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert p.returncode == 2, p.stdout + p.stderr
    assert "Traceback" not in p.stdout + p.stderr
    assert "tcp/" in p.stdout + p.stderr  # says what an endpoint looks like


def test_robot_without_a_server_says_so_and_exits_nonzero(tiny_scenario: Path) -> None:
    port = _free_port()
    p = subprocess.run([*CLI, "robot", f"car1={tiny_scenario / 'car1'}:0-8", "--connect", f"tcp/127.0.0.1:{port}",
                        "--odometry", "gt", "--wait", "1"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert p.returncode == 3, p.stdout + p.stderr
    assert "did not acknowledge" in p.stdout + p.stderr


def test_a_robot_that_leaves_before_the_server_finishes_and_a_stopped_server_say_so(
    tiny_scenario: Path, tmp_path: Path
) -> None:
    """The robot said "placed: not placed" and exited 0 while the server still waited for --expect robots;
    the stopped server's folder looked like a finished run's."""
    port = _free_port()
    server = _server(tmp_path / "out", port, expect=3)
    _wait_for_server(tmp_path / "out", server)  # --wait counts from the robot's last frame, not the server's start
    p = subprocess.run([*CLI, "robot", f"car1={tiny_scenario / 'car1'}:0-8", "--connect", f"tcp/127.0.0.1:{port}",
                        "--odometry", "gt", "--wait", "5", "--out", str(tmp_path / "car1")],
                       capture_output=True, text=True, timeout=TIMEOUT_S)  # fmt: skip
    assert p.returncode == 4, p.stdout + p.stderr
    assert "had not finished" in " ".join(p.stdout.split())
    assert (tmp_path / "car1" / "car1_odometry_tum.txt").is_file()
    server.send_signal(signal.SIGTERM)
    out, _ = server.communicate(timeout=TIMEOUT_S)
    assert server.returncode == 130, out[-2000:]
    said = " ".join(out.split())  # it said who came while it waited for the others
    assert "car1: connected (1 of 3 robots expected)" in said and "car1: sent its last keyframe" in said
    s = json.loads((tmp_path / "out" / "server.json").read_text())
    assert s["interrupted"] is True  # "finished": its results are written, after the stop


def test_a_robot_fed_frame_by_frame_joins_the_fleet(tiny_scenario: Path, tmp_path: Path) -> None:
    """``LiveRobot``: car2's frames given one by one in this process (as its camera would give them), car1 a
    ``shgm-slam robot`` process: the server places car2 as for a recorded robot, and car2's own poses say so."""
    from shgm_slam import open_sequence
    from shgm_slam.config import ShgmConfig
    from shgm_slam.live import LiveRobot

    port = _free_port()
    server = _server(tmp_path, port)
    car1 = _robot("car1", tiny_scenario / "car1", port)
    seq = open_sequence(tiny_scenario / "car2")
    cfg = ShgmConfig.model_validate({"odometry": {"kind": "gt"}})
    poses = []
    with LiveRobot("car2", seq.intrinsics, config=cfg, connect=f"tcp/127.0.0.1:{port}", out=tmp_path / "car2",
                   wait_s=90) as robot:  # fmt: skip
        for f in seq:
            poses += robot.add_frame(f.image_rgb, f.timestamp_s, depth_m=f.depth_m, label_ids=f.label_ids,
                                     T_world_cam=f.T_world_cam)  # fmt: skip
            robot.poll(timeout_s=0.01)
        summary = robot.finish()
    _wait(car1, "robot car1")
    _wait(server, "server")
    _check_results(tmp_path, tiny_scenario)
    assert [p.index for p in poses] == list(range(len(seq)))
    assert summary.acknowledged and summary.server_finished and summary.placed_agents == ["car2"]
    assert summary.frames == summary.frames_processed == len(seq)
    times, T = read_tum(tmp_path / "car2" / "car2_fused_tum.txt")
    assert len(T) == len(seq)
    now_times, T_now = robot.trajectory()  # the written fused trajectory is the robot's estimate at its end
    np.testing.assert_allclose(now_times, times, atol=1e-6)
    np.testing.assert_allclose(T_now[:, :3, 3], T[:, :3, 3], atol=1e-4)
