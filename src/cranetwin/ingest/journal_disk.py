"""The send journal's disk side: the active segment (rolled, written out, sealed with an fsync),
reading records back, the atomic ``state`` file, deleting released segments, and closing the
descriptors. A failed write or sync makes the journal unusable (:meth:`JournalDisk._fail`).

:class:`JournalDisk` is the base of :class:`~cranetwin.ingest.journal.FileJournal`; its state is
set by the journal's ``__init__`` (see :mod:`cranetwin.ingest.journal` for the layout). The
record format and the segment index are :mod:`~cranetwin.ingest.journal_files`.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from pathlib import Path

from cranetwin.ingest.journal_files import (
    FILE_MODE,
    Cursor,
    Segment,
    SenderError,
    read_records,
    seg_name,
    write_all,
    write_file,
)
from cranetwin.ingest.journal_state import state_body

__all__ = ["JournalDisk"]

log = logging.getLogger("cranetwin.ingest.journal")


class JournalDisk:
    """Files of a journal directory (base of :class:`~cranetwin.ingest.journal.FileJournal`)."""

    directory: Path
    fsync: bool
    state_interval_s: float
    _clock: Callable[[], float]
    fsyncs: int
    _epoch: int
    _start: int
    _end: int
    _synced_end: int
    _released: int
    _owner: str | None
    _last_state: float
    _segments: list[Segment]
    _firsts: list[int]
    _fd: int | None
    _buf: bytearray
    _tail: list[bytes]
    _dir_dirty: bool
    _rfd: tuple[int, int] | None
    _cursor: Cursor
    _rejected: set[int]
    _state_dirty: bool
    _broken: str
    _lock_fd: int
    _dir_fd: int

    @property
    def rejected_path(self) -> Path:
        """The dead-letter file of refused datagrams (exists once one was refused)."""
        return self.directory / "rejected.log"

    def _write_state(self) -> None:
        """Persist epoch and watermark atomically: temp file, fsync, rename, directory fsync."""
        d = self.directory
        tmp, path = d / "state.tmp", d / "state"
        body = state_body(self._epoch, self._released, self._owner)
        try:
            self._write_file(tmp, body, os.O_TRUNC)
            os.replace(tmp, path)
            self._fsync_dir()
        except OSError as exc:
            raise self._fail(f"cannot write the journal state {path}: {exc}") from exc
        self._state_dirty = False
        self._last_state = self._clock()


    def _fail(self, message: str) -> SenderError:
        """A write or sync failed: what reached the disk is unknown (and a retried fsync may
        report success for data it lost), so every further call fails and :meth:`close`
        only lets go of the files. Reopening recovers the synced prefix."""
        self._broken = message
        return SenderError(message)

    def _advance(self, below: int) -> None:
        """Set start to ``below`` (then past refused seqs) and delete released segments."""
        start = below
        while start in self._rejected:
            start += 1
        if start != self._start or below > self._released:
            self._start = start
            self._released = max(self._released, start)
            self._state_dirty = True
        self._rejected = {s for s in self._rejected if s >= start}
        while len(self._segments) > 1 and self._segments[1].first <= start:
            seg = self._segments.pop(0)
            self._firsts.pop(0)
            if self._rfd is not None and self._rfd[0] == seg.first:
                os.close(self._rfd[1])
                self._rfd = None
            self._unlink(seg.path)
        if self._state_dirty and self._clock() - self._last_state >= self.state_interval_s:
            self._write_state()

    def _roll(self, seq: int) -> Segment:
        """Seal the active segment (write + fsync) and start ``seg-<seq>.log``."""
        if self._fd is not None:
            self._write_out()
            try:
                if self.fsync and self._synced_end < self._segments[-1].end:
                    os.fsync(self._fd)
                    self.fsyncs += 1
                os.close(self._fd)
            except OSError as exc:
                raise self._fail(f"cannot seal {self._segments[-1].path}: {exc}") from exc
            self._fd = None
            self._synced_end = max(self._synced_end, self._segments[-1].end)
        path = self.directory / seg_name(seq)
        try:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND,
                               FILE_MODE)
        except OSError as exc:
            raise self._fail(f"cannot create {path}: {exc}") from exc
        seg = Segment(seq, path, end=seq)
        self._segments.append(seg)
        self._firsts.append(seq)
        self._dir_dirty = True
        return seg

    def _write_out(self) -> None:
        if not self._buf:
            return
        assert self._fd is not None
        try:
            write_all(self._fd, self._buf)
        except OSError as exc:
            raise self._fail(f"cannot write to {self._segments[-1].path}: {exc}") from exc
        self._buf.clear()
        self._tail.clear()

    def _read_segment(self, seg: Segment, seq: int, n: int) -> list[bytes]:
        """``n`` datagrams from ``seq`` in ``seg`` (all of them on disk, not in the buffer)."""
        if self._rfd is None or self._rfd[0] != seg.first:
            if self._rfd is not None:
                os.close(self._rfd[1])
                self._rfd = None
            try:
                self._rfd = (seg.first, os.open(seg.path, os.O_RDONLY))
            except OSError as exc:
                raise SenderError(f"cannot open {seg.path}: {exc}") from exc
        out, self._cursor = read_records(self._rfd[1], seg, seq, n, self._cursor)
        return out

    def _write_file(self, path: Path, data: bytes, mode_flag: int) -> None:
        """Write ``data`` to ``path`` (created 0600; ``os.O_APPEND`` or ``os.O_TRUNC``) and
        fsync it when the journal syncs. Raises OSError."""
        self.fsyncs += write_file(path, data, mode_flag, self.fsync)

    def _fsync_dir(self) -> None:
        if self.fsync:
            os.fsync(self._dir_fd)
            self.fsyncs += 1

    def _unlink(self, path: Path) -> None:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("journal: cannot delete %s: %s", path, exc)

    def _release_fds(self) -> None:
        for fd in (self._fd, None if self._rfd is None else self._rfd[1], self._dir_fd,
                   self._lock_fd):
            if fd is not None and fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._fd, self._rfd, self._dir_fd, self._lock_fd = None, None, -1, -1
