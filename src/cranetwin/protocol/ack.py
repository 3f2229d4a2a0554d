"""Server → machine datagrams: acknowledgements (type 0x03) and refusals (type 0x04).

An **ack** covers one epoch of the machine's sender. ``cumulative`` = c means every sequence
number of that epoch below c is durable on the server or was released by the sender (its
``lag`` field said it no longer holds it); bit i of the selective bitmap means c + 1 + i is
durable too. The server sends an ack only after the datagrams it covers are committed.

A **refusal** names one authenticated datagram (epoch, seq) that the server will never store,
with a reason code (:data:`~cranetwin.protocol.errors.REFUSAL_CODES`); the sender stops
retransmitting it and keeps it for its operator.

Both are authenticated with the machine's key like every other datagram; the type byte inside
the authenticated bytes keeps a data datagram from being reflected as an ack. Byte layout:
docs/PROTOCOL.md, "Ack datagram" and "Refusal datagram".
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from cranetwin.protocol.errors import REFUSAL_CODES, REFUSAL_REASONS, GarbageError, TruncatedError
from cranetwin.protocol.wire import (
    TYPE_ACK,
    TYPE_REFUSAL,
    VERSION,
    MachineKey,
    open_datagram,
    pack_header,
    tag,
)

ACK_FIXED = struct.Struct(">QqB")  # cumulative, server time, bitmap length
REFUSAL_FIXED = struct.Struct(">QqB")  # seq, server time, reason code
MAX_SACK_BYTES = 128  # selective acks cover cumulative + 1 … cumulative + 1024


@dataclass(frozen=True)
class Ack:
    """A decoded acknowledgement.

    Attributes:
        cumulative: Every seq < cumulative (of ``epoch``) is durable or released.
        selective: Durable seqs above ``cumulative`` (each in cumulative + 1 … + 1024), sorted.
        server_time_ns: Server clock when the ack was sent [ns since the Unix epoch].
        epoch: The sender epoch the ack is for (0 for a version-1 ack).
    """

    cumulative: int
    selective: tuple[int, ...] = ()
    server_time_ns: int = 0
    epoch: int = 0

    def covers(self, seq: int) -> bool:
        """Whether ``seq`` is acknowledged by this ack."""
        return seq < self.cumulative or seq in self.selective


@dataclass(frozen=True)
class Refusal:
    """A decoded refusal: the server will never store datagram ``seq`` of ``epoch``.

    Attributes:
        epoch: Sender epoch of the refused datagram.
        seq: Its sequence number.
        reason: One of :data:`~cranetwin.protocol.errors.REFUSAL_CODES` ("unknown" for a code
            this version does not know).
        server_time_ns: Server clock when the refusal was sent [ns since the Unix epoch].
    """

    epoch: int
    seq: int
    reason: str
    server_time_ns: int = 0


def encode_ack(key: MachineKey, cumulative: int, selective: Iterable[int] = (), *,
               server_time_ns: int = 0, epoch: int = 1, version: int = VERSION) -> bytes:
    """Encode an authenticated ack. Selective seqs beyond cumulative + 1024 are left out (they will
    be acknowledged by a later ack); seqs ≤ cumulative are ignored.

    Args:
        key: The machine's key.
        cumulative: Every seq below is durable or released, 0 ≤ cumulative < 2**64.
        selective: Further durable seqs.
        server_time_ns: Server clock [ns since the Unix epoch].
        epoch: Sender epoch acknowledged (version 2).
        version: 2, or 1 to answer a version-1 sender (``epoch`` is then ignored).

    Raises:
        ValueError: cumulative outside [0, 2**64) or a bad epoch.
    """
    if not 0 <= cumulative < 2**64:
        raise ValueError(f"cumulative ack must be in [0, 2**64), got {cumulative}")
    offs = sorted({s - cumulative - 1 for s in selective
                   if 0 <= s - cumulative - 1 < 8 * MAX_SACK_BYTES})
    nbytes = (offs[-1] // 8 + 1) if offs else 0
    bits = np.zeros(8 * nbytes, dtype=np.uint8)
    bits[offs] = 1
    out = pack_header(version, TYPE_ACK, key.wire_id, 0 if version == 1 else epoch)
    out += ACK_FIXED.pack(cumulative, server_time_ns, nbytes)
    out += np.packbits(bits).tobytes()
    out += tag(key.secret, out)
    return bytes(out)


def decode_ack(datagram: bytes, key: MachineKey) -> Ack:
    """Authenticate and decode an ack datagram (version 1 or 2).

    Raises:
        DatagramError: any subclass, for any malformed, truncated or forged input.
    """
    head, body = open_datagram(datagram, key, TYPE_ACK, "ack", ACK_FIXED.size)
    wid = head.wire_id
    fixed_end = head.size + ACK_FIXED.size
    cum, server_ns, nbytes = ACK_FIXED.unpack_from(body, head.size)
    if nbytes > MAX_SACK_BYTES:
        raise GarbageError(f"selective bitmap of {nbytes} bytes > {MAX_SACK_BYTES}", wid)
    if len(body) != fixed_end + nbytes:
        cls = TruncatedError if len(body) < fixed_end + nbytes else GarbageError
        raise cls(f"ack body is {len(body)} bytes, fields say {fixed_end + nbytes}", wid)
    bits = np.unpackbits(np.frombuffer(body[fixed_end:], dtype=np.uint8))
    sel = tuple(cum + 1 + int(i) for i in np.flatnonzero(bits))
    if sel and sel[-1] >= 2**64:
        raise GarbageError("selective ack beyond 2**64", wid)
    return Ack(cumulative=cum, selective=sel, server_time_ns=server_ns, epoch=head.epoch)


def encode_refusal(key: MachineKey, epoch: int, seq: int, reason: str, *,
                   server_time_ns: int = 0) -> bytes:
    """Encode an authenticated refusal of datagram ``seq`` of ``epoch`` (version 2 only).

    Raises:
        ValueError: unknown reason, seq outside [0, 2**64) or a bad epoch.
    """
    if reason not in REFUSAL_CODES:
        raise ValueError(f"unknown refusal reason {reason!r}; one of {sorted(REFUSAL_CODES)}")
    if not 0 <= seq < 2**64:
        raise ValueError(f"seq must be in [0, 2**64), got {seq}")
    out = pack_header(2, TYPE_REFUSAL, key.wire_id, epoch)
    out += REFUSAL_FIXED.pack(seq, server_time_ns, REFUSAL_CODES[reason])
    out += tag(key.secret, out)
    return bytes(out)


def decode_refusal(datagram: bytes, key: MachineKey) -> Refusal:
    """Authenticate and decode a refusal datagram.

    Raises:
        DatagramError: any subclass, for any malformed, truncated or forged input.
    """
    head, body = open_datagram(datagram, key, TYPE_REFUSAL, "refusal", REFUSAL_FIXED.size)
    if len(body) != head.size + REFUSAL_FIXED.size:
        raise GarbageError("refusal longer than its fields", head.wire_id)
    seq, server_ns, code = REFUSAL_FIXED.unpack_from(body, head.size)
    return Refusal(head.epoch, seq, REFUSAL_REASONS.get(code, "unknown"), server_ns)
