"""The sender's durable journal (:class:`cranetwin.ingest.journal.FileJournal`): round trip,
resume, torn tails, kill -9 of a writing process, segment deletion, file modes, and a stateful
property test against a model (append / sync / release / reject / reopen / crash)."""

from __future__ import annotations

import json
import os
import random
import select
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from cranetwin.ingest.journal import MAX_SEQ, FileJournal, SenderError, encode_record

try:
    from cranetwin.protocol import Journal
except ImportError:  # the sans-IO protocol's Journal is not there yet: the contract's copy
    from typing import Protocol

    class Journal(Protocol):  # type: ignore[no-redef]
        @property
        def epoch(self) -> int: ...
        @property
        def start(self) -> int: ...
        @property
        def end(self) -> int: ...
        def append(self, seq: int, datagram: bytes) -> None: ...
        def sync(self) -> None: ...
        def read(self, seq: int, limit: int) -> list[bytes]: ...
        def release(self, below: int) -> None: ...
        def reject(self, seq: int, datagram: bytes, reason: str) -> None: ...
        def __len__(self) -> int: ...


def dg(seq: int) -> bytes:
    """A datagram whose content and length depend on its seq only."""
    return seq.to_bytes(8, "big") * (1 + seq % 7) + b"|"


def segments(d: Path) -> list[str]:
    return sorted(p.name for p in d.glob("seg-*.log"))


def fill(j: FileJournal, n: int) -> None:
    for _ in range(n):
        j.append(j.end, dg(j.end))


def crash(j: FileJournal) -> None:
    """What a kill -9 leaves: what was written to the OS stays, the user-space buffer is gone,
    the lock is released, nothing is synced or persisted on the way out."""
    j._buf.clear()
    j._tail.clear()
    j._release_fds()
    j._closed = True


@pytest.mark.timeout(20)
def test_round_trip_across_segments(tmp_path: Path) -> None:
    j: Journal = FileJournal(tmp_path / "j", segment_records=100, segment_bytes=1 << 20)
    assert isinstance(j, FileJournal)
    assert 0 < j.epoch < MAX_SEQ and j.start == j.end == len(j) == 0
    fill(j, 1000)
    assert len(j) == 1000 and j.end == 1000
    assert j.read(0, 2000) == [dg(s) for s in range(1000)]  # before sync: from the OS buffer
    j.sync()
    assert len(segments(tmp_path / "j")) == 10
    assert j.read(777, 5) == [dg(s) for s in range(777, 782)]  # sparse index, mid-segment
    chunks: list[bytes] = []
    while len(chunks) < 1000:  # sequential reading in odd chunks crosses segment borders
        chunks += j.read(len(chunks), 37)
    assert chunks == [dg(s) for s in range(1000)]
    assert j.read(1000, 10) == [] and j.read(5, 0) == []
    with pytest.raises(ValueError):
        j.read(1001, 1)
    with pytest.raises(ValueError):
        j.append(999, b"x")  # not the next seq
    with pytest.raises(ValueError):
        j.append(1000, b"")
    j.close()


@pytest.mark.timeout(20)
def test_reopen_resumes_with_the_same_epoch(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=64)
    epoch = j.epoch
    fill(j, 300)
    j.release(130)
    j.close()
    j = FileJournal(d, segment_records=64)
    assert (j.epoch, j.start, j.end) == (epoch, 130, 300)
    assert j.read(130, 1000) == [dg(s) for s in range(130, 300)]
    fill(j, 10)  # continues at 300
    j.close()
    j = FileJournal(d, segment_records=64)
    assert (j.epoch, j.start, j.end) == (epoch, 130, 310)
    assert j.read(299, 20) == [dg(s) for s in range(299, 310)]
    j.close()
    other = FileJournal(tmp_path / "other")
    assert other.epoch != epoch  # 63 random bits
    other.close()


@pytest.mark.timeout(20)
def test_a_crash_loses_only_what_was_not_synced(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=50, state_interval_s=3600)
    fill(j, 120)
    j.sync()
    j.release(60)  # not persisted (interval): start comes back lower, never higher
    fill(j, 7)  # never synced
    crash(j)
    j = FileJournal(d, segment_records=50)
    assert j.end == 120 and 50 <= j.start <= 60  # segment 0…49 was deleted, so ≥ 50
    assert j.read(j.start, 200) == [dg(s) for s in range(j.start, 120)]
    j.close()


