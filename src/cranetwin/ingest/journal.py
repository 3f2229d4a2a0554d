"""The sender's durable journal: every datagram is on disk before it is sent.

:class:`FileJournal` implements the sans-IO sender's ``Journal`` protocol
(:class:`cranetwin.protocol.Journal`) with a directory of append-only segment files, the way
write-ahead logs do it (Kafka's segments named by their first offset, SQLite's WAL recovery that
keeps the longest valid prefix)::

    DIR/                       0700
      lock                     flock held while a sender uses the journal (its pid inside)
      state                    {"epoch": …, "released": …}: written atomically (temp file,
                               fsync, rename, directory fsync)
      seg-<first seq:020d>.log records  u32 length ‖ u32 crc32 ‖ u64 seq ‖ datagram  (big endian)
      rejected.log             datagrams the server refused, one JSON line each (dead letters)

* :meth:`~FileJournal.append` only buffers; :meth:`~FileJournal.sync` writes the buffer and
  fsyncs the active segment (plus the directory once after a new segment was created). The
  sender calls it once per batch, before the new datagrams leave, so a datagram that was ever
  sent is durable and a crash can only lose datagrams that were never sent.
* A segment is rolled at ``segment_bytes`` (4 MiB) or ``segment_records`` (4096) and sealed with
  an fsync first, so only the newest segment can have a torn tail. On open a torn or corrupt
  tail of the newest segment (short record, bad crc, wrong seq) is cut away; damage anywhere
  else is an error, never silently dropped.
* :meth:`~FileJournal.release` moves the watermark and deletes whole segments below it (the
  newest one is always kept, so the next seq is known after everything was released). The
  watermark is persisted at most every ``state_interval_s`` (5 s) and on close: losing it
  only means datagrams that were acked already are sent again, which the server deduplicates
  (at most one segment's worth, since older segments are gone). Each write costs two fsyncs
  (temp file, directory): at 0.5 s it cost more than the data itself for a sender at real time
  (2 acks/s: 5.2 fsyncs/s instead of 2.4).
* The epoch (the sender's boot id in protocol version 2) is drawn with
  :func:`secrets.randbits` when the directory is new and kept for the journal's life. A
  directory whose state cannot be read is an error; a new epoch is only ever chosen for an
  empty directory, so data that could not be read is never overwritten under a new identity.

Modules: the record format, segment indexing and reading, and file helpers are
:mod:`~cranetwin.ingest.journal_files`; the ``state`` file and the dead letters of
``rejected.log`` are :mod:`~cranetwin.ingest.journal_state`; the active segment, reading back,
the atomic state write and deleting released segments are :mod:`~cranetwin.ingest.journal_disk`;
opening and recovery (lock, state, torn tails) are :mod:`~cranetwin.ingest.journal_recovery`;
this module is the journal's interface (appending, syncing, reading, releasing, rejecting,
closing).

Files are created 0600 and directories 0700. One process at a time: a second
:class:`FileJournal` on the same directory raises :class:`SenderError` (two senders sharing an
epoch would reuse sequence numbers).
"""

from __future__ import annotations

import bisect
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType

from cranetwin.ingest.journal_files import (
    MAX_RECORD,
    MAX_SEQ,
    REC,
    Cursor,
    Segment,
    SenderError,
    encode_record,
)
from cranetwin.ingest.journal_recovery import JournalRecovery
from cranetwin.ingest.journal_state import STATE_FORMAT, rejected_line

__all__ = ["MAX_RECORD", "MAX_SEQ", "SEGMENT_BYTES", "SEGMENT_RECORDS", "STATE_FORMAT",
           "STATE_INTERVAL_S", "FileJournal", "SenderError", "encode_record"]

log = logging.getLogger(__name__)

SEGMENT_BYTES = 4 << 20
SEGMENT_RECORDS = 4096
STATE_INTERVAL_S = 5.0
_WRITE_OUT = 1 << 20  # buffered bytes written to the OS (not synced) beyond this


