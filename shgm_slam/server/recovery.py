"""Crash recovery of the map server: the newest usable snapshot, then the journal records after it.

A snapshot is usable when it reads back intact (``SnapshotStore``), covers a prefix of this very
journal (its record count and the journal's running CRC at that count agree), was made with the same
configuration (``config_digest``) and has the same shared frame as ``--reference``. Its state is
loaded with the node's ``restore`` (which raises on inconsistent content: then the snapshot before it
is tried); without any, the whole journal is replayed. Records after the snapshot are replayed as
before, so the matches they trigger run again and nothing the snapshot holds runs twice.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from shgm_slam.errors import DataError
from shgm_slam.server.journal import Journal
from shgm_slam.server.snapshot import SnapshotStore
from shgm_slam.server.snapshot_codec import ServerSnapshot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecoveryReport:
    """How a (re)started server got its state back.

    ``snapshot_records``: journal records restored from a snapshot (0: none used); ``replayed``: journal
    records replayed after it; ``seconds``: wall time of the whole recovery.
    """

    snapshot_records: int = 0
    replayed: int = 0
    seconds: float = 0.0

    def to_json_dict(self) -> dict:
        return {"snapshot_records": self.snapshot_records, "replayed": self.replayed, "seconds": round(self.seconds, 3)}


def recover(
    journal: Journal,
    store: SnapshotStore | None,
    *,
    digest: str,
    reference: str | None,
    restore: Callable[[ServerSnapshot], None],
    replay: Callable[[bytes, int], None],
) -> RecoveryReport:
    """Bring a server back from its results folder (see the module docstring).

    Args:
        journal: the server's journal (read here; appends continue after it).
        store: its snapshots (None: replay the whole journal).
        digest: ``config_digest`` of the server's configuration.
        reference: the ``--reference`` robot, if one was given.
        restore: loads a snapshot into the server (raises ``ShgmError`` on inconsistent content).
        replay: applies one journal record (payload, index) to the server.

    Raises:
        DataError: the journal is corrupt before its tail (``Journal.replay``), or empty or missing while the
            folder holds snapshots (it was lost: starting afresh would overwrite the earlier run's results).
    """
    t0 = time.perf_counter()
    payloads: list[bytes] = []
    chains = [journal.chain]
    for payload in journal.replay():
        payloads.append(payload)
        chains.append(journal.chain)

    def usable(snap: ServerSnapshot) -> str | None:
        if snap.journal_records > len(payloads) or chains[snap.journal_records] != snap.journal_chain:
            return f"it covers {snap.journal_records} records of another journal than this one"
        if snap.config_digest != digest:
            return "it was made with another configuration"
        if reference is not None and snap.reference not in (None, reference):
            return f"its shared frame is {snap.reference}'s, not --reference {reference}'s"
        return None

    if store is not None and not payloads and (found := store.paths()):
        # snapshots are written only after journal records: the journal that made them was emptied or removed
        raise DataError(
            f"{journal.path} is {'empty' if journal.path.exists() else 'missing'} but {store.folder} holds "
            f"{', '.join(p.name for p in found)} of an earlier run: its journal was lost, and starting afresh would "
            "overwrite that run's results; restore the journal from a backup, or pass --overwrite to start afresh"
        )
    start = 0
    if store is not None and payloads:
        snap = store.restore_newest(usable, restore)
        start = snap.journal_records if snap is not None else 0
    for i in range(start, len(payloads)):
        replay(payloads[i], i)
    return RecoveryReport(start, len(payloads) - start, time.perf_counter() - t0)

