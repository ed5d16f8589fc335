"""The map server's journal: an append-only log of every message it accepted, for crash recovery.

Each record is ``[u32 length][u32 crc32][payload]`` (little-endian), the payload being the message's
wire bytes exactly as received. A server killed at any moment and started again on the same results
folder replays the journal through a fresh map server: the mirrored graphs, the pose graph and the
match log come back as they were (matching is deterministic given the message order). A record cut
short by the kill (or corrupted) ends the replay; the file is truncated there so appends stay valid.

``chain`` is a running CRC-32 over the records' CRCs: a snapshot stores the record count and chain it
covers, so a restarted server can tell that the snapshot belongs to this very journal.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

from shgm_slam.errors import DataError

log = logging.getLogger(__name__)

_HEADER = struct.Struct("<II")
_CRC = struct.Struct("<I")
MAX_RECORD_BYTES = 64 * 1024 * 1024


class Journal:
    """Append-only message log at ``path`` (created with its folder when missing).

    Args:
        path: the journal file.
        sync_every: ``fsync`` after this many appends (flushes to the OS after every append anyway,
            which survives a killed process; fsync is for power loss).
    """

    def __init__(self, path: Path, *, sync_every: int = 50) -> None:
        self.path = Path(path)
        self.sync_every = max(1, sync_every)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"cannot create the journal folder {self.path.parent}: {exc.strerror}") from None
        self._file = None
        self._since_sync = 0
        self.records = 0
        self.chain = 0  # running CRC-32 of the records' CRCs (see the module docstring)

    def _count(self, crc: int) -> None:
        self.records += 1
        self.chain = zlib.crc32(_CRC.pack(crc), self.chain)

    def replay(self) -> Iterator[bytes]:
        """Yield every intact record's payload in order; truncate a torn or corrupt tail. While a payload
        is yielded, ``records`` and ``chain`` count it and every record before it."""
        if not self.path.exists():
            return
        good_end = 0
        with open(self.path, "rb") as f:
            while True:
                head = f.read(_HEADER.size)
                if not head:
                    break
                if len(head) < _HEADER.size:
                    log.warning("journal %s: a record header is cut short at byte %d; dropped", self.path, good_end)
                    break
                length, crc = _HEADER.unpack(head)
                payload = f.read(length) if length <= MAX_RECORD_BYTES else b""
                if len(payload) != length or zlib.crc32(payload) != crc:
                    log.warning("journal %s: record at byte %d is cut short or corrupt; replay ends there",
                                self.path, good_end)  # fmt: skip
                    break
                good_end = f.tell()
                self._count(crc)
                yield payload
        if good_end < self.path.stat().st_size:
            with open(self.path, "r+b") as f:
                f.truncate(good_end)

    def append(self, payload: bytes) -> None:
        """Append one record (flushed to the OS before returning).

        Raises:
            DataError: the disk is full or the journal cannot be written.
        """
        try:
            if self._file is None:
                self._file = open(self.path, "ab")
            crc = zlib.crc32(payload)
            self._file.write(_HEADER.pack(len(payload), crc) + payload)
            self._file.flush()
            self._since_sync += 1
            if self._since_sync >= self.sync_every:
                os.fsync(self._file.fileno())
                self._since_sync = 0
        except OSError as exc:
            raise DataError(f"cannot append to the journal {self.path}: {exc.strerror}") from None
        self._count(crc)

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.flush()
                os.fsync(self._file.fileno())
            finally:
                self._file.close()
                self._file = None
