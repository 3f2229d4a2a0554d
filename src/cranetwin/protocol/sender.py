"""Machine-side protocol state: batching, journal, retransmission, refusals (sans-IO).

Fed samples (:meth:`Sender.push`), status (:meth:`Sender.push_status`), server datagrams
(:meth:`Sender.receive`) and the current time; returns the datagrams to send
(:meth:`Sender.datagrams_to_send`) and when to call again (:meth:`Sender.next_timer_ns`). The
asyncio shell is :func:`cranetwin.ingest.sender.run_sender`.

**Nothing produced is ever lost.** Every datagram is appended to a :class:`Journal` when it is
made, and the journal is synced before the datagram is first handed out for sending, so a crash
at any moment loses nothing that was sent (and nothing acknowledged depends on memory). A
datagram leaves the journal only when an ack covers it, or when the server refuses it (then the
journal keeps it for the operator, :meth:`Journal.reject`). On restart the sender resumes from
the journal: same epoch, next sequence number = ``journal.end``, the unreleased datagrams are
sent again (the server deduplicates). At most ``max_unacked`` datagrams are held in memory; the
rest wait in the journal, in order.

**Retransmission** follows TCP's rules: the retransmission timeout of RFC 6298 (SRTT/RTTVAR
from ack round trips, Karn's rule: no samples from retransmitted datagrams, exponential backoff,
clamped to [``min_rto_ns``, ``max_rto_ns``]); when the timer expires only the **oldest**
unacknowledged datagram is retransmitted (the link may just be slow). Datagrams that selective
acks show to be lost are retransmitted at once by the time-based rule of RACK (RFC 8985): one
sent more than ``rtt + reorder window`` before a datagram that was acknowledged is lost. Every
transmission carries the current oldest unacknowledged seq (``lag``; the tag is recomputed when
it changed), so the receiver can forget what the sender no longer holds.
"""

from __future__ import annotations

import secrets
import struct
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.protocol.ack import Ack, Refusal, decode_ack, decode_refusal
from cranetwin.protocol.data import DATA_FIXED, MAX_SAMPLES, encode_data
from cranetwin.protocol.errors import GarbageError
from cranetwin.protocol.status import STATUS_FIXED, StatusReport, encode_status
from cranetwin.protocol.wire import (
    EPOCH_MAX,
    MAX_DATAGRAM,
    SEQ_LIMIT,
    TAG_BYTES,
    TYPE_ACK,
    TYPE_DATA,
    TYPE_REFUSAL,
    MachineKey,
    get_varint,
    peek_header,
    put_varint,
    tag,
)

F64 = npt.NDArray[np.float64]
_SEQ = struct.Struct(">Q")
_N = struct.Struct(">H")


class Journal(Protocol):
    """Durable, ordered log of one sender epoch's datagrams (``seq`` contiguous from ``start``).

    :class:`MemoryJournal` is the in-memory one (tests, short runs);
    :class:`cranetwin.ingest.journal.FileJournal` keeps it on disk, crash-safe.
    """

    @property
    def epoch(self) -> int:
        """The sender epoch, 1 … 2**63 − 1, fixed for the journal's life."""

    @property
    def start(self) -> int:
        """Oldest seq not yet released (== :attr:`end` when empty)."""

    @property
    def end(self) -> int:
        """Next seq to append."""

    def append(self, seq: int, datagram: bytes) -> None:
        """Add ``datagram`` with ``seq == end``; durable once :meth:`sync` returns."""

    def sync(self) -> None:
        """Make every appended datagram durable (fsync)."""

    def read(self, seq: int, limit: int) -> list[bytes]:
        """Datagrams seq, seq + 1, … (below :attr:`end`), at most ``limit``."""

    def release(self, below: int) -> None:
        """Every seq < ``below`` is acknowledged (or refused) and may be discarded."""

    def reject(self, seq: int, datagram: bytes, reason: str) -> None:
        """The server refused ``datagram`` for ``reason``: keep it for the operator."""

    def __len__(self) -> int:
        """``end − start``."""


def new_epoch() -> int:
    """A random sender epoch in 1 … 2**63 − 1 (collision odds 2**−63 per pair of restarts)."""
    return secrets.randbelow(EPOCH_MAX) + 1


