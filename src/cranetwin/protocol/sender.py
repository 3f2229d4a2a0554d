"""Machine-side protocol state: batching, sequence numbers, retransmission, spill (sans-IO).

Fed samples (:meth:`Sender.push`), status (:meth:`Sender.push_status`), acks
(:meth:`Sender.receive`) and the current time; returns the datagrams to send
(:meth:`Sender.datagrams_to_send`) and when to call again (:meth:`Sender.next_timer_ns`). The
asyncio shell is :func:`cranetwin.ingest.sender.run_sender`.

Nothing is ever dropped: a datagram leaves the sender only when an ack covers it. At most
``max_unacked`` datagrams (≤ 1200 bytes each) are kept in memory; newer ones go to a
:class:`Spill` (a file on the machine, :class:`cranetwin.ingest.sender.FileSpill`) and come back
in order as acks free memory, so a link that is down for hours costs disk, not RAM. Each
in-memory datagram is retransmitted when its timer expires, with exponential backoff from
``rto_ns`` up to ``max_rto_ns``; the first ack after a silence resets the backoff of all
pending datagrams (next try one initial timeout after its last send) so that recovery starts at
once. Every transmission carries the current oldest unacknowledged seq (the ``lag`` field is
rewritten and the tag recomputed when it changed), so the receiver's replay window follows.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.protocol.ack import Ack, decode_ack
from cranetwin.protocol.data import DATA_FIXED_END, MAX_SAMPLES, encode_data
from cranetwin.protocol.status import STATUS_FIXED_END, StatusReport, encode_status
from cranetwin.protocol.wire import (
    HEADER_BYTES,
    MAX_DATAGRAM,
    TAG_BYTES,
    TYPE_DATA,
    MachineKey,
    get_varint,
    put_varint,
    tag,
)

F64 = npt.NDArray[np.float64]
_SEQ = struct.Struct(">Q")


class Spill(Protocol):
    """FIFO store for datagrams that do not fit in memory (oldest out first)."""

    def append(self, datagram: bytes) -> None:
        """Store ``datagram`` after all others."""

    def popleft(self) -> bytes:
        """Remove and return the oldest datagram (IndexError if empty)."""

    def __len__(self) -> int:
        """Number of datagrams stored."""


class MemorySpill:
    """A :class:`Spill` in memory (unbounded: for tests and short runs)."""

    def __init__(self) -> None:
        self._q: deque[bytes] = deque()

    def append(self, datagram: bytes) -> None:
        self._q.append(datagram)

    def popleft(self) -> bytes:
        return self._q.popleft()

    def __len__(self) -> int:
        return len(self._q)


@dataclass
class _Pending:
    datagram: bytes
    next_send_ns: int
    rto_ns: int
    sends: int = 0
    last_sent_ns: int = 0
    lag: int = -1  # seq − oldest_unacked written in the datagram (-1: not parsed yet)


def restamp_lag(datagram: bytes, secret: bytes, lag: int) -> bytes:
    """``datagram`` (data or status, made by this sender) with its lag field replaced and the tag
    recomputed. Retransmissions carry the current oldest unacknowledged seq this way, so the
    receiver's window moves past seqs that were acked meanwhile (e.g. after a restart left a gap
    in the sequence numbers)."""
    fixed = DATA_FIXED_END if datagram[3] == TYPE_DATA else STATUS_FIXED_END
    _, after = get_varint(datagram, fixed, len(datagram) - TAG_BYTES)
    out = bytearray(datagram[:fixed])
    put_varint(out, lag)
    out += datagram[after:-TAG_BYTES]
    out += tag(secret, out)
    return bytes(out)


def datagram_lag(datagram: bytes) -> int:
    """The lag field of a data or status datagram."""
    fixed = DATA_FIXED_END if datagram[3] == TYPE_DATA else STATUS_FIXED_END
    return get_varint(datagram, fixed, len(datagram) - TAG_BYTES)[0]


def datagram_seq(datagram: bytes) -> int:
    """Sequence number of a data or status datagram this sender made (bytes 8–15)."""
    return int(_SEQ.unpack_from(datagram, HEADER_BYTES)[0])


class Sender:
    """Protocol core of one machine's sender.

    Args:
        key: Machine identity, secret and layout.
        period_ns: Sample period [ns] (10_000_000 at 100 Hz).
        first_seq: First sequence number. Must exceed every seq this key ever used: persist
            :attr:`next_seq` across restarts, or derive it from a clock (the shell uses Unix
            milliseconds, which stays ahead as long as fewer than 1000 datagrams/s are sent).
        batch_samples: Samples per data datagram (1..4096); a batch whose datagram would exceed
            ``max_datagram`` bytes is split in halves.
        max_unacked: Datagrams kept in memory awaiting an ack (memory bound ≈ this × 1200 B).
        spill: Where datagrams beyond ``max_unacked`` wait (default: :class:`MemorySpill`).
        rto_ns: Initial retransmission timeout [ns].
        max_rto_ns: Backoff cap [ns].
        max_burst: Datagrams returned per :meth:`datagrams_to_send` call at most.
        max_datagram: Size limit of a datagram [bytes of UDP payload].
    """

    def __init__(self, key: MachineKey, period_ns: int, *, first_seq: int = 0,
                 batch_samples: int = 50, max_unacked: int = 512, spill: Spill | None = None,
                 rto_ns: int = 1_000_000_000, max_rto_ns: int = 30_000_000_000,
                 max_burst: int = 64, max_datagram: int = MAX_DATAGRAM) -> None:
        if not 1 <= batch_samples <= MAX_SAMPLES:
            raise ValueError(f"batch_samples must be in 1..{MAX_SAMPLES}, got {batch_samples}")
        if max_unacked < 1 or max_burst < 1 or rto_ns < 1 or max_rto_ns < rto_ns:
            raise ValueError("max_unacked, max_burst, rto_ns ≥ 1 and max_rto_ns ≥ rto_ns needed")
        self.key = key
        self.period_ns = int(period_ns)
        self.next_seq = int(first_seq)
        self.batch_samples = batch_samples
        self.max_unacked = max_unacked
        self.spill: Spill = spill if spill is not None else MemorySpill()
        self.rto_ns = rto_ns
        self.max_rto_ns = max_rto_ns
        self.max_burst = max_burst
        self.max_datagram = max_datagram
        self._pending: dict[int, _Pending] = {}  # insertion order = seq order
        self._buf: list[F64] = []
        self._buf_n = 0
        self._buf_t0 = 0
        self._last_ack_ns: int | None = None
        self._offsets: deque[int] = deque(maxlen=256)
        self.sent_datagrams = 0
        self.retransmissions = 0
        self.sent_bytes = 0
        self.acked_samples = 0
        self._samples_of: dict[int, int] = {}
        self._refill()  # a spill file left by an earlier run is sent first

    # --- input ---------------------------------------------------------------------------------
    def push(self, t0_ns: int, values: F64) -> None:
        """Queue samples taken at ``t0_ns + i·period_ns``.

        Args:
            t0_ns: Time of the first row [ns since the Unix epoch, machine clock].
            values: Shape (m, c), layout column order [channel units]; NaN = missing.
        """
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != len(self.key.layout.channels):
            raise ValueError(f"values must have shape (m, {len(self.key.layout.channels)}), "
                             f"got {v.shape}")
        if self._buf_n and t0_ns != self._buf_t0 + self._buf_n * self.period_ns:
            self.flush()  # a gap in time: the batch so far goes out as it is
        if not self._buf_n:
            self._buf_t0 = int(t0_ns)
        self._buf.append(v)
        self._buf_n += v.shape[0]
        if self._buf_n >= self.batch_samples:
            allv = np.concatenate(self._buf)
            t0 = self._buf_t0
            n_full = (self._buf_n // self.batch_samples) * self.batch_samples
            for i in range(0, n_full, self.batch_samples):
                self._enqueue_batch(t0 + i * self.period_ns, allv[i:i + self.batch_samples])
            rest = allv[n_full:]
            self._buf = [rest] if rest.shape[0] else []
            self._buf_n = rest.shape[0]
            self._buf_t0 = t0 + n_full * self.period_ns

    def flush(self) -> None:
        """Send the samples buffered so far as a (short) batch now."""
        if self._buf_n:
            self._enqueue_batch(self._buf_t0, np.concatenate(self._buf))
        self._buf, self._buf_n = [], 0

    def push_status(self, report: StatusReport) -> int:
        """Queue a status report (its ``seq`` and ``machine_id`` are replaced). Returns the seq."""
        seq = self._take_seq()
        rep = StatusReport(self.key.machine_id, seq, report.t_ns, report.latitude_deg,
                           report.longitude_deg, report.altitude_m, report.operating_hours,
                           dict(report.channels))
        self._enqueue(seq, encode_status(self.key, rep, oldest_unacked=self._oldest(seq)), 0)
        return seq

    def receive(self, datagram: bytes, now_ns: int) -> Ack:
        """Process an ack datagram from the server.

        Raises:
            DatagramError: forged, corrupted or foreign ack (the caller counts and ignores it).
        """
        ack = decode_ack(datagram, self.key)
        silent = self._last_ack_ns is None or now_ns - self._last_ack_ns > self.rto_ns
        self._last_ack_ns = now_ns
        self._offsets.append(ack.server_time_ns - now_ns)
        done = [s for s in self._pending if ack.covers(s)]
        for s in done:
            del self._pending[s]
            self.acked_samples += self._samples_of.pop(s, 0)
        if silent or done:
            for p in self._pending.values():
                if p.sends > 1:  # backed off: the link works again, retry 1 RTO after last send
                    p.rto_ns = self.rto_ns
                    p.next_send_ns = min(p.next_send_ns, p.last_sent_ns + self.rto_ns)
        self._refill()
        return ack

    # --- output --------------------------------------------------------------------------------
    def datagrams_to_send(self, now_ns: int) -> list[bytes]:
        """Datagrams due now (new ones and retransmissions, oldest first, ≤ ``max_burst``)."""
        out: list[bytes] = []
        oldest = next(iter(self._pending), 0)
        for seq, p in self._pending.items():
            if len(out) >= self.max_burst:
                break
            if p.next_send_ns <= now_ns:
                if p.lag < 0:
                    p.lag = datagram_lag(p.datagram)
                if p.lag != seq - oldest:
                    p.lag = seq - oldest
                    p.datagram = restamp_lag(p.datagram, self.key.secret, p.lag)
                if p.sends:
                    self.retransmissions += 1
                p.sends += 1
                p.last_sent_ns = now_ns
                p.next_send_ns = now_ns + p.rto_ns
                p.rto_ns = min(2 * p.rto_ns, self.max_rto_ns)
                out.append(p.datagram)
                self.sent_bytes += len(p.datagram)
        self.sent_datagrams += len(out)
        return out

    def next_timer_ns(self) -> int | None:
        """Earliest time at which :meth:`datagrams_to_send` has something to send, or None."""
        return min((p.next_send_ns for p in self._pending.values()), default=None)

    # --- state ---------------------------------------------------------------------------------
    @property
    def in_memory(self) -> int:
        """Unacknowledged datagrams held in memory."""
        return len(self._pending)

    @property
    def spilled(self) -> int:
        """Datagrams waiting in the spill store."""
        return len(self.spill)

    @property
    def buffered_samples(self) -> int:
        """Samples pushed but not yet in a datagram."""
        return self._buf_n

    @property
    def idle(self) -> bool:
        """True when every pushed sample and status is acknowledged."""
        return not (self._pending or len(self.spill) or self._buf_n)

    def pending_seqs(self) -> Iterator[int]:
        """Sequence numbers held in memory, oldest first."""
        return iter(self._pending)

    def clock_offset_ns(self) -> int | None:
        """Estimated server clock − machine clock [ns] from ack timestamps (lower bound: minus
        the smallest return-path delay seen), or None before the first ack."""
        return max(self._offsets) if self._offsets else None

    # --- internals -----------------------------------------------------------------------------
    def _take_seq(self) -> int:
        seq = self.next_seq
        self.next_seq += 1
        return seq

    def _oldest(self, seq: int) -> int:
        return next(iter(self._pending), seq)

    def _enqueue_batch(self, t0_ns: int, values: F64) -> None:
        seq = self._take_seq()
        dg = encode_data(self.key, seq, t0_ns, self.period_ns, values,
                         oldest_unacked=self._oldest(seq))
        n = values.shape[0]
        if len(dg) > self.max_datagram and n > 1:
            self.next_seq -= 1  # this number was not used: split instead
            half = n // 2
            self._enqueue_batch(t0_ns, values[:half])
            self._enqueue_batch(t0_ns + half * self.period_ns, values[half:])
            return
        self._enqueue(seq, dg, n)

    def _enqueue(self, seq: int, datagram: bytes, n_samples: int) -> None:
        self._samples_of[seq] = n_samples
        self._refill()
        if len(self._pending) < self.max_unacked and not len(self.spill):
            self._pending[seq] = _Pending(datagram, 0, self.rto_ns)
        else:
            self.spill.append(datagram)

    def _refill(self) -> None:
        """Move the oldest spilled datagrams into memory while there is room. Invariant: the
        spill is empty or memory is full, so memory always holds the oldest unacknowledged
        datagrams and ``_oldest`` is right."""
        while len(self._pending) < self.max_unacked and len(self.spill):
            dg = self.spill.popleft()
            self._pending[datagram_seq(dg)] = _Pending(dg, 0, self.rto_ns)
