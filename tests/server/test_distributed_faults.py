"""Faults users of a distributed SLAM system run into: a robot that comes after the map server finished, a
server stopped (Ctrl-C, twice) while robots are connected, a server that is not there or goes silent, a
server started on a finished run's folder, keyframes acknowledged but not yet journaled when the server
dies, an empty endpoint. Nodes on the in-process bus with a fake clock, and a few ``shgm-slam`` processes
over Zenoh on loopback (free ports, bounded waits)."""

from __future__ import annotations

import json
import logging
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from shgm_slam.errors import ConfigError, DataError, ProtocolError
from shgm_slam.messages import RobotState
from shgm_slam.robot.node import SERVER_SILENT_S, RobotNode
from shgm_slam.runner import make_frontend
from shgm_slam.server import serve as serve_module
from shgm_slam.server.node import CLASH_WINDOW_S, ServerNode
from shgm_slam.server.serve import ServerView, _state_line
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.zenoh_transport import parse_endpoints
from tests.server.conftest import FakeClock, drive, finish, fresh

CLI = [sys.executable, "-m", "shgm_slam"]
TIMEOUT_S = 120


def _warnings(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and text in r.getMessage()]


def _journal_bytes(folder: Path) -> int:
    return (folder / "journal.bin").stat().st_size


def test_a_robot_that_comes_after_the_server_finished_is_refused_and_changes_nothing(robots, cfg, tmp_path) -> None:
    """With --expect 1 the server finishes once car1 is done, then lingers; car2 arriving then was acknowledged
    and told "finished" (its process exited 0, "placed: not placed"), while the results, written before, lacked it
    and its messages went into the finished run's journal."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=1, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    drive(server, nodes, {"car1": range(10)}, clock)
    finish(server, nodes, clock)
    journal, written = _journal_bytes(tmp_path), json.loads((tmp_path / "server.json").read_text())
    late = RobotNode(make_frontend("car2", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    late.hello()
    clock.t += 0.1
    server.poll()
    with pytest.raises(ProtocolError, match=r"has finished.*another --out"):
        for i in range(5):
            late.poll()
            late.step(i)
            server.poll()
    assert list(server.robots) == ["car1"]
    assert _journal_bytes(tmp_path) == journal
    assert server.summary()["robots"] == written["robots"]


def test_keyframes_after_a_stopped_server_finished_are_not_taken_and_the_robots_say_so(robots, cfg, tmp_path,
                                                                                      caplog) -> None:  # fmt: skip
    """Ctrl-C on the server: it writes its results and lingers; the robots, still running, used to have their next
    keyframes taken into the map and journal after the results were written (the printed summary said 15 keyframes,
    server.json 8), and went on without a word until --wait ran out."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    drive(server, nodes, {r: range(8) for r in nodes}, clock)
    server.interrupted = True
    server.finish()
    held = {a: server.map.received(a) for a in server.map.agents}
    journal, written = _journal_bytes(tmp_path), server.summary()["robots"]
    with caplog.at_level(logging.WARNING):
        drive(server, nodes, {r: range(8, 20) for r in nodes}, clock)
        for _ in range(4):
            clock.t += 0.5
            server.poll()
            for n in nodes.values():
                n.poll()
    assert {a: server.map.received(a) for a in server.map.agents} == held
    assert _journal_bytes(tmp_path) == journal
    assert server.summary()["robots"] == written
    said = _warnings(caplog, "finished before this robot was done")
    assert sorted(line.split(":")[0] for line in said) == ["car1", "car2"]  # each once, with what to do
    assert all("start it again on the same --out" in line for line in said)
    restarted = RobotNode(make_frontend("car2", robots["car2"], cfg), InProcessTransport(bus), clock=clock)
    clock.t += CLASH_WINDOW_S + 1
    restarted.hello()
    server.poll()
    with pytest.raises(ProtocolError, match=r"was stopped.*start it again on the same --out"):
        restarted.poll()


