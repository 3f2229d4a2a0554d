"""Acknowledgement datagrams from the server (type 0x03): cumulative plus selective.

``cumulative`` = c means every sequence number below c is durable on the server (or was released
by the sender, see ``oldest_unacked``); bit i of the selective bitmap means c + 1 + i is durable
too. The server sends an ack only after the datagrams it covers are committed. Acks are
authenticated with the machine's key like every other datagram; the type byte inside the
authenticated bytes keeps a data datagram from being reflected as an ack. Byte layout:
docs/PROTOCOL.md, "Ack datagram".
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from cranetwin.protocol.errors import GarbageError, TruncatedError
from cranetwin.protocol.wire import (
    HEADER,
    HEADER_BYTES,
    MAGIC,
    TYPE_ACK,
    VERSION,
    MachineKey,
    peek_header,
    tag,
    verify,
)

ACK_FIXED = struct.Struct(">QqB")  # cumulative, server time, bitmap length
ACK_FIXED_END = HEADER_BYTES + ACK_FIXED.size  # 25
MAX_SACK_BYTES = 128  # selective acks cover cumulative + 1 … cumulative + 1024


@dataclass(frozen=True)
class Ack:
    """A decoded acknowledgement.

    Attributes:
        cumulative: Every seq < cumulative is durable.
        selective: Durable seqs above ``cumulative`` (each in cumulative + 1 … + 1024), sorted.
        server_time_ns: Server clock when the ack was sent [ns since the Unix epoch].
    """

    cumulative: int
    selective: tuple[int, ...] = ()
    server_time_ns: int = 0

    def covers(self, seq: int) -> bool:
        """Whether ``seq`` is acknowledged by this ack."""
        return seq < self.cumulative or seq in self.selective


def encode_ack(key: MachineKey, cumulative: int, selective: Iterable[int] = (), *,
               server_time_ns: int = 0) -> bytes:
    """Encode an authenticated ack. Selective seqs beyond cumulative + 1024 are left out (they will
    be acknowledged by a later ack); seqs ≤ cumulative are ignored.

    Raises:
        ValueError: cumulative outside [0, 2**64).
    """
    if not 0 <= cumulative < 2**64:
        raise ValueError(f"cumulative ack must be in [0, 2**64), got {cumulative}")
    offs = sorted({s - cumulative - 1 for s in selective
                   if 0 <= s - cumulative - 1 < 8 * MAX_SACK_BYTES})
    nbytes = (offs[-1] // 8 + 1) if offs else 0
    bits = np.zeros(8 * nbytes, dtype=np.uint8)
    bits[offs] = 1
    out = bytearray(HEADER.pack(MAGIC, VERSION, TYPE_ACK, key.wire_id))
    out += ACK_FIXED.pack(cumulative, server_time_ns, nbytes)
    out += np.packbits(bits).tobytes()
    out += tag(key.secret, out)
    return bytes(out)


def decode_ack(datagram: bytes, key: MachineKey) -> Ack:
    """Authenticate and decode an ack datagram.

    Raises:
        DatagramError: any subclass, for any malformed, truncated or forged input.
    """
    head = peek_header(datagram)
    wid = head.wire_id
    if head.type != TYPE_ACK:
        raise GarbageError(f"expected an ack datagram (type 0x03), got {head.type:#04x}", wid)
    if wid != key.wire_id:
        raise GarbageError(f"ack for wire id {wid}, key is for {key.wire_id}", wid)
    body = verify(key.secret, datagram, wid)
    if len(body) < ACK_FIXED_END:
        raise TruncatedError("ack shorter than its fixed fields", wid)
    cum, server_ns, nbytes = ACK_FIXED.unpack_from(body, HEADER_BYTES)
    if nbytes > MAX_SACK_BYTES:
        raise GarbageError(f"selective bitmap of {nbytes} bytes > {MAX_SACK_BYTES}", wid)
    if len(body) != ACK_FIXED_END + nbytes:
        cls = TruncatedError if len(body) < ACK_FIXED_END + nbytes else GarbageError
        raise cls(f"ack body is {len(body)} bytes, fields say {ACK_FIXED_END + nbytes}", wid)
    bits = np.unpackbits(np.frombuffer(body[ACK_FIXED_END:], dtype=np.uint8))
    sel = tuple(cum + 1 + int(i) for i in np.flatnonzero(bits))
    if sel and sel[-1] >= 2**64:
        raise GarbageError("selective ack beyond 2**64", wid)
    return Ack(cumulative=cum, selective=sel, server_time_ns=server_ns)
