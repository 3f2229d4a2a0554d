"""Why a datagram was rejected: one :class:`DatagramError` subclass per drop reason.

Every decoding or receiving function of :mod:`cranetwin.protocol` raises only these, whatever the
input bytes; the ingest daemon catches :class:`DatagramError` (itself a
:class:`cranetwin.errors.ProtocolError`) and counts drops by ``err.reason``::

    ProtocolError
    └── DatagramError            reason ∈ REASONS
        ├── GarbageError         "garbage": not our magic, unknown type, bad field values
        ├── TruncatedError       "truncated": shorter than its fields say
        ├── WrongVersionError    "wrong_version": a protocol version this code does not speak
        ├── UnknownMachineError  "unknown_machine": wire id not registered
        ├── BadHmacError         "bad_hmac": authentication tag does not verify
        ├── ReplayedError        "replayed": (epoch, seq) already durable: answered with an ack
        ├── LayoutError          "bad_layout": channel layout differs from the registered machine
        └── RefusedError         authenticated, valid in form, but never to be stored: answered
            │                    with a refusal datagram (type 0x04) carrying REFUSAL_CODES[reason]
            ├── OutOfRangeError  "out_of_range": a value beyond its sensor's range (+ margin)
            ├── BadTimeError     "bad_time": timestamps outside the window around server time
            ├── OversizeError    "oversize": datagram larger than the protocol's 1200 bytes
            ├── BadSeqError      "bad_seq": sequence number ≥ 2**63
            └── (storage-level)  "unstorable", "seq_reused", "overlap": see
                                 :meth:`cranetwin.protocol.Receiver.refuse`

Errors of authenticated datagrams (``replayed``, ``bad_layout`` and the refusals) carry
``machine_id``, ``epoch`` and ``seq``; all others only the ``wire_id`` read from the header, and
the server never answers them (nothing is trusted before the HMAC verified).
"""

from __future__ import annotations

from typing import ClassVar

from cranetwin.errors import ProtocolError

REFUSAL_CODES: dict[str, int] = {
    "out_of_range": 1, "bad_time": 2, "oversize": 3, "bad_seq": 4, "unstorable": 5,
    "seq_reused": 6, "overlap": 7,
}
"""Refusal reason → the u8 code carried by a refusal datagram (docs/PROTOCOL.md §6)."""
REFUSAL_REASONS: dict[int, str] = {v: k for k, v in REFUSAL_CODES.items()}

REASONS: tuple[str, ...] = (
    "garbage", "truncated", "wrong_version", "unknown_machine", "bad_hmac", "replayed",
    "bad_layout", *REFUSAL_CODES,
)


class DatagramError(ProtocolError):
    """A datagram was rejected; ``reason`` is one of :data:`REASONS`.

    Attributes:
        reason: Short, fixed drop reason (for counters).
        wire_id: Machine wire id from the header, if it could be read.
        machine_id: Machine identifier, set only when the datagram was authenticated
            (``replayed``, ``bad_layout``, refusals).
        epoch: The sender's epoch of an authenticated datagram (0 in version 1).
        seq: Its sequence number (None when not authenticated).
        version: Protocol version of an authenticated datagram (the answer uses the same).
    """

    reason: ClassVar[str] = "garbage"

    def __init__(self, message: str, wire_id: int | None = None,
                 machine_id: str | None = None, *, epoch: int = 0, seq: int | None = None,
                 version: int = 2) -> None:
        super().__init__(message)
        self.wire_id = wire_id
        self.machine_id = machine_id
        self.epoch = epoch
        self.seq = seq
        self.version = version

    @property
    def authenticated(self) -> bool:
        """Whether the datagram's HMAC verified (only then may the server answer it)."""
        return self.machine_id is not None and self.seq is not None


class GarbageError(DatagramError):
    """Not a cranetwin datagram, or a field holds an impossible value."""

    reason = "garbage"


class TruncatedError(DatagramError):
    """The datagram ends before its fields do."""

    reason = "truncated"


class WrongVersionError(DatagramError):
    """Protocol version not spoken by this code."""

    reason = "wrong_version"


class UnknownMachineError(DatagramError):
    """No key is registered for the datagram's wire id."""

    reason = "unknown_machine"


class BadHmacError(DatagramError):
    """The HMAC tag does not verify under the machine's key (forged or corrupted)."""

    reason = "bad_hmac"


class ReplayedError(DatagramError):
    """Sequence number already durable (acknowledged) or below the machine's window."""

    reason = "replayed"


class LayoutError(DatagramError):
    """The datagram's channel layout id or channel mask does not match the machine."""

    reason = "bad_layout"


class RefusedError(DatagramError):
    """An authenticated datagram that will never be stored; the server answers it with a
    refusal so that the sender stops retransmitting it (and keeps it for its operator)."""

    reason = "unstorable"


class OutOfRangeError(RefusedError):
    """A value lies beyond its sensor's declared range by more than the allowed margin."""

    reason = "out_of_range"


class BadTimeError(RefusedError):
    """Sample or report times outside the accepted window around the server's clock."""

    reason = "bad_time"


class OversizeError(RefusedError):
    """Datagram larger than the protocol allows (1200 bytes)."""

    reason = "oversize"


class BadSeqError(RefusedError):
    """Sequence number outside [0, 2**63)."""

    reason = "bad_seq"