class FileJournal(JournalRecovery):
    """Durable, crash-safe log of a sender's datagrams in ``directory`` (see the module doc).

    Args:
        directory: The journal directory (created 0700 with its missing parents).
        fsync: Sync to disk in :meth:`sync` (False: only hand the data to the OS, which survives
            a crash of the process but not of the machine; for tests).
        owner: Identity of the sender (e.g. machine id, wire id and a key fingerprint), stored
            when the journal is created; reopening with a different one raises
            :class:`SenderError` (its datagrams were signed with another key).
        segment_bytes: A segment is rolled when it reaches this size [bytes].
        segment_records: … or this many records.
        state_interval_s: Least time between two writes of the release watermark [s].
        clock: Monotonic clock [s] (injectable for tests).

    Raises:
        SenderError: the directory or its state cannot be read or created, a segment other than
            the newest is damaged, another process uses the journal, or ``owner`` differs.

    Attributes:
        fsyncs: ``os.fsync`` calls made (segments, directory, state, rejected.log).
        syncs: :meth:`sync` calls that had something to make durable.
        truncated_bytes: Bytes of a torn tail cut away when the journal was opened.
    """

    def __init__(self, directory: str | os.PathLike[str], *, fsync: bool = True,
                 owner: str | None = None, segment_bytes: int = SEGMENT_BYTES,
                 segment_records: int = SEGMENT_RECORDS,
                 state_interval_s: float = STATE_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if segment_bytes < 1 or segment_records < 1:
            raise ValueError("segment_bytes and segment_records must be ≥ 1")
        self.directory = Path(directory)
        self.fsync = fsync
        self.segment_bytes = segment_bytes
        self.segment_records = segment_records
        self.state_interval_s = state_interval_s
        self._clock = clock
        self.fsyncs = 0
        self.syncs = 0
        self.truncated_bytes = 0
        self._epoch = 0
        self._start = self._end = self._synced_end = self._released = 0
        self._owner: str | None = None
        self._last_state = 0.0
        self._segments: list[Segment] = []
        self._firsts: list[int] = []
        self._fd: int | None = None  # active (newest) segment, open for appending
        self._buf = bytearray()  # appended, not yet written to the OS
        self._tail: list[bytes] = []  # the datagrams in _buf, read from memory
        self._tail_first = 0  # seq of _tail[0]
        self._dir_dirty = False
        self._rfd: tuple[int, int] | None = None  # (segment first, fd) of the last read
        self._cursor: Cursor = (-1, -1, 0)  # (segment, next seq, its offset)
        self._rejected: set[int] = set()
        self._state_dirty = False
        self._closed = False
        self._broken = ""  # why the journal became unusable (a failed write or sync)
        self._lock_fd = -1
        self._dir_fd = -1
        try:
            self._open(owner)
        except BaseException:
            self._release_fds()
            raise

    # --- Journal protocol ----------------------------------------------------------------------
    @property
    def epoch(self) -> int:
        """The sender's boot id, 1 … 2**63 − 1, fixed for the journal's life."""
        return self._epoch

    @property
    def start(self) -> int:
        """Oldest seq not yet released (== :attr:`end` when nothing is pending)."""
        return self._start

    @property
    def end(self) -> int:
        """Next seq to append."""
        return self._end

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, seq: int, datagram: bytes) -> None:
        """Add ``datagram`` as ``seq`` (== :attr:`end`); durable after the next :meth:`sync`.

        Raises:
            ValueError: ``seq`` is not :attr:`end`, or the datagram is empty or too long.
            SenderError: the disk write failed.
        """
        self._check_open()
        if seq != self._end:
            raise ValueError(f"append of seq {seq}, the journal's next seq is {self._end}")
        if not 0 < len(datagram) <= MAX_RECORD:
            raise ValueError(f"a datagram of {len(datagram)} bytes cannot be journaled "
                             f"(1 … {MAX_RECORD})")
        if seq >= MAX_SEQ:
            raise ValueError("sequence numbers are < 2**63")
        rec = encode_record(seq, bytes(datagram))
        seg = self._segments[-1] if self._segments else None
        if (seg is None or seg.end != seq or seg.end - seg.first >= self.segment_records
                or (seg.size >= self.segment_bytes and seg.end > seg.first)):
            seg = self._roll(seq)
        if not self._tail:
            self._tail_first = seq
        self._buf += rec
        self._tail.append(rec[REC.size:])
        seg.add(len(rec))
        self._end = seq + 1
        if len(self._buf) >= _WRITE_OUT:
            self._write_out()

    def sync(self) -> None:
        """Make every appended datagram durable: write the buffer and fsync the active segment
        (and the directory once after a new segment was created). A no-op when nothing was
        appended since the last call.

        Raises:
            SenderError: the write or fsync failed (the data may not be durable).
        """
        self._check_open()
        if self._synced_end == self._end and not self._dir_dirty:
            return
        self._write_out()
        try:
            if self.fsync and self._fd is not None:
                os.fsync(self._fd)
                self.fsyncs += 1
            if self._dir_dirty:
                self._fsync_dir()
                self._dir_dirty = False
        except OSError as exc:
            raise self._fail(f"cannot sync the journal in {self.directory}: {exc}") from exc
        self._synced_end = self._end
        self.syncs += 1

    def read(self, seq: int, limit: int) -> list[bytes]:
        """Datagrams ``seq``, ``seq + 1``, … (below :attr:`end`), at most ``limit`` of them.

        Reading on from where the previous read stopped continues in the file without a lookup.

        Raises:
            ValueError: ``seq`` is below :attr:`start` or above :attr:`end`.
            SenderError: a record on disk no longer matches its checksum.
        """
        self._check_open()
        if not self._start <= seq <= self._end:
            raise ValueError(f"read of seq {seq} outside the journal's {self._start} … "
                             f"{self._end}")
        n = min(limit, self._end - seq)
        if n <= 0:
            return []
        stop = seq + n
        disk_stop = min(stop, self._tail_first) if self._tail else stop
        out: list[bytes] = []
        i = bisect.bisect_right(self._firsts, seq) - 1
        n = max(0, disk_stop - seq)
        while len(out) < n:
            seg = self._segments[i]
            if seq < seg.end:
                k = min(n - len(out), seg.end - seq)
                out += self._read_segment(seg, seq, k)
                seq += k
            i += 1
        if stop > disk_stop:  # appended since the buffer was last written: from memory
            lo = max(seq, self._tail_first) - self._tail_first
            out += self._tail[lo:stop - self._tail_first]
        return out

    def release(self, below: int) -> None:
        """Every seq below ``below`` was acknowledged: move :attr:`start` and delete the segments
        that hold only released datagrams. The watermark reaches the disk at most every
        ``state_interval_s`` and on :meth:`close`.

        Raises:
            ValueError: ``below`` is above :attr:`end`.
        """
        self._check_open()
        if below > self._end:
            raise ValueError(f"release below {below}, beyond the journal's end {self._end}")
        if below <= self._start:
            return
        if below > self._synced_end:
            self.sync()  # the watermark never passes data that is not durable
        self._advance(below)

    def reject(self, seq: int, datagram: bytes, reason: str) -> None:
        """The server refused ``seq`` for good: keep it for the operator in ``rejected.log`` (a
        JSON line with time, epoch, seq, reason and the datagram in hex, synced) and count it as
        released.

        Raises:
            ValueError: ``seq`` is not below :attr:`end`.
            SenderError: rejected.log cannot be written.
        """
        self._check_open()
        if not 0 <= seq < self._end:
            raise ValueError(f"reject of seq {seq}, the journal ends at {self._end}")
        if seq >= self._synced_end:
            self.sync()  # a refused seq is durable: a crash can never hand it out again
        line = rejected_line(self._epoch, seq, reason, datagram)
        path = self.rejected_path
        try:
            self._write_file(path, line, os.O_APPEND)
        except OSError as exc:
            raise self._fail(f"cannot write {path}: {exc}") from exc
        log.warning("journal %s: seq %d (epoch %d) refused by the server (%s), kept in %s",
                    self.directory, seq, self._epoch, reason, path)
        if seq >= self._start:
            self._rejected.add(seq)
            if seq == self._start:
                self._advance(seq + 1)

    def last(self) -> bytes | None:
        """The newest datagram (seq :attr:`end` − 1), even if it was released: the newest
        segment is never deleted. None when the journal never held one (or it is gone after the
        end was moved up to the watermark). The sender continues its sample clock after it.

        Raises:
            SenderError: the record on disk no longer matches its checksum.
        """
        self._check_open()
        if not self._segments or self._segments[-1].end != self._end or self._end == 0:
            return None
        seg = self._segments[-1]
        if seg.end == seg.first:
            return None
        if self._tail:
            return self._tail[-1]
        return self._read_segment(seg, seg.end - 1, 1)[0]

    # --- lifecycle -----------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._closed

    def flush_state(self) -> None:
        """Write the release watermark now if it moved since it was last written."""
        self._check_open()
        if self._state_dirty:
            self._write_state()

    def close(self) -> None:
        """Sync, write the watermark and release the directory (idempotent). After a failed
        write or sync it only releases the files."""
        if self._closed:
            return
        if self._broken:
            self._closed = True
            self._release_fds()
            return
        try:
            self.sync()
            if self._state_dirty:
                self._write_state()
        finally:
            self._closed = True
            self._release_fds()

    def __enter__(self) -> FileJournal:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"FileJournal({str(self.directory)!r}, epoch={self._epoch}, start={self._start}, "
                f"end={self._end})")

    # --- internals -----------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"the journal {self.directory} is closed")
        if self._broken:
            raise SenderError(f"the journal {self.directory} is unusable after an earlier error "
                              f"({self._broken}); restart the sender: it resumes from what is "
                              "on disk")