class MemoryJournal:
    """A :class:`Journal` in memory: survives a restart of the :class:`Sender` object (pass the
    same journal to the next one), not of the process.

    Args:
        epoch: The epoch (random when None); first_seq: the first sequence number.
    """

    def __init__(self, epoch: int | None = None, first_seq: int = 0) -> None:
        self._epoch = new_epoch() if epoch is None else int(epoch)
        if not 1 <= self._epoch <= EPOCH_MAX:
            raise ValueError(f"epoch must be in [1, 2**63), got {self._epoch}")
        self._start = self._end = int(first_seq)
        self._q: deque[bytes] = deque()
        self.rejected: list[tuple[int, bytes, str]] = []
        self.syncs = 0
        self.synced_end = self._end

    @property
    def epoch(self) -> int:
        return self._epoch

    @property
    def start(self) -> int:
        return self._start

    @property
    def end(self) -> int:
        return self._end

    def append(self, seq: int, datagram: bytes) -> None:
        if seq != self._end:
            raise ValueError(f"append seq {seq}, journal expects {self._end}")
        self._q.append(datagram)
        self._end += 1

    def sync(self) -> None:
        self.syncs += 1
        self.synced_end = self._end

    def read(self, seq: int, limit: int) -> list[bytes]:
        lo = max(seq, self._start) - self._start
        return [self._q[i] for i in range(lo, min(lo + limit, len(self._q)))]

    def release(self, below: int) -> None:
        below = min(below, self._end)
        while self._start < below:
            self._q.popleft()
            self._start += 1

    def reject(self, seq: int, datagram: bytes, reason: str) -> None:
        self.rejected.append((seq, datagram, reason))

    def __len__(self) -> int:
        return self._end - self._start


@dataclass
class _Pending:
    datagram: bytes
    sends: int = 0
    last_sent_ns: int = 0
    lag: int = -1  # seq − oldest_unacked written in the datagram (-1: not parsed yet)


def _fixed(datagram: bytes) -> int:
    head = peek_header(datagram)
    return head.size + (DATA_FIXED.size if head.type == TYPE_DATA else STATUS_FIXED.size)


def restamp_lag(datagram: bytes, secret: bytes, lag: int) -> bytes:
    """``datagram`` (data or status, made by this sender) with its lag field replaced and the tag
    recomputed. Retransmissions carry the current oldest unacknowledged seq this way."""
    fixed = _fixed(datagram)
    _, after = get_varint(datagram, fixed, len(datagram) - TAG_BYTES)
    out = bytearray(datagram[:fixed])
    put_varint(out, lag)
    out += datagram[after:-TAG_BYTES]
    out += tag(secret, out)
    return bytes(out)


def datagram_lag(datagram: bytes) -> int:
    """The lag field of a data or status datagram."""
    return get_varint(datagram, _fixed(datagram), len(datagram) - TAG_BYTES)[0]


def datagram_seq(datagram: bytes) -> int:
    """Sequence number of a data or status datagram (right after the header)."""
    return int(_SEQ.unpack_from(datagram, peek_header(datagram).size)[0])


def datagram_samples(datagram: bytes) -> int:
    """Samples carried by a data datagram (0 for status)."""
    head = peek_header(datagram)
    if head.type != TYPE_DATA:
        return 0
    return int(_N.unpack_from(datagram, head.size + 20)[0])


