"""Wire primitives: constants, varints, the common header, channel layouts, keys and tags.

Every multi-byte integer is big-endian ("network order"), except varints, which are unsigned
LEB128 (7 bits per byte, least significant group first, high bit = "more bytes follow", at most
10 bytes, value < 2**64; the same as Protocol Buffers). Signed values in varints are zigzag
mapped: ``z = (v << 1) ^ (v >> 63)``, i.e. 0, −1, 1, −2, … → 0, 1, 2, 3, … (:mod:`cranetwin.codec`,
re-exported here). See docs/PROTOCOL.md.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

from cranetwin.codec.delta import unzigzag as unzigzag  # re-exported: the wire's zigzag
from cranetwin.codec.delta import zigzag as zigzag
from cranetwin.protocol.errors import (
    BadHmacError,
    GarbageError,
    TruncatedError,
    WrongVersionError,
)

MAGIC = b"CT"
VERSION = 2
"""The version this code sends. Version 1 (no epoch) is still decoded, as epoch 0, and answered
in version 1, so that a fleet can be upgraded server first (docs/PROTOCOL.md, "Versions")."""
VERSIONS = (1, 2)
TYPE_DATA = 0x01
TYPE_STATUS = 0x02
TYPE_ACK = 0x03
TYPE_REFUSAL = 0x04
TYPES = (TYPE_DATA, TYPE_STATUS, TYPE_ACK, TYPE_REFUSAL)
TAG_BYTES = 16
"""HMAC-SHA256 truncated to 128 bits: forging one datagram takes ~2**127 tries on average
(NIST SP 800-107 allows truncation to ≥ 64 bits for HMAC), and saves 16 bytes per datagram."""
HEADER_V1 = struct.Struct(">2sBBI")  # magic, version, type, wire id
HEADER = struct.Struct(">2sBBIQ")  # magic, version, type, wire id, epoch (version 2)
HEADER_BYTES = HEADER.size  # 16
EPOCH_MAX = 2**63 - 1
"""Largest epoch (and exclusive bound of sequence numbers): both fit a signed 64-bit column."""
SEQ_LIMIT = 2**63
MAX_DATAGRAM = 1200
"""Largest datagram the sender produces [bytes of UDP payload]: fits the MTU of 4G and VPN links
(1280-byte IPv6 minimum MTU minus 48 bytes of IPv6+UDP headers, with margin)."""
MAX_CHANNELS = 32
U64_MAX = 2**64 - 1
IP_UDP_OVERHEAD_V4 = 28  # 20 bytes IPv4 + 8 bytes UDP, not counted in bytes/sample
IP_UDP_OVERHEAD_V6 = 48  # 40 bytes IPv6 + 8 bytes UDP


# --- varints -----------------------------------------------------------------------------------
def put_varint(out: bytearray, value: int) -> None:
    """Append ``value`` (0 ≤ value < 2**64) as an unsigned LEB128 varint."""
    if not 0 <= value <= U64_MAX:
        raise ValueError(f"varint value {value} outside [0, 2**64)")
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def get_varint(buf: bytes | memoryview, pos: int, end: int) -> tuple[int, int]:
    """Read an unsigned LEB128 varint from ``buf[pos:end]``.

    Returns:
        ``(value, new_pos)``.

    Raises:
        TruncatedError: the varint runs past ``end``.
        GarbageError: longer than 10 bytes or ≥ 2**64.
    """
    value = 0
    shift = 0
    while True:
        if pos >= end:
            raise TruncatedError("varint runs past the end of the datagram")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            break
        shift += 7
        if shift >= 70:
            raise GarbageError("varint longer than 10 bytes")
    if value > U64_MAX:
        raise GarbageError("varint value ≥ 2**64")
    return value, pos


# --- layouts and keys --------------------------------------------------------------------------
class ChannelLike(Protocol):
    """What the protocol needs of a channel (``cranetwin.model.schema.Channel`` fits)."""

    @property
    def name(self) -> str: ...
    @property
    def min(self) -> float | None: ...
    @property
    def max(self) -> float | None: ...
    @property
    def resolution(self) -> float: ...
    @property
    def optional(self) -> bool: ...


@dataclass(frozen=True)
class ChannelSpec:
    """One channel of a layout.

    Attributes:
        name: Channel name from the machine description.
        min: Lower end of the sensor range [channel unit]; −inf: unknown (no range check).
        max: Upper end of the sensor range [channel unit]; +inf: unknown (no range check).
        resolution: Quantisation step [channel unit]; values travel as k = round(v / resolution).
        optional: Declared optional in the machine description (may be absent or sent by status).
    """

    name: str
    min: float
    max: float
    resolution: float
    optional: bool = False


@dataclass(frozen=True)
class Layout:
    """The ordered channel list both ends agree on, from the machine description.

    Attributes:
        channels: Channels in column order (at most 32).
    """

    channels: tuple[ChannelSpec, ...]

    def __post_init__(self) -> None:
        if not 1 <= len(self.channels) <= MAX_CHANNELS:
            raise ValueError(f"a layout has 1..{MAX_CHANNELS} channels, got {len(self.channels)}")
        for c in self.channels:
            if not c.resolution > 0:
                raise ValueError(f"channel {c.name!r}: resolution must be > 0")
            if len(c.name.encode()) > 255:
                raise ValueError(f"channel {c.name!r}: name longer than 255 bytes")

    @classmethod
    def from_channels(cls, channels: Iterable[ChannelLike]) -> Layout:
        """Layout of ``machine.channels`` (objects with name, min, max, resolution, optional)."""
        return cls(tuple(ChannelSpec(c.name, -math.inf if c.min is None else float(c.min),
                                     math.inf if c.max is None else float(c.max),
                                     float(c.resolution), bool(c.optional)) for c in channels))

    @cached_property
    def names(self) -> tuple[str, ...]:
        """Channel names in column order."""
        return tuple(c.name for c in self.channels)

    @cached_property
    def resolutions(self) -> tuple[float, ...]:
        """Quantisation steps in column order [channel units]."""
        return tuple(c.resolution for c in self.channels)

    @cached_property
    def layout_id(self) -> int:
        """32-bit id: first 4 bytes (big-endian) of SHA-256 over, per channel in order,
        ``u8 len(name) ‖ name (UTF-8) ‖ f64 resolution (big-endian IEEE 754)``."""
        h = hashlib.sha256()
        for c in self.channels:
            name = c.name.encode()
            h.update(bytes([len(name)]) + name + struct.pack(">d", c.resolution))
        return int.from_bytes(h.digest()[:4], "big")

    def index(self, name: str) -> int:
        """Column of channel ``name`` (ValueError if absent)."""
        return self.names.index(name)


@dataclass(frozen=True)
class MachineKey:
    """What one end needs to speak for a machine: identity, secret and layout.

    Attributes:
        wire_id: 32-bit id carried in every datagram.
        machine_id: Identifier above the wire (``SampleBlock.machine_id``).
        secret: Per-machine HMAC key (≥ 16 bytes). Never logged: ``repr`` hides it.
        layout: Channel layout of the machine.
    """

    wire_id: int
    machine_id: str
    secret: bytes
    layout: Layout

    def __post_init__(self) -> None:
        if not 0 <= self.wire_id < 2**32:
            raise ValueError(f"wire id must be in [0, 2**32), got {self.wire_id}")
        if len(self.secret) < 16:
            raise ValueError("the per-machine secret must be at least 16 bytes")

    def __repr__(self) -> str:
        return (f"MachineKey(wire_id={self.wire_id}, machine_id={self.machine_id!r}, "
                f"secret=<{len(self.secret)} bytes>, layout_id={self.layout.layout_id:#010x})")


# --- header and tag ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Header:
    """The header every datagram starts with (8 bytes in version 1, 16 in version 2).

    Attributes:
        version: Protocol version (1 or 2).
        type: ``TYPE_DATA``, ``TYPE_STATUS``, ``TYPE_ACK`` or ``TYPE_REFUSAL``.
        wire_id: Machine wire id.
        epoch: The sender's epoch (1 … 2**63 − 1 in version 2; 0 in version 1).
    """

    version: int
    type: int
    wire_id: int
    epoch: int = 0

    @property
    def size(self) -> int:
        """Bytes of the header on the wire."""
        return HEADER.size if self.version >= 2 else HEADER_V1.size


def pack_header(version: int, typ: int, wire_id: int, epoch: int) -> bytearray:
    """The header bytes of a datagram (version 1 carries no epoch; ``epoch`` must then be 0).

    Raises:
        ValueError: unknown version, or an epoch outside 1 … 2**63 − 1 (version 2) / not 0 (1).
    """
    if version == 1:
        if epoch != 0:
            raise ValueError("version 1 datagrams have no epoch (pass epoch=0)")
        return bytearray(HEADER_V1.pack(MAGIC, 1, typ, wire_id))
    if version != 2:
        raise ValueError(f"unknown protocol version {version}")
    if not 1 <= epoch <= EPOCH_MAX:
        raise ValueError(f"epoch must be in [1, 2**63), got {epoch}")
    return bytearray(HEADER.pack(MAGIC, 2, typ, wire_id, epoch))


def peek_header(datagram: bytes | memoryview) -> Header:
    """Read and check the common header, without authenticating anything.

    Raises:
        GarbageError: wrong magic, unknown type, or a version-2 epoch of 0 or ≥ 2**63.
        TruncatedError: shorter than header + tag.
        WrongVersionError: a version this code does not speak.
    """
    if len(datagram) < HEADER_V1.size:
        if not MAGIC.startswith(bytes(datagram[:2])):
            raise GarbageError("not a cranetwin datagram (bad magic)")
        raise TruncatedError(f"{len(datagram)} bytes: shorter than the "
                             f"{HEADER_V1.size}-byte header")
    magic, version, typ, wire_id = HEADER_V1.unpack_from(datagram, 0)
    if magic != MAGIC:
        raise GarbageError("not a cranetwin datagram (bad magic)")
    if version not in VERSIONS:
        raise WrongVersionError(f"protocol version {version}, this code speaks {VERSIONS}",
                                wire_id)
    if typ not in TYPES or (version == 1 and typ == TYPE_REFUSAL):
        raise GarbageError(f"unknown datagram type {typ:#04x}", wire_id)
    epoch = 0
    if version >= 2:
        if len(datagram) < HEADER.size + TAG_BYTES:
            raise TruncatedError("datagram shorter than header + HMAC tag", wire_id)
        epoch = int(HEADER.unpack_from(datagram, 0)[4])
        if not 1 <= epoch <= EPOCH_MAX:
            raise GarbageError(f"epoch {epoch} outside [1, 2**63)", wire_id)
    elif len(datagram) < HEADER_V1.size + TAG_BYTES:
        raise TruncatedError("datagram shorter than header + HMAC tag", wire_id)
    return Header(version, typ, wire_id, epoch)


def tag(secret: bytes, body: bytes | bytearray | memoryview) -> bytes:
    """HMAC-SHA256 of ``body`` under ``secret``, truncated to :data:`TAG_BYTES`."""
    return hmac.new(secret, body, hashlib.sha256).digest()[:TAG_BYTES]


def verify(secret: bytes, datagram: bytes, wire_id: int) -> memoryview:
    """Check the trailing tag in constant time; return the authenticated part (without tag).

    Raises:
        BadHmacError: the tag does not verify.
    """
    view = memoryview(datagram)
    body = view[:-TAG_BYTES]
    if not hmac.compare_digest(tag(secret, body), bytes(view[-TAG_BYTES:])):
        raise BadHmacError("HMAC tag does not verify under the machine's key", wire_id)
    return body


def open_datagram(
    datagram: bytes, key: MachineKey, expected_type: int, kind: str, fixed_size: int
) -> tuple[Header, memoryview]:
    """Check type, wire id and HMAC of a data or status datagram; return (header, body).

    ``body`` is the authenticated part (header included, tag excluded), at least
    ``header.size + fixed_size`` bytes long.

    Raises:
        DatagramError: any subclass, for a wrong type or wire id, a bad tag or a short body.
    """
    head = peek_header(datagram)
    wid = head.wire_id
    if head.type != expected_type:
        raise GarbageError(
            f"expected a {kind} datagram (type {expected_type:#04x}), got {head.type:#04x}", wid)
    if wid != key.wire_id:
        raise GarbageError(f"datagram for wire id {wid}, key is for {key.wire_id}", wid)
    body = verify(key.secret, datagram, wid)
    if len(body) < head.size + fixed_size:
        raise TruncatedError(f"{kind} datagram shorter than its fixed fields", wid)
    return head, body