def test_a_robot_says_when_no_server_answers_when_one_does_and_when_it_goes_silent(robots, cfg, tmp_path,
                                                                                  caplog) -> None:  # fmt: skip
    """A robot whose --connect names an endpoint nobody listens on (or whose server was killed) ran every frame
    without a word, then waited --wait seconds and said only "did not acknowledge"."""
    clock, bus = FakeClock(), InProcessBus()
    robot = RobotNode(make_frontend("car1", robots["car1"], cfg), InProcessTransport(bus), clock=clock)
    robot.hello()
    with caplog.at_level(logging.WARNING):
        robot.step(0)
        clock.t += SERVER_SILENT_S + 1
        robot.poll()
        robot.poll()
        assert len(_warnings(caplog, "no map server has answered in")) == 1  # once, not every poll
        server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
        robot.hello()
        server.poll()
        robot.poll()
        assert _warnings(caplog, "the map server answers now")
        clock.t += SERVER_SILENT_S + 1  # killed: nothing more from it
        robot.poll()
        assert _warnings(caplog, "the map server has been silent for")
        assert not _warnings(caplog, "restarted")


@pytest.mark.parametrize("snapshot_every", [0, 1])
def test_a_killed_server_queues_again_the_keyframes_that_waited_for_their_turn(robots, cfg, tmp_path, caplog,
                                                                              snapshot_every) -> None:  # fmt: skip
    """With --expect 2 a robot's keyframes wait (acknowledged, not in the map, so not journaled) for the other robot;
    car1 left (exit 4 after --wait) and the server was killed: restarted, it held car1 "done" with 0 keyframes and
    waited for it for ever. ``queued.bin`` keeps them; the restarted server queues them again (also when it starts
    from a snapshot, which does not keep car1's first frame's time: the hello kept beside them gives it), and once
    car2 has run, car1's keyframes are in the map and the server finishes."""
    cfg = cfg.model_copy(deep=True)
    cfg.server.snapshot_every_messages = snapshot_every
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    drive(server, nodes, {"car1": range(10)}, clock)
    nodes["car1"].done()
    clock.t += 1.5
    server.poll()
    nodes["car1"].poll()
    made = nodes["car1"].keyframes_sent
    assert nodes["car1"].all_acknowledged() and server.map.received("car1") == 0  # queued for its turn only
    assert (tmp_path / "queued.bin").stat().st_size > 0 and made > 0
    assert bool(list(tmp_path.glob("snapshot-*.bin"))) == bool(snapshot_every)
    with caplog.at_level(logging.WARNING):
        restarted = ServerNode(cfg, InProcessTransport(bus := InProcessBus()), tmp_path, expect=2, clock=clock)
    assert not _warnings(caplog, "start robot car1 again")
    assert restarted.robots["car1"].done is not None and restarted.map.received("car1") == 0
    assert restarted.robots["car1"].complete(restarted.map, restarted._order.held)  # all of it queued again
    said: list[str] = []
    ServerView(RecordingViz(), say=said.append).recovered(restarted)
    assert said == [f"car1: recovered from the journal (0 keyframes, {made} more queued for their turn; it had sent "
                    "its last)"]  # fmt: skip
    car2 = fresh(robots, cfg, bus, clock, names=("car2",))
    drive(restarted, car2, {"car2": range(len(robots["car2"]))}, clock)
    finish(restarted, car2, clock)
    assert restarted.map.received("car1") == made
    assert (tmp_path / "queued.bin").stat().st_size == 0  # emptied once every keyframe it kept was in the map


