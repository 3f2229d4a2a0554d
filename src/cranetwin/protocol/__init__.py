"""Wire protocol between machines and the ingest daemon (sans-IO, versioned; docs/PROTOCOL.md).

Pure functions and state machines over bytes and a caller-supplied ``now``: no sockets, no
clocks, no threads, no files (the spill file and the sockets live in :mod:`cranetwin.ingest`).
Dependencies: the standard library, numpy and :mod:`cranetwin.codec` (quantisation,
zigzag/deltas and bit packing, shared with storage). numpy because the daemon must decode
100,000 samples/s on two cores, and bit-packing in pure Python is ~50× too slow; numpy does no
I/O, so the package is still sans-IO.

Datagrams (all authenticated with HMAC-SHA256/128 under a per-machine secret):

* data (0x01): a batch of samples, quantised at sensor resolution, delta + bit-packed
  (:func:`encode_data`, :func:`decode_data` → :class:`~cranetwin.samples.SampleBlock`);
* status (0x02): GPS, operating hours, low-rate channels (:func:`encode_status`,
  :func:`decode_status` → :class:`StatusReport`);
* ack (0x03): cumulative + selective acknowledgement of one sender epoch (:func:`encode_ack`,
  :func:`decode_ack` → :class:`Ack`);
* refusal (0x04): the server will never store one authenticated datagram, and says why
  (:func:`encode_refusal`, :func:`decode_refusal` → :class:`Refusal`).

State machines: :class:`Receiver` (server side: keys, validation, durable set, acks, refusals,
clock offset) and :class:`Sender` (machine side: batching, durable :class:`Journal`, RFC 6298
retransmission with RACK loss detection, bounded memory). Every rejection raises a
:class:`DatagramError` whose ``reason`` is one of :data:`REASONS`.
"""

from __future__ import annotations

from cranetwin.protocol.ack import (
    Ack,
    Refusal,
    decode_ack,
    decode_refusal,
    encode_ack,
    encode_refusal,
)
from cranetwin.protocol.data import decode_data, encode_data, on_grid, quantise
from cranetwin.protocol.errors import (
    REASONS,
    REFUSAL_CODES,
    BadHmacError,
    BadSeqError,
    BadTimeError,
    DatagramError,
    GarbageError,
    LayoutError,
    OutOfRangeError,
    OversizeError,
    RefusedError,
    ReplayedError,
    TruncatedError,
    UnknownMachineError,
    WrongVersionError,
)
from cranetwin.protocol.measure import WireStats, measure_bytes_per_sample
from cranetwin.protocol.receiver import Limits, Receiver
from cranetwin.protocol.sender import (
    Journal,
    MemoryJournal,
    Sender,
    datagram_samples,
    datagram_seq,
    new_epoch,
)
from cranetwin.protocol.status import StatusReport, decode_status, encode_status
from cranetwin.protocol.wire import (
    IP_UDP_OVERHEAD_V4,
    IP_UDP_OVERHEAD_V6,
    MAX_DATAGRAM,
    TAG_BYTES,
    TYPE_ACK,
    TYPE_DATA,
    TYPE_REFUSAL,
    TYPE_STATUS,
    VERSION,
    ChannelSpec,
    Header,
    Layout,
    MachineKey,
    peek_header,
)

__all__ = [
    "IP_UDP_OVERHEAD_V4", "IP_UDP_OVERHEAD_V6", "MAX_DATAGRAM", "REASONS", "REFUSAL_CODES",
    "TAG_BYTES", "TYPE_ACK", "TYPE_DATA", "TYPE_REFUSAL", "TYPE_STATUS", "VERSION",
    "Ack", "BadHmacError", "BadSeqError", "BadTimeError", "ChannelSpec", "DatagramError",
    "GarbageError", "Header", "Journal", "Layout", "LayoutError", "Limits", "MachineKey",
    "MemoryJournal", "OutOfRangeError", "OversizeError", "Receiver", "RefusedError", "Refusal",
    "ReplayedError", "Sender", "StatusReport", "TruncatedError", "UnknownMachineError",
    "WireStats", "WrongVersionError", "datagram_samples", "datagram_seq", "decode_ack",
    "decode_data", "decode_refusal", "decode_status", "encode_ack", "encode_data",
    "encode_refusal", "encode_status", "measure_bytes_per_sample", "new_epoch", "on_grid",
    "peek_header", "quantise",
]
