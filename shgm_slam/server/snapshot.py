"""Snapshots of the map server's state: written every so often, the newest valid one read on restart.

A restarted server used to replay its whole journal, re-running every match (as long as the server
had worked). Now it also writes a ``ServerSnapshot`` every ``server.snapshot_every_messages`` journal
records or ``server.snapshot_every_s`` seconds: every robot's mirrored graph and keyframes, the pose
graph's decisions (closures with their evidence, consistency votes, anchors, estimate), the match log
and the robot sessions. On restart the newest snapshot that is intact, belongs to this journal (record
count and running CRC, ``Journal.chain``) and was made with the same configuration is loaded, and only
the journal records after it are replayed. A corrupt, cut or foreign snapshot falls back to the one
before it, and without any to the whole journal.

Files: ``snapshot-<records>.bin`` in the results folder, written atomically and fsync'd, the newest
``server.snapshots_kept`` kept. Layout: ``b"SHGMSNAP"``, u32 format version, u32 CRC-32 of the body,
u64 body length (little-endian), then the body (msgpack, ``snapshot_codec``; never pickle).
"""

from __future__ import annotations

import hashlib
import logging
import re
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import pydantic_core

from shgm_slam.config import ShgmConfig
from shgm_slam.errors import ShgmError
from shgm_slam.io.export import ResultsWriter
from shgm_slam.server.snapshot_codec import ServerSnapshot, SnapshotError, decode_snapshot, encode_snapshot

log = logging.getLogger(__name__)

SNAPSHOT_VERSION = 2
"""Version of the snapshot layout written; a snapshot of a version not in ``READABLE_VERSIONS`` is skipped (the
journal still has all). 2: each distinct set of objects behind closures stored once (``snapshot_codec``)."""

READABLE_VERSIONS = (1, 2)
"""Snapshot layouts this build reads (version 1 holds every closure's objects in place)."""

MAX_SNAPSHOT_BYTES = 4 * 1024**3
"""Largest snapshot body read back."""

_MAGIC = b"SHGMSNAP"
_HEADER = struct.Struct("<8sIIQ")
_NAME = re.compile(r"snapshot-(\d{9,})\.bin")


def config_digest(cfg: ShgmConfig) -> str:
    """SHA-256 of everything in ``cfg`` but the ``server`` stage (which does not change what the map holds).

    Dumped to plain values first, then to JSON (the same text ``model_dump_json`` gives): pydantic's JSON
    serializer wraps a KeyboardInterrupt raised in Python code it calls (a Ctrl-C landing as it reads an enum's
    value) into a ``PydanticSerializationError``, a traceback instead of the command's "interrupted"."""
    data = pydantic_core.to_json(cfg.model_dump(mode="json", exclude={"server"}), inf_nan_mode="null")
    return hashlib.sha256(data).hexdigest()


class SnapshotStore:
    """The snapshot files of one results folder (see the module docstring).

    Args:
        folder: the results folder.
        keep: how many of the newest snapshots to keep (older ones are removed after each write).
    """

    def __init__(self, folder: Path, *, keep: int = 2) -> None:
        self.folder = Path(folder)
        self.keep = max(1, keep)
        self._writer = ResultsWriter(self.folder)
        self.written = 0
        self.last_bytes = 0

    def paths(self) -> list[Path]:
        """Snapshot files in the folder, newest (most journal records) first."""
        found = [(int(m[1]), p) for p in self.folder.glob("snapshot-*.bin") if (m := _NAME.fullmatch(p.name))]
        return [p for _, p in sorted(found, reverse=True)]

    def write(self, snapshot: ServerSnapshot) -> Path:
        """Encode and write ``snapshot`` atomically, then keep it and the ``keep - 1`` before it (files of more
        records are of another journal history and go too).

        Raises:
            DataError: the disk is full or the folder is not writable (older snapshots are kept).
        """
        body = encode_snapshot(snapshot)
        name = f"snapshot-{snapshot.journal_records:09d}.bin"
        self._writer.write_bytes(name, _HEADER.pack(_MAGIC, SNAPSHOT_VERSION, zlib.crc32(body), len(body)) + body)
        self.written += 1
        self.last_bytes = _HEADER.size + len(body)
        # newer-numbered files cannot belong to this journal (it has only now reached this count): another history
        paths = self.paths()
        mine = paths.index(self.folder / name)
        for old in paths[:mine] + paths[mine + self.keep :]:
            old.unlink(missing_ok=True)
        return self.folder / name

    def read(self, path: Path) -> ServerSnapshot:
        """Read and decode one snapshot file.

        Raises:
            SnapshotError: cut short, corrupt, another version, or not a snapshot.
        """
        try:
            with open(path, "rb") as f:
                head = f.read(_HEADER.size)
                if len(head) < _HEADER.size:
                    raise SnapshotError(f"{path.name} is cut short ({len(head)} bytes)")
                magic, version, crc, length = _HEADER.unpack(head)
                if magic != _MAGIC:
                    raise SnapshotError(f"{path.name} is not a shgm_slam snapshot")
                if version not in READABLE_VERSIONS:
                    raise SnapshotError(
                        f"{path.name} has version {version}, this build reads {', '.join(map(str, READABLE_VERSIONS))}"
                    )
                body = f.read(length) if length <= MAX_SNAPSHOT_BYTES else b""
        except OSError as exc:
            raise SnapshotError(f"cannot read {path}: {exc.strerror}") from None
        if len(body) != length or zlib.crc32(body) != crc:
            raise SnapshotError(f"{path.name} is cut short or corrupt (CRC mismatch)")
        return decode_snapshot(body)

    def restore_newest(
        self, usable: Callable[[ServerSnapshot], str | None], restore: Callable[[ServerSnapshot], None]
    ) -> ServerSnapshot | None:
        """Restore the newest snapshot that reads back, is ``usable`` and restores without error.

        Args:
            usable: returns why a decoded snapshot cannot be used here (None: it can).
            restore: loads a snapshot into the server; raises ``ShgmError`` when its content is inconsistent.

        Returns:
            The snapshot restored, or None (no snapshot, or none usable: the caller replays the whole journal).
        """
        for path in self.paths():
            try:
                snap = self.read(path)
                why = usable(snap)
                if why is None:
                    restore(snap)
                    return snap
            except ShgmError as exc:
                why = str(exc)
            log.warning("snapshot %s not used (%s); trying an older one, else the whole journal", path.name, why)
        return None
