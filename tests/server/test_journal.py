"""The server journal: append, replay, and a torn or corrupt tail after a kill."""

from __future__ import annotations

from pathlib import Path

import pytest

from shgm_slam.errors import DataError
from shgm_slam.server.journal import Journal


def test_replay_returns_every_record_in_order(tmp_path: Path) -> None:
    j = Journal(tmp_path / "j" / "journal.bin", sync_every=2)
    payloads = [bytes([i]) * (i * 37 % 200) for i in range(50)]
    for p in payloads:
        j.append(p)
    j.close()
    assert list(Journal(tmp_path / "j" / "journal.bin").replay()) == payloads


def test_torn_tail_is_dropped_and_appends_continue_cleanly(tmp_path: Path) -> None:
    path = tmp_path / "journal.bin"
    j = Journal(path)
    for p in (b"one", b"two", b"three"):
        j.append(p)
    j.close()
    whole = path.read_bytes()
    path.write_bytes(whole[:-2])  # killed mid-write
    j2 = Journal(path)
    assert list(j2.replay()) == [b"one", b"two"]
    j2.append(b"four")
    j2.close()
    assert list(Journal(path).replay()) == [b"one", b"two", b"four"]


def written_journal(tmp_path: Path, payloads: tuple[bytes, ...]) -> Path:
    """A journal holding ``payloads``, closed; its path."""
    path = tmp_path / "journal.bin"
    j = Journal(path)
    for p in payloads:
        j.append(p)
    j.close()
    return path


def test_corrupt_last_record_ends_the_replay(tmp_path: Path) -> None:
    path = written_journal(tmp_path, (b"alpha", b"beta", b"gamma"))
    data = bytearray(path.read_bytes())
    data[-2] ^= 0xFF  # a byte of "gamma", the last record
    path.write_bytes(bytes(data))
    assert list(Journal(path).replay()) == [b"alpha", b"beta"]


def test_corrupt_record_with_records_after_it_is_refused_and_kept(tmp_path: Path) -> None:
    path = written_journal(tmp_path, (b"alpha", b"beta", b"gamma"))
    data = bytearray(path.read_bytes())
    data[8 + 5 + 8 + 1] ^= 0xFF  # a byte of "beta": "gamma" after it must not be thrown away
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"record 1 at byte 13 is corrupt.*truncate -s 13"):
        list(Journal(path).replay())
    assert path.read_bytes() == bytes(data)
    with pytest.raises(DataError, match=r"record 1 at byte 13 is corrupt.*Delete it to resume$"):  # another file's
        list(Journal(path, damaged_advice="Delete it to resume").replay())  # advice (the queue's: delete it)


def test_zero_filled_tail_is_dropped_not_replayed_as_empty_records(tmp_path: Path) -> None:
    path = tmp_path / "journal.bin"
    j = Journal(path)
    for p in (b"one", b"two"):
        j.append(p)
    j.close()
    whole = path.read_bytes()
    path.write_bytes(whole + bytes(4096))  # a crash can leave the file's tail zero-filled
    j2 = Journal(path)
    assert list(j2.replay()) == [b"one", b"two"]
    assert j2.records == 2
    assert path.read_bytes() == whole


def test_missing_journal_replays_nothing(tmp_path: Path) -> None:
    assert list(Journal(tmp_path / "none.bin").replay()) == []


def test_chain_identifies_the_records_so_far(tmp_path: Path) -> None:
    j = Journal(tmp_path / "journal.bin")
    chains = []
    for p in (b"a", b"b", b"c"):
        j.append(p)
        chains.append(j.chain)
    j.close()
    again = Journal(tmp_path / "journal.bin")
    assert [again.chain for _ in again.replay()] == chains
    assert len(set(chains)) == 3
    other = Journal(tmp_path / "other.bin")
    for p in (b"a", b"x", b"c"):
        other.append(p)
    assert other.chain != chains[-1]
