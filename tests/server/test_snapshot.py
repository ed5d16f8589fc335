"""Map-server snapshots: what a restarted server loads instead of replaying its whole journal.

A snapshot restores the same graphs, keyframes, match log, closures and sessions; a restart from it
re-runs no match the snapshot holds and ends like an uninterrupted run; a corrupt, cut, foreign or
other-configuration snapshot falls back to an older one or to the journal."""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest

import shgm_slam.server.map_server as map_server_module
from shgm_slam.errors import ShgmError
from shgm_slam.server.node import ServerNode
from shgm_slam.server.snapshot import SnapshotStore
from shgm_slam.server.snapshot_codec import SnapshotError, decode_snapshot, encode_snapshot
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from tests.server.conftest import FakeClock, drive, finish, fresh, fused


def with_snapshots(cfg, every: int):
    return cfg.model_copy(update={"server": cfg.server.model_copy(update={"snapshot_every_messages": every})})


def assert_same_map(a: ServerNode, b: ServerNode) -> None:
    assert a.map.agents == b.map.agents
    for agent in a.map.agents:
        ga, gb = a.map.graph(agent), b.map.graph(agent)
        for f in ("node_ids", "label_ids", "positions_xyz", "sizes", "edges"):
            np.testing.assert_array_equal(getattr(ga, f), getattr(gb, f))
        np.testing.assert_array_equal(a.map.keyframe_poses(agent), b.map.keyframe_poses(agent))
        assert a.map.is_placed(agent) == b.map.is_placed(agent)
    log_a, log_b = ([{**m.to_json_dict(), "timings_ms": None} for m in n.map.matches] for n in (a, b))
    assert log_a == log_b  # matches re-run from the journal take other times


@pytest.fixture(scope="module")
def half_run(robots, cfg, tmp_path_factory):
    """Both cars driven halfway on a server writing a snapshot after every batch of messages."""
    out = tmp_path_factory.mktemp("half")
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(with_snapshots(cfg, 1), InProcessTransport(bus), out, expect=2, clock=clock)
    nodes = fresh(robots, cfg, bus, clock)
    k = min(len(s) for s in robots.values()) // 2
    drive(server, nodes, {r: range(k) for r in nodes}, clock)
    server.transport.close()  # killed: its journal and snapshots survive
    return out, server, nodes, bus, clock, k


def test_snapshot_round_trip_restores_the_same_state(uninterrupted, cfg, tmp_path: Path) -> None:
    snap = decode_snapshot(encode_snapshot(uninterrupted.snapshot()))
    node = ServerNode(cfg, InProcessTransport(InProcessBus()), tmp_path, journal=False)
    node.restore(snap)
    assert_same_map(uninterrupted, node)
    assert node.reference == uninterrupted.reference and set(node.robots) == set(uninterrupted.robots)
    assert node.map.state().support == uninterrupted.map.state().support  # what confirms placements
    assert node.map.state().surface_offset == uninterrupted.map.state().surface_offset
    assert node.map.placement("car2") == uninterrupted.map.placement("car2")
    np.testing.assert_allclose(fused(node, "car2"), fused(uninterrupted, "car2"), atol=0.05)


def test_restart_loads_the_newest_snapshot_and_reruns_no_match(half_run, cfg, monkeypatch, tmp_path) -> None:
    out, first, _, bus, clock, _ = half_run
    out = copy_of(out, tmp_path)
    calls = []
    real = map_server_module.match_graphs
    monkeypatch.setattr(map_server_module, "match_graphs", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    second = ServerNode(with_snapshots(cfg, 1), InProcessTransport(bus), out, expect=2, clock=clock)
    assert second.recovery.snapshot_records == first.journal.records and second.recovery.replayed == 0
    assert calls == []  # every match was in the snapshot
    assert_same_map(first, second)


def test_restart_from_a_snapshot_ends_like_an_uninterrupted_run(half_run, uninterrupted, robots, cfg, tmp_path) -> None:
    out, _, nodes, bus, clock, k = half_run
    out = copy_of(out, tmp_path)
    second = ServerNode(with_snapshots(cfg, 1), InProcessTransport(bus), out, expect=2, clock=clock)
    second.poll()  # its new session: robots say hello again and re-send what it lacks
    for n in nodes.values():
        n.poll()
    drive(second, nodes, {r: range(k, len(robots[r])) for r in nodes}, clock)
    finish(second, nodes, clock)
    assert second.summary()["robots"]["car2"]["placed"] == uninterrupted.summary()["robots"]["car2"]["placed"]
    closures = [[(c["keyframe_a"], c["keyframe_b"], c["accepted"]) for c in m.closures] for m in second.map.matches]
    assert closures == [[(c["keyframe_a"], c["keyframe_b"], c["accepted"]) for c in m.closures]
                        for m in uninterrupted.map.matches]  # fmt: skip
    np.testing.assert_allclose(fused(second, "car2"), fused(uninterrupted, "car2"), atol=0.05)
    np.testing.assert_allclose(fused(second, "car1"), fused(uninterrupted, "car1"), atol=0.05)


def copy_of(out: Path, tmp_path: Path) -> Path:
    """A copy of the killed server's folder (tests that restart on it must not change the fixture)."""
    for f in out.iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes())
    return tmp_path