def test_the_view_says_a_robot_started_again_and_robots_recovered_not_connected(robots, cfg, tmp_path) -> None:
    """The server printed nothing when a robot was killed and started again under its name, and a restarted server
    said "car1: connected" of every robot it recovered from its journal, before any had."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    said: list[str] = []
    view = ServerView(RecordingViz(), say=said.append)
    drive(server, nodes, {"car1": range(5)}, clock)
    view.update(server, [])
    clock.t += CLASH_WINDOW_S + 1
    fresh(robots, cfg, bus, clock, names=("car1",))  # the same name, a new process
    server.poll()
    view.update(server, [])
    assert said == ["car1: connected", "car1: started again (a new process); it goes on from the keyframes the "
                    "server holds"]  # fmt: skip
    said.clear()
    recovered = ServerNode(cfg, InProcessTransport(InProcessBus()), tmp_path, clock=clock)
    view = ServerView(RecordingViz(), say=said.append)
    view.recovered(recovered)
    view.update(recovered, [])
    assert said == [f"car1: recovered from the journal ({recovered.map.received('car1')} keyframes)"]


def test_a_robot_beyond_the_expected_ones_is_said_as_such() -> None:
    """With --expect 1 a second robot that connects while the first runs is waited for too: it was said as
    "car2: connected (2 of 1 robots expected)"."""
    assert _state_line("car2", RobotState.ACTIVE, 2, 1) == (
        "car2: connected (2 robots, 1 expected: the server waits for all 2)")
    assert _state_line("car1", RobotState.ACTIVE, 1, 3) == "car1: connected (1 of 3 robots expected)"


class RecordingViz:
    def __getattr__(self, name):
        return lambda *args, **kwargs: None


def _in_process(monkeypatch) -> None:
    monkeypatch.setattr(serve_module, "make_transport", lambda role, listen: InProcessTransport(InProcessBus()))
    monkeypatch.setattr(serve_module, "LINGER_S", 0.1)


def _serve(cfg, folder: Path, **options) -> serve_module.ServeSummary:
    """``serve`` on the in-process bus (``_in_process``); a stop that gets out of it fails the test (not pytest)."""
    try:
        return serve_module.serve(cfg, folder, **options)
    except KeyboardInterrupt:
        pytest.fail("a stop got out of serve: the server ended without its results written and said")


def _stop_at_once(monkeypatch) -> None:
    """Ctrl-C at the server loop's first poll; later polls (while it lingers) get nothing."""
    polls: list[ServerNode] = []

    def stopped(self, timeout_s: float = 0.0):
        polls.append(self)
        if polls.count(self) == 1:
            raise KeyboardInterrupt
        return []

    monkeypatch.setattr(ServerNode, "poll", stopped)


def _server_run(robots, cfg, folder: Path, *, stopped: bool = False) -> None:
    """A map server's folder (journal and results) of car1's first frames: finished (--expect 1), or ``stopped``."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), folder, expect=None if stopped else 1, clock=clock)
    nodes = fresh(robots, cfg, bus, clock, names=("car1",))
    drive(server, nodes, {"car1": range(4)}, clock)
    if stopped:
        server.interrupted = True
        server.finish()
    else:
        finish(server, nodes, clock)
    assert (folder / "journal.bin").is_file()


def test_a_finished_servers_folder_is_refused_and_a_stopped_ones_resumed(robots, cfg, tmp_path, monkeypatch) -> None:
    """A server started on the folder of a run that had finished replayed it: with --expect it finished at once,
    saying each old robot "connected" (the new run's robots then found no server); without, the new robots were
    taken for the old ones started again and their keyframes ignored up to the number the old ones sent."""
    _in_process(monkeypatch)
    _server_run(robots, cfg, tmp_path / "done")
    _server_run(robots, cfg, tmp_path / "stopped", stopped=True)
    _stop_at_once(monkeypatch)
    with pytest.raises(DataError, match=r"finished.*choose another --out, or pass --overwrite"):
        _serve(cfg, tmp_path / "done")
    assert _serve(cfg, tmp_path / "stopped").interrupted  # resumed (and stopped again)


def test_a_second_stop_while_a_stopped_server_writes_its_results_waits_for_them(cfg, tmp_path, monkeypatch,
                                                                                python_ctrl_c) -> None:  # fmt: skip
    """An impatient second Ctrl-C landed in the final matching of a stopped server: the process ended with one
    word ("interrupted"), the folder a checkpoint (server.json: not finished) and no summary. Then, said "not
    waiting for the robots' final corrections", it lingered for them all the same."""
    _in_process(monkeypatch)
    _stop_at_once(monkeypatch)
    original = ServerNode.finish
    lingered: list[float] = []

    def finish_stopped_again(self, *, match: bool = True):
        signal.raise_signal(signal.SIGINT)  # the second Ctrl-C, while it matches and writes
        return original(self, match=match)

    monkeypatch.setattr(ServerNode, "finish", finish_stopped_again)
    monkeypatch.setattr(serve_module, "_linger", lambda node, seconds: lingered.append(seconds) or True)
    result = _serve(cfg, tmp_path, reference="car1")  # the second stop waited for the results
    assert result.interrupted
    assert json.loads((tmp_path / "server.json").read_text())["finished"] is True
    assert lingered == []


def test_an_empty_endpoint_is_refused_not_taken_for_the_default() -> None:
    for spec in ("", " ", " , "):
        with pytest.raises(ConfigError, match="no endpoint given"):
            parse_endpoints(spec)
    assert parse_endpoints(()) == [] and parse_endpoints(None) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=TIMEOUT_S)


