"""Server-side protocol state: authentication, validation, replay set, acks, refusals (sans-IO).

The daemon feeds every datagram with its own receive time to :meth:`Receiver.receive`, stores
what comes back, calls :meth:`Receiver.mark_durable` once the write is committed (newly stored
or found already stored) and sends :meth:`Receiver.ack` to the machine's address. On
:class:`ReplayedError` it answers with ``ack(err.machine_id, err.epoch, now)``; on
:class:`RefusedError` with :meth:`Receiver.refusal`. It never answers any other error: nothing is
trusted, and nothing is said, before the HMAC has verified. No sockets, no clocks, no threads.

Sequence rules (per machine and sender epoch; docs/PROTOCOL.md §7):

* Identity of a datagram is (machine, epoch, seq). A sender that restarts from its durable
  journal keeps its epoch and goes on counting; one that lost its journal starts a new random
  epoch at seq 0, so no jump, reset or clock change can make new data look like old.
* A datagram is **dropped as replayed only if its (epoch, seq) is in the exact set of seqs this
  receiver has seen committed**. Everything else that is authentic and valid is returned for
  storage, whose writes are idempotent on (machine, epoch, seq): a restarted receiver, a
  forgotten entry or a duplicate of a datagram still being written costs a redundant write,
  never a lost sample. Acked ⇒ stored holds by construction: an ack names only seqs marked
  durable after a commit, or seqs below the sender's own ``oldest unacknowledged`` claim.
* ``released`` = ``seq − lag`` of the newest datagram: the sender no longer holds anything
  below, so the durable set forgets it (bounded memory) and the cumulative ack starts there. A
  lower claim than before (reordering, or a sender that went backwards) lowers it again: the
  ack then covers less, never something that is not stored.

Validation at the edge, after the HMAC: datagram size, sequence range, timestamps within a
window around the server clock, and every value within its sensor's declared range plus a
margin (:class:`Limits`). A failing datagram raises a :class:`RefusedError`; the sender is told
and nothing of it is stored.

Clock offset: for each accepted data datagram the receiver records
``receive_time − (t_last_sample + period)``; the minimum over the last :data:`OFFSET_WINDOW`
datagrams estimates server clock − machine clock, like the minimum filter of NTP.
"""

from __future__ import annotations

import bisect
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from cranetwin.protocol.ack import encode_ack, encode_refusal
from cranetwin.protocol.data import DATA_FIXED, parse_data
from cranetwin.protocol.errors import (
    BadSeqError,
    BadTimeError,
    DatagramError,
    GarbageError,
    OutOfRangeError,
    OversizeError,
    RefusedError,
    ReplayedError,
    UnknownMachineError,
)
from cranetwin.protocol.status import STATUS_FIXED, StatusReport, parse_status
from cranetwin.protocol.wire import (
    MAX_DATAGRAM,
    SEQ_LIMIT,
    TYPE_ACK,
    TYPE_DATA,
    TYPE_REFUSAL,
    Header,
    MachineKey,
    get_varint,
    peek_header,
    verify,
)
from cranetwin.samples import SampleBlock

OFFSET_WINDOW = 256
MAX_INTERVALS = 4096
"""Durable seq intervals kept per epoch; beyond it the oldest are forgotten (only costs a
redundant idempotent write if one of them is retransmitted again)."""
MAX_EPOCHS = 8
"""Sender epochs remembered per machine (least recently used forgotten first)."""
SACK_SPAN = 1024


@dataclass(frozen=True)
class Limits:
    """What the receiver accepts from an authenticated machine.

    Attributes:
        max_datagram: Largest datagram [bytes of UDP payload] (the protocol's 1200).
        max_past_s: Oldest sample time accepted, before the server clock [s] (a sender may hold
            data for a long outage).
        max_future_s: Newest sample time accepted, after the server clock [s] (clock skew).
        range_margin: Share of each channel's span ``max − min`` a value may lie beyond
            ``[min, max]`` (sensors over-range a little before they saturate).
    """

    max_datagram: int = MAX_DATAGRAM
    max_past_s: float = 400 * 86400.0
    max_future_s: float = 300.0
    range_margin: float = 0.1