def _recover(out: Path, cfg, clock) -> ServerNode:
    return ServerNode(cfg, InProcessTransport(InProcessBus()), out, clock=clock)


def test_corrupt_newest_falls_back_to_the_one_before_then_to_the_journal(half_run, cfg, tmp_path: Path) -> None:
    out, first, *_ = half_run
    copy_of(out, tmp_path)
    newest, older = SnapshotStore(tmp_path).paths()[:2]
    data = bytearray(newest.read_bytes())
    data[len(data) // 2] ^= 0xFF
    newest.write_bytes(bytes(data))
    node = _recover(tmp_path, with_snapshots(cfg, 1), FakeClock())
    n_older = int(older.stem.split("-")[1])
    assert node.recovery.snapshot_records == n_older
    assert node.recovery.replayed == first.journal.records - n_older
    assert_same_map(first, node)
    older.write_bytes(older.read_bytes()[:-10])  # cut short: nothing usable is left
    node = _recover(tmp_path, with_snapshots(cfg, 1), FakeClock())
    assert node.recovery.snapshot_records == 0 and node.recovery.replayed == first.journal.records
    assert_same_map(first, node)


def test_snapshots_of_another_configuration_or_journal_are_not_used(half_run, cfg, tmp_path: Path) -> None:
    out, first, *_ = half_run
    copy_of(out, tmp_path)
    stricter = cfg.matching.model_copy(update={"min_inliers": cfg.matching.min_inliers + 1})
    other = cfg.model_copy(update={"matching": stricter})
    node = _recover(tmp_path, other, FakeClock())
    assert node.recovery.snapshot_records == 0 and node.recovery.replayed == first.journal.records
    journal = tmp_path / "journal.bin"
    journal.write_bytes(journal.read_bytes()[: journal.stat().st_size // 2])  # a shorter history
    node = _recover(tmp_path, with_snapshots(cfg, 1), FakeClock())
    assert node.recovery.snapshot_records == 0


def test_malformed_snapshot_bodies_are_snapshot_errors(uninterrupted) -> None:
    body = encode_snapshot(uninterrupted.snapshot())
    with pytest.raises(SnapshotError):
        decode_snapshot(b"\xc1not msgpack")
    with pytest.raises(SnapshotError):
        decode_snapshot(body[: len(body) // 3])
    rng = np.random.default_rng(0)
    for _ in range(30):  # flipped bytes: a clear error or a snapshot; never another exception
        data = bytearray(body)
        for i in rng.integers(0, len(data), 3):
            data[i] ^= int(rng.integers(1, 256))
        try:
            decode_snapshot(bytes(data))
        except ShgmError:
            pass


def test_damaged_content_is_refused_by_restore_not_loaded(uninterrupted, cfg, tmp_path: Path) -> None:
    snap = uninterrupted.snapshot()
    bad_graph = replace(snap.map.graphs["car2"], anchor_slots=snap.map.graphs["car2"].anchor_slots + 10_000)
    damaged = replace(snap, map=replace(snap.map, graphs={**snap.map.graphs, "car2": bad_graph}))
    node = ServerNode(cfg, InProcessTransport(InProcessBus()), tmp_path, journal=False)
    with pytest.raises(ShgmError):
        node.restore(decode_snapshot(encode_snapshot(damaged)))
    assert node.map is None and node.robots == {}  # nothing changed


def test_file_header_is_checked(half_run, tmp_path: Path) -> None:
    out, *_ = half_run
    store = SnapshotStore(out)
    path = store.paths()[0]
    raw = path.read_bytes()
    magic, version, crc, length = struct.unpack("<8sIIQ", raw[:24])
    for name, blob in {
        "version": struct.pack("<8sIIQ", magic, version + 1, crc, length) + raw[24:],
        "magic": b"NOTASNAP" + raw[8:],
        "short": raw[:10],
        "crc": struct.pack("<8sIIQ", magic, version, zlib.crc32(b"x"), length) + raw[24:],
    }.items():
        p = tmp_path / f"snapshot-{name}.bin"
        p.write_bytes(blob)
        with pytest.raises(SnapshotError):
            store.read(p)
    older = tmp_path / "snapshot-older.bin"  # version 1: every closure's objects in place, still read
    older.write_bytes(struct.pack("<8sIIQ", magic, 1, crc, length) + raw[24:])
    assert store.read(older).journal_records == store.read(path).journal_records


def test_match_evidence_survives_a_snapshot_and_older_snapshots_decode_without_it(uninterrupted) -> None:
    from shgm_slam.server.snapshot_codec import _match, _unmatch

    snap = uninterrupted.snapshot()
    records = snap.map.matches
    assert any(m.evidence is not None and not m.success for m in records)  # rejected hypotheses are kept
    for m in (m for m in records if m.success):  # an accepted hypothesis is the match's transform
        np.testing.assert_allclose(m.evidence.T_a_b_hypothesis, m.T_a_b)
        assert m.evidence.llr >= m.evidence.llr_threshold
    back = decode_snapshot(encode_snapshot(snap)).map.matches
    for a, b in zip(records, back, strict=True):
        assert (a.evidence is None) == (b.evidence is None)
        if a.evidence is not None:
            np.testing.assert_array_equal(a.evidence.T_a_b_hypothesis, b.evidence.T_a_b_hypothesis)
            # field by field, NaN equal to NaN (a rejected match predicts no precision)
            np.testing.assert_equal(vars(replace(a.evidence, T_a_b_hypothesis=None)),
                                    vars(replace(b.evidence, T_a_b_hypothesis=None)))  # fmt: skip
    older = {k: v for k, v in _match(records[0]).items() if k != "ev"}  # written before the record existed
    assert _unmatch(older).evidence is None
    # an accepted match carries the precision it predicted; a snapshot written before that field reads NaN
    accepted = [m for m in records if m.success]
    assert accepted and all(0.0 < m.evidence.centroid_sigma_m < 10.0 for m in accepted)
    assert all(np.isnan(m.evidence.centroid_sigma_m) for m in records if m.evidence is not None and not m.success)
    before = _match(accepted[0])
    before["ev"] = {k: v for k, v in before["ev"].items() if k != "cs"}
    assert np.isnan(_unmatch(before).evidence.centroid_sigma_m)


def test_an_accepted_matchs_rival_is_recorded_and_older_snapshots_read_none(uninterrupted) -> None:
    """The best alignment placing B elsewhere is kept with the evidence: an accepted match whose rival clears the
    threshold too leads it by log(1 / false alarm rate); a snapshot written before the field reads -inf."""
    from shgm_slam.config import MatchingConfig
    from shgm_slam.server.snapshot_codec import _match, _unmatch

    margin = math.log(1.0 / MatchingConfig().false_alarm_rate)
    records = [m for m in uninterrupted.snapshot().map.matches if m.evidence is not None]
    assert any(np.isfinite(m.evidence.rival_llr) for m in records)
    for m in records:
        e = m.evidence
        if m.success and e.rival_llr >= e.llr_threshold:
            assert e.llr - e.rival_llr >= margin - 1e-9
        assert e.to_json_dict()["rival_llr"] == (round(e.rival_llr, 3) if np.isfinite(e.rival_llr) else None)
    encoded = _match(records[0])
    older = {**encoded, "ev": {k: v for k, v in encoded["ev"].items() if k != "rl"}}
    assert _unmatch(older).evidence.rival_llr == -math.inf


def test_closures_of_one_match_share_one_support_set_and_older_snapshots_decode(uninterrupted) -> None:
    from shgm_slam.server.snapshot_codec import _map, _support, _unsupport

    support = uninterrupted.map.state().support
    distinct = {tuple(sorted((a, tuple(sorted(ids))) for a, ids in s.items())) for s in support.values()}
    assert len(support) > len(distinct)  # closures of one match share their objects
    encoded = _support(support)
    assert len(encoded["support_sets"]) == len(distinct)  # each distinct set written once
    assert _unsupport(encoded) == support
    older = {"support": [[cid, {a: sorted(ids) for a, ids in s.items()}] for cid, s in support.items()]}
    assert _unsupport(older) == support  # written before the sets were shared
    assert len(msgpack.packb(encoded)) < len(msgpack.packb(older))
    assert _unsupport({}) == {}
    for bad in ([[0, 99]], [[0]], [[0, "x"]]):
        with pytest.raises(SnapshotError):
            _unsupport({**encoded, "support": bad})
    assert "support_sets" in _map(uninterrupted.map.state())


def test_a_closures_decisive_flag_survives_a_snapshot_and_older_snapshots_read_it_as_plain() -> None:
    from shgm_slam.backend.pose_graph import ClosureRecord, ClosureStatus
    from shgm_slam.server.snapshot_codec import _closure, _unclosure

    for decisive in (False, True):
        c = ClosureRecord(3, "car1", 4, "car2", 7, np.eye(4), 12, ClosureStatus.ACCEPTED, "accepted", True, 2, "car2",
                          decisive)  # fmt: skip
        assert _unclosure(_closure(c)).decisive is decisive
    older = {k: v for k, v in _closure(replace(c, decisive=True)).items() if k != "dec"}  # before the flag existed
    assert _unclosure(older).decisive is False