def test_the_commands_refuse_a_finished_folder_and_an_empty_endpoint_and_name_a_missing_server(
    robots, cfg, tiny_scenario: Path, tmp_path: Path
) -> None:
    _server_run(robots, cfg, tmp_path / "done")
    (config := tmp_path / "config.yaml").write_text(cfg.to_yaml())  # the run's: its journal is not refused for it
    p = _run("server", "--out", str(tmp_path / "done"), "--listen", f"tcp/127.0.0.1:{_free_port()}", "--rerun", "off",
             "--expect", "1", "--config", str(config))  # fmt: skip
    said = " ".join((p.stdout + p.stderr).split())
    assert p.returncode == 2 and "Traceback" not in said and "holds a map server run that finished" in said, said
    car1 = f"car1={tiny_scenario / 'car1'}:0-4"
    p = _run("robot", car1, "--connect", "", "--odometry", "gt", "--wait", "1")
    said = " ".join((p.stdout + p.stderr).split())
    assert p.returncode == 2 and "no endpoint given" in said and "Traceback" not in said, said
    port = _free_port()
    p = _run("robot", car1, "--connect", f"tcp/127.0.0.1:{port}", "--odometry", "gt", "--wait", "1")
    said = " ".join((p.stdout + p.stderr).split())
    assert p.returncode == 3 and f"no map server answered at tcp/127.0.0.1:{port}" in said, said


@pytest.mark.slow
def test_a_stop_of_the_server_while_robots_run_writes_its_results_and_the_robots_say_so(
    tiny_scenario: Path, tmp_path: Path
) -> None:
    port = _free_port()
    out = tmp_path / "out"
    server = subprocess.Popen([*CLI, "server", "--out", str(out), "--expect", "2", "--listen",
                               f"tcp/127.0.0.1:{port}", "--reference", "car1", "--rerun", "off"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    deadline = time.monotonic() + TIMEOUT_S  # robots paced in real time must not finish before the server listens
    while not (out / "config.yaml").is_file():  # (it writes it once it listens and has subscribed)
        assert server.poll() is None and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.1)
    robots = [subprocess.Popen([*CLI, "robot", f"{r}={tiny_scenario / r}", "--connect", f"tcp/127.0.0.1:{port}",
                                "--odometry", "gt", "--realtime", "--wait", "2"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
              for r in ("car1", "car2")]  # fmt: skip
    try:
        deadline = time.monotonic() + TIMEOUT_S  # until both robots' keyframes are in its journal
        while not ((j := out / "journal.bin").is_file() and b"car1" in j.read_bytes() and b"car2" in j.read_bytes()):
            assert server.poll() is None and time.monotonic() < deadline, "no keyframes arrived"
            time.sleep(0.1)
        server.send_signal(signal.SIGTERM)  # stops it as Ctrl-C does (a SIGINT: pytest-xdist's workers ignore it, and
        # so do the processes they start)
        server_out, _ = server.communicate(timeout=TIMEOUT_S)
        robot_outs = [" ".join(r.communicate(timeout=TIMEOUT_S)[0].split()) for r in robots]
    finally:
        for p in (server, *robots):
            if p.poll() is None:
                p.kill()
                p.wait()
    assert server.returncode == 130, server_out
    s = json.loads((out / "server.json").read_text())
    assert s["finished"] and s["interrupted"]
    for name, r in s["robots"].items():  # what it printed is what it wrote (not what came while it lingered)
        assert f"{name}: {r['keyframes']} keyframes" in " ".join(server_out.split()), server_out
    for r, said in zip(robots, robot_outs, strict=True):
        assert r.returncode == 3, said
        assert "finished before this robot was done" in said and "start it again on its --out" in said, said
