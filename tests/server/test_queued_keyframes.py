"""``queued.bin`` (keyframes acknowledged but waiting for their turn in the time order) across map server restarts:
the robot's hello is kept before its keyframes, whatever came first after a restart."""

from __future__ import annotations

import errno
import logging

from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend
from shgm_slam.server import journal as journal_module
from shgm_slam.server.journal import Journal
from shgm_slam.server.node import ServerNode
from shgm_slam.transport.base import Inbox
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import ALL_DONE, ALL_HELLO, ALL_KEYFRAMES
from tests.server.conftest import FakeClock


def _recorded(robots, cfg, clock: FakeClock, keyframes: int, name: str = "car1") -> dict[str, list[tuple[str, bytes]]]:
    """Robot ``name``'s hello, first ``keyframes`` keyframes and done as published (key, payload), by kind."""
    bus, tap = InProcessBus(), Inbox()
    listener = InProcessTransport(bus)
    for key in (ALL_HELLO, ALL_KEYFRAMES, ALL_DONE):
        listener.subscribe(key, tap)
    robot = RobotNode(make_frontend(name, robots[name], cfg), InProcessTransport(bus), clock=clock)
    robot.hello()
    i = 0
    while robot.keyframes_sent < keyframes:
        robot.step(i)
        i += 1
    robot.done()
    sent: dict[str, list[tuple[str, bytes]]] = {"hello": [], "keyframe": [], "done": []}
    for key, payload in tap.drain():
        sent[key.rsplit("/", 1)[1]].append((key, payload))
    return sent


def test_keyframes_that_came_before_the_hello_after_a_restart_are_kept_with_it(robots, cfg, tmp_path,
                                                                              caplog) -> None:  # fmt: skip
    """Restarted from its journal (the hello replayed), the server took car1's next keyframe before car1's live
    hello: ``queued.bin`` kept it without the hello (the first frame's time that orders it), and once a snapshot
    covered the hello, a server restarted again queued none of car1's waiting keyframes (car1 had left: they were
    lost, the server waited for them for ever)."""
    clock = FakeClock()
    sent = _recorded(robots, cfg, clock, keyframes=2)
    (hello, *_), (kf0, kf1, *_), (done, *_) = sent["hello"], sent["keyframe"], sent["done"]
    no_snapshots, snapshots = cfg.model_copy(deep=True), cfg.model_copy(deep=True)
    no_snapshots.server.snapshot_every_messages = 0
    snapshots.server.snapshot_every_messages = 1

    first = ServerNode(no_snapshots, InProcessTransport(bus := InProcessBus()), tmp_path, expect=2, clock=clock)
    InProcessTransport(bus).publish(*hello)
    first.poll()  # killed: its journal holds car1's hello

    second = ServerNode(snapshots, InProcessTransport(bus := InProcessBus()), tmp_path, expect=2, clock=clock)
    assert second.recovery.replayed == 1 and second.robots["car1"].start_s is not None
    robot = InProcessTransport(bus)
    for message in (kf0, hello, kf1, done):  # a keyframe before its live hello; both wait for car2
        robot.publish(*message)
        clock.t += 0.05
        second.poll()
    assert second.map.received("car1") == 0
    assert list(tmp_path.glob("snapshot-*.bin"))  # killed: its newest snapshot holds the hello and the done

    with caplog.at_level(logging.WARNING):
        third = ServerNode(snapshots, InProcessTransport(InProcessBus()), tmp_path, expect=2, clock=clock)
    assert third.recovery.snapshot_records == 2 and third.recovery.replayed == 0
    assert third.robots["car1"].complete(third._map(), third._order.held)  # both keyframes queued again
    assert not [r for r in caplog.records if "start robot car1 again" in r.getMessage()]


def test_keyframes_after_the_queue_emptied_keep_the_hello_the_restart_read_from_queued_bin(robots, cfg, tmp_path,
                                                                                         caplog) -> None:  # fmt: skip
    """Restarted from a snapshot (no first frame's time) with car1's hello and keyframe in ``queued.bin``: once that
    keyframe was in the map (the file emptied), car1's next one, come before its live hello, was kept without the
    hello, and a server restarted again queued none of it (car1 had left: lost)."""
    clock = FakeClock()
    sent = _recorded(robots, cfg, clock, keyframes=2)
    (hello, *_), (kf0, kf1, *_), (done, *_) = sent["hello"], sent["keyframe"], sent["done"]
    car2_hello = _recorded(robots, cfg, clock, keyframes=0, name="car2")["hello"][0]
    snapshots = cfg.model_copy(deep=True)
    snapshots.server.snapshot_every_messages = 1

    first = ServerNode(snapshots, InProcessTransport(bus := InProcessBus()), tmp_path, expect=2, clock=clock)
    for message in (hello, kf0):  # a snapshot holds the hello; kf0 waits for car2
        InProcessTransport(bus).publish(*message)
        clock.t += 0.05
        first.poll()
    assert list(tmp_path.glob("snapshot-*.bin")) and first.map.received("car1") == 0  # killed

    second = ServerNode(snapshots, InProcessTransport(bus := InProcessBus()), tmp_path, expect=2, clock=clock)
    assert second.recovery.snapshot_records == 1 and len(second._order) == 1  # start_s from queued.bin's hello
    clock.t += second.connect_wait_s + 1  # car2 late: kf0 goes into the map, queued.bin is emptied
    second.poll()
    assert second.map.received("car1") == 1 and (tmp_path / "queued.bin").stat().st_size == 0
    robot = InProcessTransport(bus)
    for message in (car2_hello, kf1, done):  # car1's next keyframe (before its live hello) waits for car2
        robot.publish(*message)
        clock.t += 0.05
        second.poll()
    assert second.map.received("car1") == 1  # killed; car1 had left

    with caplog.at_level(logging.WARNING):
        third = ServerNode(snapshots, InProcessTransport(InProcessBus()), tmp_path, expect=2, clock=clock)
    assert third.recovery.replayed == 0 and third.map.received("car1") == 1
    assert third.robots["car1"].complete(third.map, third._order.held)  # kf1 queued again
    assert not [r for r in caplog.records if "start robot car1 again" in r.getMessage()]


def test_emptying_queued_bin_does_not_fsync_what_it_cuts_away(tmp_path, monkeypatch) -> None:
    """``clear`` closed the file with ``close``, an fsync of the records it then cut away (``queued.bin`` is emptied
    about once per keyframe, the journal is synced every 50 records), and an fsync failing there (EIO on a network
    disk) got out as a bare OSError, not a DataError."""
    queued = Journal(tmp_path / "queued.bin", sync_every=1000)
    queued.append(b"kept")

    def failing(fd: int) -> None:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(journal_module.os, "fsync", failing)
    queued.clear()
    assert (tmp_path / "queued.bin").stat().st_size == 0 and queued.records == 0
    queued.append(b"next")
    monkeypatch.undo()
    queued.close()
    assert list(Journal(tmp_path / "queued.bin").replay()) == [b"next"]
