"""Status datagrams: low-rate machine status (type 0x02).

GPS position, operating-hours counter and any channels of the layout sent at low rate (typically
the ones declared ``optional`` in the machine description: slew angle, load cell). Status
datagrams share the machine's sequence space with data datagrams and are acknowledged the same
way. Byte layout: docs/PROTOCOL.md, "Status datagram".
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field

from cranetwin.protocol.errors import GarbageError, LayoutError, TruncatedError
from cranetwin.protocol.wire import (
    SEQ_LIMIT,
    TAG_BYTES,
    TYPE_STATUS,
    VERSION,
    Header,
    MachineKey,
    get_varint,
    open_datagram,
    pack_header,
    peek_header,
    put_varint,
    tag,
    unzigzag,
    zigzag,
)

STATUS_FIXED = struct.Struct(">QqIBiiiI")  # seq, t, layout, flags, lat, lon, alt, op seconds
FLAG_GPS = 0x01
FLAG_HOURS = 0x02
DEG_SCALE = 1e7  # latitude/longitude in 1e-7 degree (≈ 1.1 cm)
ALT_SCALE = 1e3  # altitude in mm


@dataclass(frozen=True)
class StatusReport:
    """Decoded machine status.

    Attributes:
        machine_id: Machine identifier.
        seq: Sequence number (shared with data datagrams).
        t_ns: Time of the report [ns since the Unix epoch, machine clock].
        latitude_deg: WGS-84 latitude [deg], NaN if no GPS fix (resolution 1e-7 deg).
        longitude_deg: WGS-84 longitude [deg], NaN if no GPS fix.
        altitude_m: Altitude above the WGS-84 ellipsoid [m] (resolution 1 mm), NaN if no fix.
        operating_hours: Operating-hours counter [h] (resolution 1 s), NaN if not reported.
        channels: Low-rate channel readings by name [channel units], on the resolution grid.
        epoch: The sender's epoch (see :class:`cranetwin.samples.SampleBlock`).
    """

    machine_id: str
    seq: int
    t_ns: int
    latitude_deg: float = math.nan
    longitude_deg: float = math.nan
    altitude_m: float = math.nan
    operating_hours: float = math.nan
    channels: Mapping[str, float] = field(default_factory=dict)
    epoch: int = 0


def encode_status(key: MachineKey, report: StatusReport, *,
                  oldest_unacked: int | None = None, version: int = VERSION) -> bytes:
    """Encode ``report`` as an authenticated status datagram (``report.machine_id`` is ignored;
    the key's wire id is sent; ``report.epoch`` is the sender's epoch: 0 with ``version=1``,
    and 0 means epoch 1 in version 2, like :func:`~cranetwin.protocol.encode_data`'s default).

    Raises:
        ValueError: a field outside its wire range or an unknown channel name.
    """
    seq = report.seq
    low = seq if oldest_unacked is None else oldest_unacked
    if not 0 <= low <= seq < (SEQ_LIMIT if version >= 2 else 2**64):
        raise ValueError(f"need 0 ≤ oldest_unacked ≤ seq < 2**63, got {low}, {seq}")
    flags = 0
    lat = lon = alt = 0
    if not (math.isnan(report.latitude_deg) or math.isnan(report.longitude_deg)):
        if not (abs(report.latitude_deg) <= 90 and abs(report.longitude_deg) <= 180):
            raise ValueError("latitude must be in [-90, 90] and longitude in [-180, 180] deg")
        flags |= FLAG_GPS
        lat = round(report.latitude_deg * DEG_SCALE)
        lon = round(report.longitude_deg * DEG_SCALE)
        alt = 0 if math.isnan(report.altitude_m) else round(report.altitude_m * ALT_SCALE)
        if not -(2**31) <= alt < 2**31:
            raise ValueError("altitude outside ±2147 km")
    hours_s = 0
    if not math.isnan(report.operating_hours):
        hours_s = round(report.operating_hours * 3600.0)
        if not 0 <= hours_s < 2**32:
            raise ValueError("operating hours outside [0, 2**32 s)")
        flags |= FLAG_HOURS
    layout = key.layout
    epoch = 0 if version == 1 else (report.epoch or 1)
    out = pack_header(version, TYPE_STATUS, key.wire_id, epoch)
    out += STATUS_FIXED.pack(seq, report.t_ns, layout.layout_id, flags, lat, lon, alt, hours_s)
    put_varint(out, seq - low)
    items = [(layout.index(name), v) for name, v in report.channels.items() if not math.isnan(v)]
    if len(items) > 255:
        raise ValueError("at most 255 status channels")
    out.append(len(items))
    for j, v in sorted(items):
        out.append(j)
        put_varint(out, zigzag(round(v / layout.channels[j].resolution)))
    out += tag(key.secret, out)
    return bytes(out)


def decode_status(datagram: bytes, key: MachineKey) -> StatusReport:
    """Authenticate and decode a status datagram (no replay check: see :class:`Receiver`).

    Raises:
        DatagramError: any subclass, for any malformed, truncated, forged or mismatched input.
    """
    head, body = open_datagram(datagram, key, TYPE_STATUS, "status", STATUS_FIXED.size)
    return parse_status(head, body, key)


def parse_status(head: Header, body: memoryview, key: MachineKey) -> StatusReport:
    """Decode the authenticated ``body`` (header included, tag excluded) of a status datagram
    whose HMAC the caller has verified (:func:`decode_status` does both).

    Raises:
        DatagramError: any subclass, for malformed or mismatched fields.
    """
    wid = head.wire_id
    end = len(body)
    fixed_end = head.size + STATUS_FIXED.size
    if end < fixed_end:
        raise TruncatedError("status datagram shorter than its fixed fields", wid)
    seq, t_ns, layout_id, flags, lat, lon, alt, hours_s = STATUS_FIXED.unpack_from(
        body, head.size)
    layout = key.layout
    if layout_id != layout.layout_id:
        raise LayoutError(f"layout id {layout_id:#010x}, machine has {layout.layout_id:#010x}",
                          wid)
    if flags & ~(FLAG_GPS | FLAG_HOURS):
        raise GarbageError(f"reserved status flag bits set ({flags:#04x})", wid)
    lag, pos = get_varint(body, fixed_end, end)
    if lag > seq:
        raise GarbageError("oldest-unacknowledged lag exceeds the sequence number", wid)
    if pos >= end:
        raise TruncatedError("status channel count missing", wid)
    count = body[pos]
    pos += 1
    channels: dict[str, float] = {}
    for _ in range(count):
        if pos >= end:
            raise TruncatedError("status channel entry runs past the end", wid)
        j = body[pos]
        pos += 1
        if j >= len(layout.channels):
            raise LayoutError(f"status channel index {j} beyond the layout", wid)
        z, pos = get_varint(body, pos, end)
        ch = layout.channels[j]
        if ch.name in channels:
            raise GarbageError(f"status channel {ch.name!r} repeated", wid)
        channels[ch.name] = float(unzigzag(z)) * ch.resolution
    if pos != end:
        raise GarbageError(f"{end - pos} unexpected bytes before the tag", wid)
    gps = bool(flags & FLAG_GPS)
    if gps and not (abs(lat) <= 90 * DEG_SCALE and abs(lon) <= 180 * DEG_SCALE):
        raise GarbageError("GPS position outside ±90° / ±180°", wid)
    return StatusReport(
        machine_id=key.machine_id, seq=seq, t_ns=t_ns,
        latitude_deg=lat / DEG_SCALE if gps else math.nan,
        longitude_deg=lon / DEG_SCALE if gps else math.nan,
        altitude_m=alt / ALT_SCALE if gps else math.nan,
        operating_hours=hours_s / 3600.0 if flags & FLAG_HOURS else math.nan,
        channels=channels, epoch=head.epoch)


def status_lag(datagram: bytes | memoryview) -> int:
    """``seq − oldest_unacked`` of a status datagram (not authenticated here)."""
    head = peek_header(datagram)
    lag, _ = get_varint(datagram, head.size + STATUS_FIXED.size, len(datagram) - TAG_BYTES)
    return lag