def _last_record_offset(path: Path) -> int:
    data, pos, last = path.read_bytes(), 0, 0
    while pos < len(data):
        last = pos
        pos += 16 + int.from_bytes(data[pos:pos + 4], "big")
    return last


@pytest.mark.timeout(20)
@pytest.mark.parametrize("damage", ["cut_header", "cut_body", "flip_body", "flip_crc",
                                    "flip_seq", "zeros", "garbage_length"])
def test_a_torn_or_corrupt_tail_is_cut_and_everything_before_kept(tmp_path: Path,
                                                                   damage: str) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=40)
    fill(j, 100)
    j.close()
    last = d / segments(d)[-1]  # seq 80 … 99
    size = last.stat().st_size
    off = _last_record_offset(last)  # record 99
    data = bytearray(last.read_bytes())
    if damage == "cut_header":
        data = data[:off + 7]
    elif damage == "cut_body":
        data = data[:size - 3]
    elif damage == "flip_body":
        data[size - 2] ^= 0x40
    elif damage == "flip_crc":
        data[off + 5] ^= 0x01
    elif damage == "flip_seq":
        data[off + 15] ^= 0x02
    elif damage == "zeros":  # a file extended by the kernel but never written
        data = data[:off] + bytes(64)
    elif damage == "garbage_length":
        data[off:off + 4] = (1 << 31).to_bytes(4, "big")
    last.write_bytes(bytes(data))
    j = FileJournal(d, segment_records=40)
    assert j.end == 99 and j.truncated_bytes > 0
    assert j.read(0, 200) == [dg(s) for s in range(99)]
    assert last.stat().st_size == off
    fill(j, 3)  # seq 99 is written anew and the journal goes on
    j.close()
    j = FileJournal(d, segment_records=40)
    assert j.read(0, 200) == [dg(s) for s in range(102)] and j.truncated_bytes == 0
    j.close()


@pytest.mark.timeout(20)
def test_damage_in_a_sealed_segment_is_an_error_not_a_silent_cut(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=40)
    fill(j, 100)
    j.close()
    first = d / segments(d)[0]
    data = bytearray(first.read_bytes())
    data[200] ^= 0xFF
    first.write_bytes(bytes(data))
    with pytest.raises(SenderError, match="damaged"):
        FileJournal(d, segment_records=40)
    first.write_bytes(bytes(data[:200]))  # cut short instead: still not a torn write
    with pytest.raises(SenderError, match="damaged"):
        FileJournal(d, segment_records=40)
    first.unlink()  # the oldest segment gone: as if released (start moves up to 40)
    j = FileJournal(d, segment_records=40)
    assert (j.start, j.end) == (40, 100)
    j.close()
    (d / segments(d)[0]).unlink()  # a middle one gone would hide pending data: an error
    fill_j = FileJournal(tmp_path / "k", segment_records=40)
    fill(fill_j, 100)
    fill_j.close()
    (tmp_path / "k" / segments(tmp_path / "k")[1]).unlink()
    with pytest.raises(SenderError, match="lacks datagrams 40 … 79"):
        FileJournal(tmp_path / "k", segment_records=40)


@pytest.mark.timeout(20)
def test_unreadable_state_is_an_error_and_never_a_new_epoch(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d)
    fill(j, 5)
    j.close()
    state = d / "state"
    good = state.read_bytes()
    for bad in (b"", b"{", b'{"format": "cranetwin-send-journal", "version": 1, "epoch": 0, '
                b'"released": 0}', json.dumps({**json.loads(good), "released": -1}).encode()):
        state.write_bytes(bad)
        with pytest.raises(SenderError, match="corrupt"):
            FileJournal(d)
    state.unlink()
    with pytest.raises(SenderError, match="no state file"):
        FileJournal(d)
    state.write_bytes(good)
    j = FileJournal(d)
    assert j.end == 5
    j.close()
    file_not_dir = tmp_path / "plain"
    file_not_dir.write_text("x")
    with pytest.raises(SenderError, match="cannot use"):
        FileJournal(file_not_dir)
    state_dir = tmp_path / "k"
    (state_dir / "state").mkdir(parents=True)
    with pytest.raises(SenderError, match="state"):
        FileJournal(state_dir)
    leftover = tmp_path / "fresh"  # an interrupted first state write: still a new journal
    leftover.mkdir()
    (leftover / "state.tmp").write_text("{")
    j = FileJournal(leftover)
    assert j.end == 0 and not (leftover / "state.tmp").exists()
    j.close()


