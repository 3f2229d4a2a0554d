"""Segment files of the send journal: the record format, indexing a segment, reading records
back, and the small file helpers (mode 0600 files, 0700 directories, whole writes).

A record is ``u32 length ‖ u32 crc32(seq ‖ datagram) ‖ u64 seq ‖ datagram`` (big endian); a
segment ``seg-<first seq:020d>.log`` holds consecutive seqs from ``first``. See
:mod:`cranetwin.ingest.journal` for how the journal uses them.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from cranetwin.errors import ProtocolError

REC = struct.Struct(">IIQ")  # length of the datagram, crc32 of (seq ‖ datagram), seq
MAX_RECORD = 65_507  # largest UDP payload [bytes]
MAX_SEQ = 2**63  # sequence numbers are < 2**63
SEG_RE = re.compile(r"seg-(\d{20})\.log")
SPARSE = 64  # a file offset is kept for every 64th record of a segment
READ_BLOCK = 256 << 10
FILE_MODE = 0o600
DIR_MODE = 0o700


class SenderError(ProtocolError):
    """The sender could not start or continue: bad address, bad key, or an unusable journal."""


def seg_name(first: int) -> str:
    """File name of the segment whose first record is ``first``."""
    return f"seg-{first:020d}.log"


def crc(seq_bytes: bytes | memoryview, datagram: bytes | memoryview) -> int:
    """crc32 of ``seq ‖ datagram``."""
    return zlib.crc32(datagram, zlib.crc32(seq_bytes)) & 0xFFFFFFFF


def encode_record(seq: int, datagram: bytes) -> bytes:
    """One journal record: ``u32 length ‖ u32 crc32(seq ‖ datagram) ‖ u64 seq ‖ datagram``."""
    seq_bytes = seq.to_bytes(8, "big")
    return REC.pack(len(datagram), crc(seq_bytes, datagram), seq) + datagram


@dataclass
class Segment:
    """One segment file: records ``first`` … ``end − 1`` in ``size`` bytes."""

    first: int
    path: Path
    end: int = 0
    size: int = 0
    marks: list[int] = field(default_factory=list)  # offset of record first + k·SPARSE

    def add(self, record_bytes: int) -> None:
        if (self.end - self.first) % SPARSE == 0:
            self.marks.append(self.size)
        self.end += 1
        self.size += record_bytes


def index_records(seg: Segment, data: bytes) -> int:
    """Index the valid records of ``data`` (the file of ``seg``) into ``seg``.

    Returns:
        The offset where the valid prefix ends (== len(data) when every record is valid).
    """
    mv = memoryview(data)
    pos, size = 0, len(data)
    while pos < size:
        if pos + REC.size > size:
            break
        length, c, seq = REC.unpack_from(mv, pos)
        end = pos + REC.size + length
        if (length == 0 or length > MAX_RECORD or end > size or seq != seg.end
                or crc(mv[pos + 8:pos + 16], mv[pos + 16:end]) != c):
            break
        seg.add(end - pos)
        pos = end
    return pos


Cursor = tuple[int, int, int]
"""Where the last read stopped: (segment first, next seq, its file offset)."""


def read_records(fd: int, seg: Segment, seq: int, n: int, cursor: Cursor
                 ) -> tuple[list[bytes], Cursor]:
    """``n`` datagrams from ``seq`` in ``seg`` (open as ``fd``; all of them on disk).

    Continues from ``cursor`` without a lookup when it points at ``seq``; else starts at the
    nearest sparse mark.

    Raises:
        SenderError: a record no longer matches its checksum, or the file is short.
    """
    if cursor[:2] == (seg.first, seq):
        pos, at = cursor[2], seq
    else:
        k = (seq - seg.first) // SPARSE
        pos, at = seg.marks[k], seg.first + k * SPARSE
    out: list[bytes] = []
    block, bpos = b"", pos  # file bytes [bpos, bpos + len(block))
    while len(out) < n:
        need = pos + REC.size - bpos
        if need > len(block):
            block, bpos = _pread(fd, seg, pos, REC.size), pos
        length, c, rseq = REC.unpack_from(block, pos - bpos)
        end = pos + REC.size + length
        if end - bpos > len(block):
            block, bpos = _pread(fd, seg, pos, REC.size + length), pos
        body = block[pos - bpos + REC.size:end - bpos]
        if rseq != at or crc(block[pos - bpos + 8:pos - bpos + 16], body) != c:
            raise SenderError(f"{seg.path}: record seq {at} at byte {pos} no longer matches "
                              "its checksum (disk damage?)")
        if at >= seq:
            out.append(bytes(body))
        at += 1
        pos = end
    return out, (seg.first, at, pos)


def _pread(fd: int, seg: Segment, pos: int, need: int) -> bytes:
    want = max(need, min(READ_BLOCK, seg.size - pos))
    try:
        data = os.pread(fd, want, pos)
    except OSError as exc:
        raise SenderError(f"cannot read {seg.path}: {exc}") from exc
    if len(data) < need:
        raise SenderError(f"{seg.path} is shorter than its index ({pos + len(data)} < "
                          f"{pos + need} bytes): changed behind the sender's back?")
    return data


def write_file(path: Path, data: bytes, mode_flag: int, fsync: bool) -> int:
    """Write ``data`` to ``path`` (created 0600; ``os.O_APPEND`` or ``os.O_TRUNC``), fsynced
    when ``fsync``. Returns the number of fsyncs made. Raises OSError."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | mode_flag, FILE_MODE)
    try:
        write_all(fd, data)
        if fsync:
            os.fsync(fd)
            return 1
        return 0
    finally:
        os.close(fd)


def make_dirs(d: Path) -> None:
    """Create ``d`` and its missing parents with mode 0700."""
    missing: list[Path] = []
    p = d
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    for q in reversed(missing):
        with contextlib.suppress(FileExistsError):
            os.mkdir(q, DIR_MODE)
    if not d.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "not a directory", str(d))


def write_all(fd: int, data: bytes | bytearray) -> None:
    """``os.write`` until every byte of ``data`` is written."""
    mv = memoryview(data)
    while mv:
        n = os.write(fd, mv)
        mv = mv[n:]