@dataclass
class _Epoch:
    """Receive state of one sender epoch: durable seqs as sorted disjoint [start, end)."""

    version: int
    released: int = 0
    starts: list[int] = field(default_factory=list)
    ends: list[int] = field(default_factory=list)

    def contains(self, seq: int) -> bool:
        i = bisect.bisect_right(self.starts, seq) - 1
        return i >= 0 and seq < self.ends[i]

    def add(self, seq: int) -> None:
        if seq < self.released or self.contains(seq):
            return
        i = bisect.bisect_right(self.starts, seq)  # intervals [0, i) start at or below seq
        left = i > 0 and self.ends[i - 1] == seq
        right = i < len(self.starts) and self.starts[i] == seq + 1
        if left and right:
            self.ends[i - 1] = self.ends[i]
            del self.starts[i], self.ends[i]
        elif left:
            self.ends[i - 1] = seq + 1
        elif right:
            self.starts[i] = seq
        else:
            self.starts.insert(i, seq)
            self.ends.insert(i, seq + 1)
            if len(self.starts) > MAX_INTERVALS:
                del self.starts[0], self.ends[0]

    def claim(self, below: int) -> None:
        """The newest datagram says the sender holds nothing below ``below``. A claim lower
        than an earlier one (a reordered or duplicated old datagram, or a sender that broke the
        rules) is believed too: the cumulative ack then covers less for a while, which costs at
        most a redundant retransmission, never an ack of something not stored."""
        if below < self.released:
            self.released = below  # forgotten intervals below stay forgotten (rewrite is safe)
            return
        self.released = below
        k = bisect.bisect_right(self.ends, below)  # intervals entirely below
        del self.starts[:k], self.ends[:k]
        if self.starts and self.starts[0] < below:
            self.starts[0] = below

    def cumulative(self) -> int:
        c = self.released
        if self.starts and self.starts[0] <= c:
            c = max(c, self.ends[0])
        return c

    def selective(self, cum: int) -> list[int]:
        out: list[int] = []
        i = bisect.bisect_right(self.ends, cum)
        while i < len(self.starts) and self.starts[i] <= cum + SACK_SPAN:
            out.extend(range(max(self.starts[i], cum + 1),
                             min(self.ends[i], cum + SACK_SPAN + 1)))
            i += 1
        return out


@dataclass
class _MachineState:
    key: MachineKey
    lo: np.ndarray  # accepted range per channel [channel units], shape (c,)
    hi: np.ndarray
    epochs: OrderedDict[int, _Epoch] = field(default_factory=OrderedDict)
    offsets: deque[int] = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    accepted: int = 0

    def epoch(self, epoch: int, version: int) -> _Epoch:
        ep = self.epochs.get(epoch)
        if ep is None:
            ep = self.epochs[epoch] = _Epoch(version)
            while len(self.epochs) > MAX_EPOCHS:
                self.epochs.popitem(last=False)
        else:
            self.epochs.move_to_end(epoch)
        return ep


KeyLookup = Callable[[int], MachineKey | None]
E = TypeVar("E", bound=DatagramError)


@dataclass(frozen=True)
class _Who:
    """Identity of an authenticated datagram, for the errors that may be answered."""

    head: Header
    machine_id: str
    seq: int

    def error(self, cls: type[E], message: str) -> E:
        return cls(message, self.head.wire_id, self.machine_id, epoch=self.head.epoch,
                   seq=self.seq, version=self.head.version)