@pytest.mark.timeout(20)
def test_one_process_at_a_time_and_owner_is_checked(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, owner="m1 wire 1 key ab")
    with pytest.raises(SenderError, match="in use by another sender"):
        FileJournal(d)
    j.close()
    with pytest.raises(SenderError, match="belongs to"):
        FileJournal(d, owner="m1 wire 1 key cd")
    FileJournal(d, owner="m1 wire 1 key ab").close()
    FileJournal(d).close()  # no owner given: not checked


@pytest.mark.timeout(20)
def test_release_deletes_whole_segments_and_keeps_the_next_seq(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=10, state_interval_s=0)
    fill(j, 35)
    j.sync()
    assert len(segments(d)) == 4
    j.release(19)
    assert segments(d) == ["seg-00000000000000000010.log", "seg-00000000000000000020.log",
                           "seg-00000000000000000030.log"]
    with pytest.raises(ValueError):
        j.read(18, 1)  # released
    j.release(35)  # everything acked: only the newest segment stays, so 35 is not reused
    assert segments(d) == ["seg-00000000000000000030.log"] and len(j) == 0
    with pytest.raises(ValueError):
        j.release(36)
    crash(j)
    j = FileJournal(d, segment_records=10)
    assert (j.start, j.end) == (35, 35)
    j.append(35, dg(35))
    j.close()


@pytest.mark.timeout(20)
def test_last_is_the_newest_datagram_even_when_released(tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d, segment_records=10)
    assert j.last() is None
    fill(j, 25)
    assert j.last() == dg(24)  # still in the append buffer
    j.sync()
    j.release(25)
    assert j.last() == dg(24) and len(j) == 0
    j.close()
    j = FileJournal(d, segment_records=10)
    assert j.last() == dg(24)  # from disk
    fill(j, 1)
    assert j.last() == dg(25)
    j.close()


@pytest.mark.timeout(20)
def test_the_watermark_is_written_at_most_every_interval(tmp_path: Path) -> None:
    now = [0.0]
    d = tmp_path / "j"
    j = FileJournal(d, state_interval_s=0.5, clock=lambda: now[0])
    fill(j, 100)
    j.sync()
    f0 = j.fsyncs
    for below in range(1, 51):
        j.release(below)
        now[0] += 0.01  # 50 releases within 0.5 s: none written
    assert j.fsyncs == f0 and json.loads((d / "state").read_text())["released"] == 0
    now[0] += 0.5
    j.release(51)
    assert j.fsyncs == f0 + 2  # the temp file and the directory
    assert json.loads((d / "state").read_text())["released"] == 51
    j.release(60)
    j.close()  # the last watermark on close
    assert json.loads((d / "state").read_text())["released"] == 60


@pytest.mark.timeout(20)
def test_one_fsync_per_sync_and_none_when_idle(tmp_path: Path) -> None:
    j = FileJournal(tmp_path / "j", segment_records=1000)
    fill(j, 1)
    j.sync()  # the first segment: file + directory
    f0 = j.fsyncs
    for _ in range(20):
        fill(j, 5)
        j.sync()
    assert j.fsyncs == f0 + 20 and j.syncs == 21
    j.sync()
    assert j.fsyncs == f0 + 20  # nothing new: no fsync
    j.close()


@pytest.mark.timeout(20)
def test_rejected_datagrams_go_to_the_dead_letter_file_and_count_as_released(
        tmp_path: Path) -> None:
    d = tmp_path / "j"
    j = FileJournal(d)
    fill(j, 10)
    j.sync()
    j.reject(3, dg(3), "out_of_range")
    assert j.start == 0  # 0 … 2 still pending
    j.release(3)
    assert j.start == 4  # 3 was refused: released with them
    j.reject(5, dg(5), "bad_time")
    j.close()
    j = FileJournal(d)
    assert j.start == 4
    j.release(5)
    assert j.start == 6  # the refusal of 5 survived the restart
    lines = [json.loads(x) for x in (d / "rejected.log").read_text().splitlines()]
    assert [(x["seq"], x["reason"], x["epoch"]) for x in lines] == [
        (3, "out_of_range", j.epoch), (5, "bad_time", j.epoch)]
    assert bytes.fromhex(lines[0]["datagram"]) == dg(3) and "T" in lines[0]["time"]
    j.reject(6, dg(6), "unstorable")  # the oldest one: released at once
    assert j.start == 7
    j.close()


