"""Opening the send journal: the directory lock, the state (epoch, watermark, owner), and
recovery of the segments — released ones deleted, a torn or corrupt tail of the newest one cut
away (the longest valid prefix is kept), damage anywhere else an error, a missing segment an
error; a new epoch only ever for an empty directory.

:class:`JournalRecovery` is the base of :class:`~cranetwin.ingest.journal.FileJournal`, which
calls :meth:`JournalRecovery._open` from its ``__init__``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os

from cranetwin.ingest.journal_disk import JournalDisk
from cranetwin.ingest.journal_files import (
    FILE_MODE,
    SEG_RE,
    Segment,
    SenderError,
    index_records,
    make_dirs,
)
from cranetwin.ingest.journal_state import load_rejected, new_epoch, read_state

__all__ = ["JournalRecovery"]

log = logging.getLogger("cranetwin.ingest.journal")


class JournalRecovery(JournalDisk):
    """Opening and recovery (base of :class:`~cranetwin.ingest.journal.FileJournal`)."""

    truncated_bytes: int

    def _open(self, owner: str | None) -> None:
        d = self.directory
        try:
            make_dirs(d)
            self._dir_fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY)
        except OSError as exc:
            raise SenderError(f"cannot use {d} as the send journal: {exc}") from exc
        self._lock()
        try:
            names = set(os.listdir(d))
        except OSError as exc:
            raise SenderError(f"cannot list the send journal {d}: {exc}") from exc
        names.discard("lock")
        if "state.tmp" in names:  # a state write interrupted before its rename
            names.discard("state.tmp")
            with contextlib.suppress(OSError):
                os.unlink(d / "state.tmp")
        segs = sorted((int(m.group(1)), n) for n in names if (m := SEG_RE.fullmatch(n)))
        if "state" not in names:
            if segs or "rejected.log" in names:
                raise SenderError(
                    f"the send journal {d} holds data but no state file (its epoch is unknown); "
                    "restore the state file or move the directory away to start a new journal")
            self._epoch = new_epoch()
            self._released = 0
            self._owner = owner
            self._write_state()
            log.info("journal %s: new, epoch %d", d, self._epoch)
        else:
            self._epoch, self._released, self._owner = read_state(d)
            if owner is not None and self._owner is not None and owner != self._owner:
                raise SenderError(
                    f"the send journal {d} belongs to {self._owner!r}, not {owner!r}: its "
                    "datagrams were signed with another key; use another --journal directory "
                    "(or move this one away once its data is no longer needed)")
            if owner is not None and self._owner is None:
                self._owner = owner
                self._state_dirty = True
        self._load_segments(segs)
        self._load_rejected()
        self._last_state = self._clock()
        self._advance(self._start)
        if self._segments:
            log.info("journal %s: epoch %d, %d datagram(s) pending (seq %d … %d)", d,
                     self._epoch, self._end - self._start, self._start, self._end - 1)

    def _lock(self) -> None:
        path = self.directory / "lock"
        try:
            self._lock_fd = os.open(path, os.O_RDWR | os.O_CREAT, FILE_MODE)
        except OSError as exc:
            raise SenderError(f"cannot create {path}: {exc}") from exc
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise SenderError(f"cannot lock {path}: {exc}") from exc
            try:
                other = os.pread(self._lock_fd, 32, 0).decode(errors="replace").strip()
            except OSError:
                other = "?"
            raise SenderError(f"the send journal {self.directory} is in use by another sender "
                              f"(pid {other or '?'})") from None
        with contextlib.suppress(OSError):
            os.ftruncate(self._lock_fd, 0)
            os.pwrite(self._lock_fd, f"{os.getpid()}\n".encode(), 0)

    def _load_segments(self, segs: list[tuple[int, str]]) -> None:
        d = self.directory
        watermark = self._released
        # segments followed by one that starts at or below the watermark hold released data only
        while len(segs) > 1 and segs[1][0] <= watermark:
            self._unlink(d / segs.pop(0)[1])
        loaded: list[Segment] = []
        for k, (first, name) in enumerate(segs):
            seg = self._scan(Segment(first, d / name, end=first), last=k == len(segs) - 1)
            if loaded and seg.first != loaded[-1].end and seg.first > max(watermark,
                                                                          loaded[0].first):
                raise SenderError(
                    f"the send journal {d} lacks datagrams {loaded[-1].end} … {seg.first - 1} "
                    f"(between {loaded[-1].path.name} and {name}); was a segment removed?")
            loaded.append(seg)
        self._segments = loaded
        self._firsts = [s.first for s in loaded]
        last_end = loaded[-1].end if loaded else 0
        first = loaded[0].first if loaded else watermark
        if watermark > last_end:
            log.warning("journal %s: release watermark %d beyond the last record %d; "
                        "continuing at the watermark", d, watermark, last_end)
        self._end = max(last_end, watermark)
        self._start = min(max(watermark, first), self._end)
        self._synced_end = self._end
        if loaded:
            try:
                self._fd = os.open(loaded[-1].path, os.O_WRONLY | os.O_APPEND)
            except OSError as exc:
                raise SenderError(f"cannot open {loaded[-1].path}: {exc}") from exc

    def _scan(self, seg: Segment, *, last: bool) -> Segment:
        """Index the records of ``seg``; cut a torn or corrupt tail if it is the newest."""
        try:
            with open(seg.path, "rb") as f:
                data = f.read()
        except OSError as exc:
            raise SenderError(f"cannot read {seg.path}: {exc}") from exc
        pos, size = index_records(seg, data), len(data)
        if pos < size:
            if not last:
                raise SenderError(
                    f"{seg.path} is damaged at byte {pos} (record seq {seg.end}); it was sealed "
                    "and synced, so this is not a torn write. Move the file away to continue "
                    "without its datagrams")
            log.warning("journal %s: cutting %d byte(s) of a torn or corrupt tail after seq %d "
                        "(never synced, never sent)", seg.path, size - pos, seg.end - 1)
            try:
                fd = os.open(seg.path, os.O_WRONLY)
                try:
                    os.ftruncate(fd, pos)
                    if self.fsync:
                        os.fsync(fd)
                        self.fsyncs += 1
                finally:
                    os.close(fd)
            except OSError as exc:
                raise SenderError(f"cannot truncate {seg.path}: {exc}") from exc
            self.truncated_bytes += size - pos
        return seg

    def _load_rejected(self) -> None:
        """Seqs of this epoch at or above the watermark that the server refused before."""
        self._rejected |= load_rejected(self.rejected_path, self._epoch, self._start, self._end)
