"""Server-side protocol state: authentication, replay window, acks and clock offset (sans-IO).

The daemon feeds every datagram with its own receive time to :meth:`Receiver.receive`, stores
what comes back, calls :meth:`Receiver.mark_durable` once the write is committed and sends the
bytes of :meth:`Receiver.ack` back to the machine's address. On :class:`ReplayedError` it drops
the datagram and also sends ``ack(err.machine_id, now)``: the machine retransmits because it
missed the earlier ack, and without a fresh one it would retransmit forever once it has nothing
new to send. No sockets, no clocks, no threads.

Replay rule (per machine; ``floor`` and ``durable`` are the receiver's state):

* ``floor``: every seq below it is durable or was released by the sender. It advances when the
  seqs above it become durable contiguously, and to the ``oldest_unacked`` a datagram claims
  (only after its HMAC verified, so only the machine itself can move it).
* A datagram is **rejected as replayed** if ``seq < floor`` or ``seq`` is in ``durable`` (the
  set of durable seqs above ``floor``; at most :data:`WINDOW` entries are tracked, the oldest are
  forgotten first).
* Anything else is **accepted**, including a duplicate of a datagram that was accepted but is not
  durable yet: storage writes are idempotent on (machine, seq), so letting it through is harmless,
  and refusing it could lose data if the first copy's write failed.
* A forgotten entry (more than :data:`WINDOW` durable seqs above a gap) or a receiver restarted
  with empty state only lets authentic old datagrams through again; idempotent storage absorbs
  them. Forgeries never pass: the HMAC is checked first (``hmac.compare_digest``).

Clock offset: for each accepted data datagram the receiver records
``receive_time − (t_last_sample + period)`` (server clock − machine clock + one-way delay +
the sender's batching delay); the minimum over the last :data:`OFFSET_WINDOW` datagrams estimates
the offset with the smallest delay, like the minimum filter of NTP.
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from cranetwin.protocol.ack import encode_ack
from cranetwin.protocol.data import data_lag, decode_data
from cranetwin.protocol.errors import GarbageError, ReplayedError, UnknownMachineError
from cranetwin.protocol.status import StatusReport, decode_status, status_lag
from cranetwin.protocol.wire import TYPE_ACK, TYPE_DATA, MachineKey, peek_header
from cranetwin.samples import SampleBlock

WINDOW = 65536
"""Durable seqs tracked above the floor per machine (≈ 9 h of a 100 Hz machine at 2 datagrams/s
behind one missing datagram)."""
OFFSET_WINDOW = 256


@dataclass
class _MachineState:
    key: MachineKey
    floor: int = 0
    durable: set[int] = field(default_factory=set)
    heap: list[int] = field(default_factory=list)  # the same seqs, for forgetting the oldest
    offsets: deque[int] = field(default_factory=lambda: deque(maxlen=OFFSET_WINDOW))
    accepted: int = 0

    def raise_floor(self, new_floor: int) -> None:
        if new_floor > self.floor:
            self.floor = new_floor
            while self.heap and self.heap[0] < new_floor:
                self.durable.discard(heapq.heappop(self.heap))
        while self.floor in self.durable:
            self.durable.discard(self.floor)
            heapq.heappop(self.heap)
            self.floor += 1


KeyLookup = Callable[[int], MachineKey | None]


class Receiver:
    """Per-machine receive state of the server side.

    Args:
        keys: Wire id → key, as a mapping or a function returning None for unknown ids (e.g. a
            cached storage lookup).
    """

    def __init__(self, keys: Mapping[int, MachineKey] | KeyLookup) -> None:
        self._lookup: KeyLookup = keys.get if isinstance(keys, Mapping) else keys
        self._by_wire: dict[int, _MachineState] = {}
        self._by_id: dict[str, _MachineState] = {}

    def _state(self, wire_id: int) -> _MachineState:
        st = self._by_wire.get(wire_id)
        if st is None:
            key = self._lookup(wire_id)
            if key is None:
                raise UnknownMachineError(f"no machine registered with wire id {wire_id}", wire_id)
            st = _MachineState(key)
            self._by_wire[wire_id] = st
            self._by_id[key.machine_id] = st
        return st

    def receive(self, datagram: bytes, now_ns: int) -> SampleBlock | StatusReport:
        """Authenticate, replay-check and decode one datagram from a machine.

        Args:
            datagram: UDP payload.
            now_ns: Server receive time [ns since the Unix epoch].

        Returns:
            The samples (data) or the status report, to be stored.

        Raises:
            DatagramError: any subclass; ``err.reason`` names the drop counter.
        """
        head = peek_header(datagram)
        if head.type == TYPE_ACK:
            raise GarbageError("an ack datagram sent to the server", head.wire_id)
        st = self._state(head.wire_id)
        item: SampleBlock | StatusReport
        if head.type == TYPE_DATA:
            item = decode_data(datagram, st.key)
            lag = data_lag(datagram)
        else:
            item = decode_status(datagram, st.key)
            lag = status_lag(datagram)
        seq = item.seq
        st.raise_floor(seq - lag)
        if seq < st.floor or seq in st.durable:
            raise ReplayedError(f"seq {seq} of {st.key.machine_id!r} is already durable "
                                f"(window floor {st.floor})", head.wire_id, st.key.machine_id)
        st.accepted += 1
        if isinstance(item, SampleBlock):
            st.offsets.append(now_ns - (item.t_end_ns + item.period_ns))
        return item

    def mark_durable(self, machine_id: str, seq: int) -> None:
        """Record that datagram ``seq`` of ``machine_id`` is committed (call before :meth:`ack`)."""
        st = self._by_id.get(machine_id)
        if st is None or seq < st.floor or seq in st.durable:
            return
        st.durable.add(seq)
        heapq.heappush(st.heap, seq)
        while len(st.heap) > WINDOW:
            st.durable.discard(heapq.heappop(st.heap))
        st.raise_floor(st.floor)

    def ack(self, machine_id: str, now_ns: int) -> bytes:
        """The ack datagram for ``machine_id`` covering everything durable so far.

        Args:
            machine_id: A machine that has sent at least one accepted datagram.
            now_ns: Server time [ns], carried in the ack.

        Raises:
            KeyError: the machine has not been seen by this receiver.
        """
        st = self._by_id[machine_id]
        return encode_ack(st.key, st.floor, (s for s in st.durable if s <= st.floor + 1024),
                          server_time_ns=now_ns)

    def floor(self, machine_id: str) -> int:
        """Every seq below this is durable or released for ``machine_id`` (0 if unseen)."""
        st = self._by_id.get(machine_id)
        return st.floor if st else 0

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