@pytest.mark.timeout(20)
def test_files_0600_and_directories_0700(tmp_path: Path) -> None:
    old = os.umask(0o002)  # even with a permissive umask
    try:
        d = tmp_path / "a" / "b" / "j"
        j = FileJournal(d, segment_records=2)
        fill(j, 5)
        j.sync()
        j.reject(0, dg(0), "x")
        j.close()
    finally:
        os.umask(old)
    for p in (tmp_path / "a", tmp_path / "a" / "b", d):
        assert stat.S_IMODE(p.stat().st_mode) == 0o700, p
    files = list(d.iterdir())
    assert {p.name for p in files} >= {"lock", "state", "rejected.log"}
    for p in files:
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p


def test_record_layout() -> None:
    rec = encode_record(7, b"abc")
    assert rec[:4] == (3).to_bytes(4, "big") and rec[8:16] == (7).to_bytes(8, "big")
    assert rec[16:] == b"abc"


# --- kill -9 of a process that appends and syncs -------------------------------------------------
_CHILD = """
from cranetwin.ingest.journal import FileJournal
def dg(seq):
    return seq.to_bytes(8, "big") * (1 + seq % 7) + b"|"
j = FileJournal({d!r}, segment_records=50, state_interval_s=0.05)
print("start", j.start, j.end, flush=True)
k = 0
while True:
    for _ in range(1 + k % 9):
        j.append(j.end, dg(j.end))
    j.sync()
    print(j.end - 1, flush=True)
    k += 1
    if k % 7 == 0 and len(j) > 120:
        j.release(j.end - 100)
"""


@pytest.mark.timeout(90)
def test_kill_9_while_appending_loses_nothing_that_was_synced(tmp_path: Path) -> None:
    d = tmp_path / "j"
    rng = random.Random(1)
    code = _CHILD.format(d=str(d))
    synced_max = -1
    epoch = None
    for _round in range(6):
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, bufsize=1)
        assert p.stdout is not None
        head = p.stdout.readline().split()
        assert head[0] == "start", p.stderr.read() if p.stderr else ""
        assert int(head[2]) >= synced_max + 1  # the child resumed after everything synced
        deadline = time.monotonic() + rng.uniform(0.05, 0.6)
        while time.monotonic() < deadline:
            r, _, _ = select.select([p.stdout], [], [], 0.01)
            if r:
                line = p.stdout.readline()
                synced_max = max(synced_max, int(line))
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
        for line in p.stdout:  # lines printed before the kill, still in the pipe
            synced_max = max(synced_max, int(line))
        p.stdout.close()
        assert p.stderr is not None
        p.stderr.close()
        j = FileJournal(d, segment_records=50)
        epoch = epoch or j.epoch
        assert j.epoch == epoch
        assert j.end > synced_max, (j.end, synced_max)
        got = j.read(j.start, j.end - j.start)
        assert got == [dg(s) for s in range(j.start, j.end)]
        j.close()
    assert synced_max > 100  # the child did write a lot


