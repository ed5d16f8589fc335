"""Crash recovery: the newest usable snapshot, then the journal records after it."""

from __future__ import annotations

from pathlib import Path

import pytest

from shgm_slam.errors import DataError
from shgm_slam.server.journal import Journal
from shgm_slam.server.recovery import recover
from shgm_slam.server.snapshot import SnapshotStore


def _recover(folder: Path) -> list[int]:
    replayed: list[int] = []
    recover(Journal(folder / "journal.bin"), SnapshotStore(folder), digest="d", reference=None,
            restore=lambda snap: None, replay=lambda payload, i: replayed.append(i))  # fmt: skip
    return replayed


@pytest.mark.parametrize("journal", ["empty", "missing"])
def test_a_lost_journal_beside_snapshots_is_refused_not_started_afresh(tmp_path: Path, journal: str) -> None:
    """Snapshots are written only after journal records: without the journal a fresh start would overwrite the
    earlier run's results (it used to start silently as a new run)."""
    (tmp_path / "snapshot-000000050.bin").write_bytes(b"SHGMSNAP")
    if journal == "empty":
        (tmp_path / "journal.bin").write_bytes(b"")
    with pytest.raises(DataError, match=rf"journal.bin is {journal} but .*snapshot-000000050.bin.*--overwrite"):
        _recover(tmp_path)


def test_a_new_folder_starts_afresh(tmp_path: Path) -> None:
    assert _recover(tmp_path) == []
    j = Journal(tmp_path / "journal.bin")
    j.append(b"one")
    j.close()
    assert _recover(tmp_path) == [0]  # no snapshot yet: the whole journal
