"""The map server's journal: an append-only log of every message it accepted, for crash recovery.

Each record is ``[u32 length][u32 crc32][payload]`` (little-endian), the payload being the message's
wire bytes exactly as received. A server killed at any moment and started again on the same results
folder replays the journal through a fresh map server: the mirrored graphs, the pose graph and the
match log come back as they were (matching is deterministic given the message order). A record cut
short by the kill (or garbled, or zero-filled, as the last in the file) ends the replay; the file is truncated
there so appends stay valid. A corrupt record with records after it is refused, the file left as it is:
truncating there would drop every record after it.

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
        damaged_advice: what to do about a corrupt record that is not the tail, when not the journal's (restore,
            cut, or start afresh): ``queued.bin``'s (the server's queue) is to delete the file.
    """

    def __init__(self, path: Path, *, sync_every: int = 50, damaged_advice: str | None = None) -> None:
        self.path = Path(path)
        self.damaged_advice = damaged_advice
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
        is yielded, ``records`` and ``chain`` count it and every record before it.

        Raises:
            DataError: a corrupt record that is not the tail (see ``_check_tail``).
        """
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
                # zeros to the end of the file read as empty records: a tail the filesystem left zero-filled
                zeros = length == 0 and crc == 0 and self._zeros_from(f, good_end)
                if zeros or len(payload) != length or zlib.crc32(payload) != crc:
                    self._check_tail(f, good_end, length)
                    log.warning("journal %s: record at byte %d is cut short or corrupt; replay ends there",
                                self.path, good_end)  # fmt: skip
                    break
                good_end = f.tell()
                self._count(crc)
                yield payload
        if good_end < self.path.stat().st_size:
            with open(self.path, "r+b") as f:
                f.truncate(good_end)

    def _check_tail(self, f, start: int, length: int) -> None:
        """Refuse a bad record at byte ``start`` that is not the journal's tail: a kill cuts only the last record
        (or leaves it zero-filled), so intact-looking bytes after it mean the journal was damaged, and cutting it
        there would throw away every record after it.

        Raises:
            DataError: bytes other than zeros follow the bad record (the file is left as it is).
        """
        size = self.path.stat().st_size
        if length <= MAX_RECORD_BYTES and start + _HEADER.size + length >= size:
            return  # the last record, cut short or garbled by the kill
        if not self._zeros_from(f, start):
            advice = self.damaged_advice or (
                f"Restore it from a backup, or cut it there to resume from the {self.records} records before it "
                f"(truncate -s {start} {self.path}; the later ones are lost), or start afresh with --overwrite"
            )
            raise DataError(
                f"{self.path}: record {self.records} at byte {start} is corrupt and {size - start} bytes of records "
                f"follow it (not a record cut short by a kill); the file is left as it is. {advice}"
            )

    @staticmethod
    def _zeros_from(f, start: int) -> bool:
        """Whether the open file ``f`` holds only zero bytes from ``start`` to its end (its position is kept)."""
        pos = f.tell()
        f.seek(start)
        try:
            while chunk := f.read(1 << 20):
                if chunk.count(0) != len(chunk):
                    return False
            return True
        finally:
            f.seek(pos)

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

    def clear(self) -> None:
        """Empty the file (its records are no longer needed): the next append starts it afresh. The open file is
        closed without an fsync (what it would make durable is cut away at once; ``queued.bin`` empties about
        once per keyframe).

        Raises:
            DataError: the file cannot be written.
        """
        try:
            if self._file is not None:
                self._file.close()
            if self.path.exists():
                with open(self.path, "wb"):
                    pass
        except OSError as exc:
            raise DataError(f"cannot empty {self.path}: {exc.strerror}") from None
        finally:
            self._file, self._since_sync = None, 0
        self.records, self.chain = 0, 0

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.flush()
                os.fsync(self._file.fileno())
            finally:
                self._file.close()
                self._file = None