# --- stateful property: the journal equals a model through any sequence of operations ----------
class JournalModel(RuleBasedStateMachine):
    """Model: ``data`` (seq → datagram, every seq ever appended and not lost), ``start``,
    ``synced`` (end of the durable prefix). A clean reopen keeps everything; a crash keeps at
    least the synced prefix and at most what was appended; either may resend released data
    (start comes back at or below the model's) but never loses pending data."""

    def __init__(self) -> None:
        super().__init__()
        import tempfile

        self.tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self.tmp.name) / "j"
        self.now = 0.0
        self.data: dict[int, bytes] = {}
        self.start = 0
        self.synced = 0
        self.rejected: set[int] = set()

    def _open(self) -> FileJournal:
        return FileJournal(self.dir, fsync=False, segment_records=4, segment_bytes=200,
                           state_interval_s=0.5, clock=lambda: self.now)

    @initialize()
    def first_open(self) -> None:
        self.j = self._open()
        self.epoch = self.j.epoch

    @property
    def end(self) -> int:
        return self.j.end

    @rule(sizes=st.lists(st.integers(1, 120), min_size=1, max_size=12), salt=st.integers(0, 255))
    def append(self, sizes: list[int], salt: int) -> None:
        for n in sizes:
            seq = self.j.end
            d = bytes([salt]) * n + seq.to_bytes(8, "big")
            self.j.append(seq, d)
            self.data[seq] = d

    @rule()
    def sync(self) -> None:
        self.j.sync()
        self.synced = self.j.end

    @rule(frac=st.floats(0, 1))
    def release(self, frac: float) -> None:
        below = self.start + int(round(frac * (self.j.end - self.start)))
        self.j.release(below)
        if below > self.start:
            self.start = below
            self.synced = max(self.synced, below)
            while self.start in self.rejected:
                self.start += 1

    @precondition(lambda self: self.j.end > self.start)
    @rule(frac=st.floats(0, 1))
    def reject(self, frac: float) -> None:
        seq = self.start + int(frac * (self.j.end - self.start - 1))
        self.j.reject(seq, self.data[seq], "test")
        self.rejected.add(seq)
        self.synced = max(self.synced, seq + 1)  # a refused datagram is made durable first
        if seq == self.start:
            while self.start in self.rejected:
                self.start += 1

    @rule(dt=st.floats(0, 1))
    def tick(self, dt: float) -> None:
        self.now += dt

    @rule()
    def reopen(self) -> None:
        self.j.close()
        self.j = self._open()
        self.synced = self.j.end
        assert self.j.start == self.start
        self.read(0.0, 10_000)

    @rule(cut=st.floats(0, 1), garbage=st.binary(max_size=40))
    def crash(self, cut: float, garbage: bytes) -> None:
        appended = self.j.end
        crash(self.j)
        # a torn tail: the newest segment is cut anywhere after its synced records, then garbage
        segs = segments(self.dir)
        if segs:
            last = self.dir / segs[-1]
            first = int(segs[-1][4:24])
            raw = last.read_bytes()
            keep, pos, seq = 0, 0, first
            while pos < len(raw):
                pos += 16 + int.from_bytes(raw[pos:pos + 4], "big")
                seq += 1
                if seq <= self.synced:
                    keep = pos
            cut_at = keep + int(cut * (len(raw) - keep))
            last.write_bytes(raw[:cut_at] + garbage)
        self.j = self._open()
        assert self.j.epoch == self.epoch
        assert self.synced <= self.j.end <= appended
        for s in range(self.j.end, appended):
            del self.data[s]
        self.rejected = {s for s in self.rejected if s < self.j.end}
        # released data may come back (its release was not persisted): the model follows
        assert self.j.start <= min(self.start, self.j.end)
        self.start = self.j.start
        self.synced = self.j.end
        self.read(0.0, 10_000)

    @invariant()
    def matches_model(self) -> None:
        j = self.j
        assert j.epoch == self.epoch
        assert j.start == self.start, (j.start, self.start)
        assert len(j) == j.end - j.start

    @rule(frac=st.floats(0, 1), limit=st.integers(1, 1000))
    def read(self, frac: float, limit: int) -> None:
        """(A rule, not an invariant: reading hands the append buffer to the OS, which would
        hide a sync that does not.)"""
        j = self.j
        seq = j.start + int(frac * (j.end - j.start))
        assert j.read(seq, limit) == [self.data[s] for s in range(seq, min(j.end, seq + limit))]

    def teardown(self) -> None:
        if not self.j.closed:
            self.j.close()
        self.tmp.cleanup()


TestJournalModel = JournalModel.TestCase
TestJournalModel.settings = settings(max_examples=150, stateful_step_count=40, deadline=None,
                                     suppress_health_check=[HealthCheck.too_slow])
TestJournalModel = pytest.mark.timeout(240)(TestJournalModel)


@pytest.mark.timeout(20)
def test_a_failed_write_makes_the_journal_unusable_until_reopened(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After ENOSPC (or a failed fsync) nothing more is accepted (a retried fsync can report
    success for data it lost); reopening recovers everything synced before."""
    import errno

    d = tmp_path / "j"
    j = FileJournal(d)
    fill(j, 10)
    j.sync()
    fill(j, 5)
    real_write = os.write

    def full(fd: int, data: bytes | memoryview) -> int:
        n = real_write(fd, bytes(data)[:7])  # part of it reaches the file
        if n:
            raise OSError(errno.ENOSPC, "No space left on device")
        return n

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(SenderError, match="No space left"):
        j.sync()
    monkeypatch.setattr(os, "write", real_write)
    with pytest.raises(SenderError, match="unusable"):
        j.append(j.end, b"x")
    with pytest.raises(SenderError, match="unusable"):
        j.sync()
    j.close()  # only lets go
    j = FileJournal(d)
    assert j.end == 10 and j.truncated_bytes == 7
    assert j.read(0, 100) == [dg(s) for s in range(10)]
    j.close()
