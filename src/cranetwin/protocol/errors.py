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
        ├── ReplayedError        "replayed": sequence number already durable or below the window
        └── LayoutError          "bad_layout": channel layout differs from the registered machine
"""

from __future__ import annotations

from typing import ClassVar

from cranetwin.errors import ProtocolError

REASONS: tuple[str, ...] = (
    "garbage", "truncated", "wrong_version", "unknown_machine", "bad_hmac", "replayed",
    "bad_layout",
)


class DatagramError(ProtocolError):
    """A datagram was rejected; ``reason`` is one of :data:`REASONS`.

    Attributes:
        reason: Short, fixed drop reason (for counters).
        wire_id: Machine wire id from the header, if it could be read.
        machine_id: Machine identifier, set when the datagram was authenticated (``replayed``):
            the server should answer a replay with a fresh ack, since the sender evidently
            missed the earlier one.
    """

    reason: ClassVar[str] = "garbage"

    def __init__(self, message: str, wire_id: int | None = None,
                 machine_id: str | None = None) -> None:
        super().__init__(message)
        self.wire_id = wire_id
        self.machine_id = machine_id


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