class Receiver:
    """Per-machine receive state of the server side.

    Args:
        keys: Wire id → key, as a mapping or a function returning None for unknown ids (e.g. a
            cached storage lookup).
        limits: What is accepted from authenticated machines (:class:`Limits`).
    """

    def __init__(self, keys: Mapping[int, MachineKey] | KeyLookup,
                 limits: Limits | None = None) -> None:
        self._lookup: KeyLookup = keys.get if isinstance(keys, Mapping) else keys
        self.limits = limits or Limits()
        self._by_wire: dict[int, _MachineState] = {}
        self._by_id: dict[str, _MachineState] = {}

    def _state(self, wire_id: int) -> _MachineState:
        st = self._by_wire.get(wire_id)
        if st is None:
            key = self._lookup(wire_id)
            if key is None:
                raise UnknownMachineError(f"no machine registered with wire id {wire_id}", wire_id)
            lo = np.array([c.min for c in key.layout.channels], dtype=np.float64)
            hi = np.array([c.max for c in key.layout.channels], dtype=np.float64)
            span = (hi - lo) * self.limits.range_margin
            st = _MachineState(key, lo - span, hi + span)
            self._by_wire[wire_id] = st
            self._by_id[key.machine_id] = st
        return st

    def receive(self, datagram: bytes, now_ns: int) -> SampleBlock | StatusReport:
        """Authenticate, replay-check, decode and validate one datagram from a machine.

        Args:
            datagram: UDP payload.
            now_ns: Server receive time [ns since the Unix epoch].

        Returns:
            The samples (data) or the status report, to be stored; ``epoch`` and ``seq`` set.

        Raises:
            ReplayedError: authenticated, already durable: answer with :meth:`ack`.
            RefusedError: authenticated, never storable: answer with :meth:`refusal`.
            DatagramError: any other subclass: not authenticated (or not ours): no answer.
        """
        head = peek_header(datagram)
        if head.type in (TYPE_ACK, TYPE_REFUSAL):
            raise GarbageError("a server datagram sent to the server", head.wire_id)
        st = self._state(head.wire_id)
        key = st.key
        body = verify(key.secret, datagram, head.wire_id)  # nothing below is trusted before this
        fixed = DATA_FIXED.size if head.type == TYPE_DATA else STATUS_FIXED.size
        if len(body) < head.size + fixed + 1:
            raise GarbageError("datagram shorter than its fixed fields", head.wire_id)
        seq = int.from_bytes(body[head.size:head.size + 8], "big")
        who = _Who(head, key.machine_id, seq)
        if len(datagram) > self.limits.max_datagram:
            raise who.error(OversizeError, f"{len(datagram)} bytes > {self.limits.max_datagram}")
        if seq >= SEQ_LIMIT:
            raise who.error(BadSeqError, f"seq {seq} ≥ 2**63")
        lag, _ = get_varint(body, head.size + fixed, len(body))
        if lag > seq:
            raise GarbageError("oldest-unacknowledged lag exceeds the sequence number",
                               head.wire_id)
        ep = st.epoch(head.epoch, head.version)
        ep.claim(seq - lag)
        if ep.contains(seq):
            raise who.error(ReplayedError, f"seq {seq} of {key.machine_id!r} epoch {head.epoch} "
                                           "is already durable")
        try:
            item = self._decode(head, body, key)
        except DatagramError as exc:  # authenticated but malformed: not answered, as before
            exc.machine_id, exc.epoch, exc.seq = key.machine_id, head.epoch, seq
            raise
        self._validate(st, item, now_ns, who)
        st.accepted += 1
        if isinstance(item, SampleBlock):
            st.offsets.append(now_ns - (item.t_end_ns + item.period_ns))
        return item

    @staticmethod
    def _decode(head: Header, body: memoryview, key: MachineKey) -> SampleBlock | StatusReport:
        if head.type == TYPE_DATA:
            return parse_data(head, body, key)
        return parse_status(head, body, key)

    def _validate(self, st: _MachineState, item: SampleBlock | StatusReport, now_ns: int,
                  who: _Who) -> None:
        lim = self.limits
        lo_t = now_ns - int(lim.max_past_s * 1e9)
        hi_t = now_ns + int(lim.max_future_s * 1e9)
        if isinstance(item, SampleBlock):
            t_first, t_last = item.t0_ns, item.t_end_ns
        else:
            t_first = t_last = item.t_ns
        if t_first < max(lo_t, 0) or t_last > hi_t:
            raise who.error(BadTimeError, f"times {t_first}…{t_last} ns outside the accepted "
                            f"window [now − {lim.max_past_s:g} s, now + {lim.max_future_s:g} s]")
        if isinstance(item, SampleBlock):
            v = item.values
            with np.errstate(invalid="ignore"):
                bad = (v < st.lo) | (v > st.hi)
            if bad.any():
                j = int(np.flatnonzero(bad.any(axis=0))[0])
                ch = st.key.layout.channels[j]
                raise who.error(OutOfRangeError, f"channel {ch.name!r}: value outside "
                                f"[{ch.min:g}, {ch.max:g}] + {lim.range_margin:.0%} margin")
        else:
            names = st.key.layout.names
            for name, x in item.channels.items():
                j = names.index(name)
                if not (math.isnan(x) or st.lo[j] <= x <= st.hi[j]):
                    raise who.error(OutOfRangeError,
                                    f"status channel {name!r} = {x:g} out of range")

    def mark_durable(self, machine_id: str, epoch: int, seq: int) -> None:
        """Record that datagram (epoch, seq) of ``machine_id`` is committed (before :meth:`ack`)."""
        st = self._by_id.get(machine_id)
        if st is None:
            return
        ep = st.epochs.get(epoch)
        if ep is None:
            ep = st.epoch(epoch, 1 if epoch == 0 else 2)
        ep.add(seq)

    def ack(self, machine_id: str, epoch: int, now_ns: int) -> bytes:
        """The ack datagram for ``machine_id``'s sender epoch ``epoch`` covering everything durable
        so far (in the sender's protocol version).

        Args:
            machine_id: A machine that has sent at least one authenticated datagram.
            epoch: Its sender epoch (0 for a version-1 sender).
            now_ns: Server time [ns], carried in the ack.

        Raises:
            KeyError: the machine or epoch has not been seen by this receiver.
        """
        st = self._by_id[machine_id]
        ep = st.epochs[epoch]
        cum = ep.cumulative()
        return encode_ack(st.key, cum, ep.selective(cum), server_time_ns=now_ns, epoch=epoch,
                          version=ep.version)

    def refusal(self, err: RefusedError, now_ns: int = 0) -> bytes:
        """The refusal datagram answering ``err`` (raised by :meth:`receive` for a datagram that
        authenticated). A version-1 sender has no refusals: it gets an ack (it would otherwise
        retransmit for ever), which the caller must then count as a refused datagram.

        Raises:
            KeyError: the machine has not been seen by this receiver.
        """
        if err.machine_id is None or err.seq is None:
            raise ValueError("only an authenticated datagram's error can be answered")
        return self.refuse(err.machine_id, err.epoch, err.seq, err.reason, now_ns)

    def refuse(self, machine_id: str, epoch: int, seq: int, reason: str, now_ns: int) -> bytes:
        """The refusal datagram for a datagram that storage refused (``reason`` one of
        :data:`~cranetwin.protocol.errors.REFUSAL_CODES`, e.g. ``"unstorable"``).

        Raises:
            KeyError: the machine has not been seen by this receiver.
        """
        st = self._by_id[machine_id]
        if epoch == 0:  # version 1: release it with an ack, so it is not retransmitted forever
            ep = st.epoch(0, 1)
            ep.add(seq)
            return self.ack(machine_id, 0, now_ns)
        return encode_refusal(st.key, epoch, seq, reason, server_time_ns=now_ns)

    def clock_offset_ns(self, machine_id: str) -> int | None:
        """Estimated server clock − machine clock [ns] (upper bound: includes the smallest
        one-way delay seen), or None before the first data datagram."""
        st = self._by_id.get(machine_id)
        if st is None or not st.offsets:
            return None
        return min(st.offsets)

    def forget(self, machine_id: str) -> None:
        """Drop the state of ``machine_id`` (e.g. its key was rotated)."""
        st = self._by_id.pop(machine_id, None)
        if st is not None:
            self._by_wire.pop(st.key.wire_id, None)