class Sender:
    """Protocol core of one machine's sender.

    Args:
        key: Machine identity, secret and layout.
        period_ns: Sample period [ns] (10_000_000 at 100 Hz).
        journal: Durable log of the datagrams (default: a new :class:`MemoryJournal`). Its
            epoch and ``end`` give this sender's epoch and next sequence number.
        batch_samples: Samples per data datagram (1..4096); a batch whose datagram would exceed
            ``max_datagram`` bytes is split in halves.
        max_unacked: Datagrams held in memory awaiting an ack (memory ≈ this × 1200 B); the
            rest wait in the journal.
        min_rto_ns: Lower bound of the retransmission timeout [ns] (RFC 6298: 1 s); also the
            initial timeout before the first round-trip sample.
        max_rto_ns: Upper bound of the backed-off timeout [ns].
        max_burst: Datagrams returned per :meth:`datagrams_to_send` call at most.
        max_datagram: Size limit of a datagram [bytes of UDP payload].
    """

    def __init__(self, key: MachineKey, period_ns: int, *, journal: Journal | None = None,
                 batch_samples: int = 50, max_unacked: int = 512,
                 min_rto_ns: int = 1_000_000_000, max_rto_ns: int = 10_000_000_000,
                 max_burst: int = 64, max_datagram: int = MAX_DATAGRAM) -> None:
        if not 1 <= batch_samples <= MAX_SAMPLES:
            raise ValueError(f"batch_samples must be in 1..{MAX_SAMPLES}, got {batch_samples}")
        if max_unacked < 1 or max_burst < 1 or min_rto_ns < 1 or max_rto_ns < min_rto_ns:
            raise ValueError("max_unacked, max_burst, min_rto_ns ≥ 1 and max_rto_ns ≥ min_rto_ns "
                             "needed")
        self.key = key
        self.period_ns = int(period_ns)
        self.journal: Journal = journal if journal is not None else MemoryJournal()
        self.epoch = self.journal.epoch
        self.next_seq = self.journal.end
        self.batch_samples = batch_samples
        self.max_unacked = max_unacked
        self.min_rto_ns = min_rto_ns
        self.max_rto_ns = max_rto_ns
        self.max_burst = max_burst
        self.max_datagram = max_datagram
        self._pending: dict[int, _Pending] = {}  # insertion order = seq order
        self._loaded = self.journal.start  # next seq to load from the journal into memory
        self._unsynced = False
        self._buf: list[F64] = []
        self._buf_n = 0
        self._buf_t0 = 0
        # RFC 6298 state
        self.srtt_ns: int | None = None
        self.rttvar_ns = 0
        self.rto_ns = min_rto_ns
        self._rto_deadline: int | None = None
        self._backoffs = 0  # consecutive timer expiries without forward progress
        self._last_timeout_ns = -1
        # RACK state (RFC 8985)
        self._rack_xmit_ns = -1
        self._rack_rtt_ns = 0
        self._min_rtt_ns: int | None = None
        self._offsets: deque[int] = deque(maxlen=256)
        self.sent_datagrams = 0
        self.retransmissions = 0
        self.timeouts = 0
        self.sent_bytes = 0
        self.acked_samples = 0
        self.refused = 0
        self.refused_samples = 0
        self.last_acked: list[tuple[int, bytes]] = []
        """(seq, datagram) of what the last :meth:`receive` call found acknowledged."""
        self._refill()

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
        """Queue a status report (its ``seq``, ``epoch`` and ``machine_id`` are replaced).
        Returns the seq."""
        seq = self._take_seq()
        rep = StatusReport(self.key.machine_id, seq, report.t_ns, report.latitude_deg,
                           report.longitude_deg, report.altitude_m, report.operating_hours,
                           dict(report.channels), epoch=self.epoch)
        self._enqueue(seq, encode_status(self.key, rep, oldest_unacked=self._oldest(seq)))
        return seq

    def receive(self, datagram: bytes, now_ns: int) -> Ack | Refusal:
        """Process an ack or refusal datagram from the server.

        An authentic datagram for another epoch of this machine (an earlier run's) is returned
        but changes nothing.

        Raises:
            DatagramError: forged, corrupted or foreign (the caller counts and ignores it).
        """
        head = peek_header(datagram)
        self.last_acked = []
        if head.type == TYPE_REFUSAL:
            ref = decode_refusal(datagram, self.key)
            if ref.epoch == self.epoch:
                self._on_refusal(ref)
            return ref
        if head.type != TYPE_ACK:
            raise GarbageError(f"not a server datagram (type {head.type:#04x})", head.wire_id)
        ack = decode_ack(datagram, self.key)
        if ack.epoch != self.epoch:
            return ack
        self._offsets.append(ack.server_time_ns - now_ns)
        done = [s for s in self._pending if ack.covers(s)]
        sample: int | None = None
        sample_xmit = -1
        newest_xmit = -1
        for s in done:
            p = self._pending.pop(s)
            self.last_acked.append((s, p.datagram))
            self.acked_samples += datagram_samples(p.datagram)
            # Karn: only a datagram sent once gives an unambiguous round trip, and not one sent
            # before the last timeout (a datagram sent into an outage measures the outage)
            measured = p.sends == 1 and p.last_sent_ns >= self._last_timeout_ns
            newest_xmit = max(newest_xmit, p.last_sent_ns)
            if measured and p.last_sent_ns > sample_xmit:
                sample_xmit, sample = p.last_sent_ns, now_ns - p.last_sent_ns
        if done:
            # forward progress clears the backoff, as Linux does (RFC 6298 (5.7) would keep it
            # until a valid sample: after an outage the tail of the queue then drains at one
            # retransmission per max_rto_ns)
            self._backoffs = 0
            self.rto_ns = self._base_rto()
            # the round trip is the newest transmission's: the one that made the server ack
            # (an older one acked along with it waited for that, e.g. behind a lost ack)
            if sample is not None and sample_xmit == newest_xmit:
                self._rtt_sample(sample)
            if newest_xmit > self._rack_xmit_ns:
                self._rack_xmit_ns = newest_xmit
                self._rack_rtt_ns = now_ns - newest_xmit
            self._release()
            self._rto_deadline = now_ns + self.rto_ns if self._outstanding() else None
        return ack

    # --- output --------------------------------------------------------------------------------
    def datagrams_to_send(self, now_ns: int) -> list[bytes]:
        """Datagrams due now, oldest first, ≤ ``max_burst``: datagrams judged lost (RACK), the
        oldest one when the retransmission timer expired, and new ones. The journal is synced
        first, so nothing is ever sent that a crash could lose."""
        if self._unsynced:
            self.journal.sync()
            self._unsynced = False
        out: list[tuple[int, _Pending]] = []
        timed_out = self._rto_deadline is not None and now_ns >= self._rto_deadline
        if timed_out:
            oldest = next((s for s, p in self._pending.items() if p.sends), None)
            if oldest is not None:
                out.append((oldest, self._pending[oldest]))
                self.timeouts += 1
                self._backoffs += 1
                self._last_timeout_ns = now_ns
                self.rto_ns = min(2 * self.rto_ns, self.max_rto_ns)  # RFC 6298 (5.5)
                if self._backoffs >= 3:  # RFC 6298 §5 note: SRTT and RTTVAR are likely bogus
                    self.srtt_ns = None
            self._rto_deadline = None
        reo = self._reorder_window()
        for seq, p in self._pending.items():
            if len(out) >= self.max_burst:
                break
            if p.sends == 0:
                out.append((seq, p))
            elif (not timed_out and p.last_sent_ns < self._rack_xmit_ns
                  and now_ns >= p.last_sent_ns + self._rack_rtt_ns + reo):
                out.append((seq, p))
        oldest_unacked = next(iter(self._pending), self._loaded)
        sent: list[bytes] = []
        seen: set[int] = set()
        for seq, p in out:
            if seq in seen:
                continue
            seen.add(seq)
            if p.lag < 0:
                p.lag = datagram_lag(p.datagram)
            if p.lag != seq - oldest_unacked:
                p.lag = seq - oldest_unacked
                p.datagram = restamp_lag(p.datagram, self.key.secret, p.lag)
            if p.sends:
                self.retransmissions += 1
            p.sends += 1
            p.last_sent_ns = now_ns
            sent.append(p.datagram)
            self.sent_bytes += len(p.datagram)
        if sent and self._rto_deadline is None:
            self._rto_deadline = now_ns + self.rto_ns
        self.sent_datagrams += len(sent)
        return sent

    def next_timer_ns(self) -> int | None:
        """Earliest time at which :meth:`datagrams_to_send` may have something to send, or
        None when nothing is in flight or waiting."""
        times: list[int] = []
        if self._rto_deadline is not None:
            times.append(self._rto_deadline)
        reo = self._reorder_window()
        for p in self._pending.values():
            if p.sends == 0:
                return 0
            if p.last_sent_ns < self._rack_xmit_ns:
                times.append(p.last_sent_ns + self._rack_rtt_ns + reo)
        return min(times, default=None)

    # --- state ---------------------------------------------------------------------------------
    @property
    def in_memory(self) -> int:
        """Unacknowledged datagrams held in memory."""
        return len(self._pending)

    @property
    def unacked(self) -> int:
        """Datagrams not yet acknowledged (in memory and waiting in the journal)."""
        return len(self._pending) + (self.journal.end - self._loaded)

    @property
    def spilled(self) -> int:
        """Datagrams waiting in the journal, not yet loaded into memory."""
        return self.journal.end - self._loaded

    @property
    def buffered_samples(self) -> int:
        """Samples pushed but not yet in a datagram."""
        return self._buf_n

    @property
    def idle(self) -> bool:
        """True when every pushed sample and status is acknowledged (or refused)."""
        return not (self._pending or self._loaded < self.journal.end or self._buf_n)

    def pending_seqs(self) -> Iterator[int]:
        """Sequence numbers held in memory, oldest first."""
        return iter(self._pending)

    def clock_offset_ns(self) -> int | None:
        """Estimated server clock − machine clock [ns] from ack timestamps (lower bound: minus
        the smallest return-path delay seen), or None before the first ack."""
        return max(self._offsets) if self._offsets else None

    # --- internals -----------------------------------------------------------------------------
    def _rtt_sample(self, r: int) -> None:
        """RFC 6298 (2.2)/(2.3): update SRTT and RTTVAR with round trip ``r`` [ns]; new RTO."""
        r = max(r, 1)
        if self.srtt_ns is None:
            self.srtt_ns, self.rttvar_ns = r, r // 2
        else:
            self.rttvar_ns = (3 * self.rttvar_ns + abs(self.srtt_ns - r)) // 4
            self.srtt_ns = (7 * self.srtt_ns + r) // 8
        self._min_rtt_ns = r if self._min_rtt_ns is None else min(self._min_rtt_ns, r)
        self.rto_ns = self._base_rto()

    def _base_rto(self) -> int:
        """RTO = SRTT + max(G, 4·RTTVAR) with G = 1 ms, clamped; the minimum before a sample."""
        if self.srtt_ns is None:
            return self.min_rto_ns
        rto = self.srtt_ns + max(1_000_000, 4 * self.rttvar_ns)
        return min(max(rto, self.min_rto_ns), self.max_rto_ns)

    def _reorder_window(self) -> int:
        """RACK's reordering window: min RTT / 4 (RFC 8985 §6.2), at least 1 ms."""
        return max(1_000_000, (self._min_rtt_ns or 0) // 4)

    def _outstanding(self) -> bool:
        return any(p.sends for p in self._pending.values())

    def _on_refusal(self, ref: Refusal) -> None:
        p = self._pending.pop(ref.seq, None)
        if p is None:
            return
        self.refused += 1
        self.refused_samples += datagram_samples(p.datagram)
        self.journal.reject(ref.seq, p.datagram, ref.reason)
        self._release()

    def _release(self) -> None:
        self._refill()
        self.journal.release(next(iter(self._pending), self._loaded))

    def _take_seq(self) -> int:
        seq = self.next_seq
        if seq >= SEQ_LIMIT:
            raise OverflowError("sequence numbers of this epoch are exhausted (2**63)")
        self.next_seq += 1
        return seq

    def _oldest(self, seq: int) -> int:
        return next(iter(self._pending), min(self._loaded, seq))

    def _enqueue_batch(self, t0_ns: int, values: F64) -> None:
        seq = self._take_seq()
        dg = encode_data(self.key, seq, t0_ns, self.period_ns, values,
                         oldest_unacked=self._oldest(seq), epoch=self.epoch)
        n = values.shape[0]
        if len(dg) > self.max_datagram and n > 1:
            self.next_seq -= 1  # this number was not used: split instead
            half = n // 2
            self._enqueue_batch(t0_ns, values[:half])
            self._enqueue_batch(t0_ns + half * self.period_ns, values[half:])
            return
        self._enqueue(seq, dg)

    def _enqueue(self, seq: int, datagram: bytes) -> None:
        self.journal.append(seq, datagram)
        self._unsynced = True
        self._refill()

    def _refill(self) -> None:
        """Load the oldest journal datagrams not in memory while there is room. Invariant:
        memory holds the oldest unacknowledged datagrams, so ``_oldest`` is right."""
        room = self.max_unacked - len(self._pending)
        end = self.journal.end
        if room <= 0 or self._loaded >= end:
            return
        for dg in self.journal.read(self._loaded, room):
            self._pending[self._loaded] = _Pending(dg)
            self._loaded += 1
