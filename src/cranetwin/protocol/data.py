"""Data datagrams: a batch of regularly spaced samples of one machine (type 0x01).

Compression (lossless at sensor resolution): each value travels as the integer
k = round(v / resolution); per channel the first k is sent as a zigzag varint and the n − 1
differences d_i = k_i − k_{i−1} as fixed-width unsigned offsets ``d_i − min(d)`` of the smallest bit
width w that holds ``max(d) − min(d)`` (frame-of-reference bit packing). Smooth motion plus a few
quanta of sensor noise gives w ≈ 3–6 bits, i.e. under 1 byte per channel per sample. Missing
samples (NaN) are flagged in a per-channel dropout bitmap; a channel that is entirely missing is
left out via the channel mask. Byte layout: docs/PROTOCOL.md, "Data datagram". The integer
transforms are :mod:`cranetwin.codec`'s; this module frames them. A decoded block carries the
integer steps (``SampleBlock.steps``) so that storage keeps them without a float round trip.
"""

from __future__ import annotations

import struct

import numpy as np
import numpy.typing as npt

from cranetwin import codec
from cranetwin.codec import on_grid as on_grid  # re-exported
from cranetwin.protocol.errors import GarbageError, LayoutError, TruncatedError
from cranetwin.protocol.wire import (
    SEQ_LIMIT,
    TAG_BYTES,
    TYPE_DATA,
    VERSION,
    Header,
    MachineKey,
    get_varint,
    open_datagram,
    pack_header,
    peek_header,
    put_varint,
    tag,
)
from cranetwin.samples import SampleBlock

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

DATA_FIXED = struct.Struct(">QqIHII")  # seq, t0_ns, period_ns, n, layout_id, channel mask
"""Fixed fields after the header (30 bytes); the lag varint follows them."""
MAX_SAMPLES = 4096
FLAG_DROPOUTS = 0x01


def quantise(values: F64, resolution: tuple[float, ...]) -> tuple[I64, npt.NDArray[np.bool_]]:
    """Integers on the sensor grid, k = round(v / resolution), and the missing mask
    (:func:`cranetwin.codec.quantise`).

    Raises:
        ValueError: shapes disagree, or a value is infinite or beyond ±2**53 quanta.
    """
    return codec.quantise(values, resolution)


def encode_data(key: MachineKey, seq: int, t0_ns: int, period_ns: int, values: F64, *,
                oldest_unacked: int | None = None, epoch: int = 1,
                version: int = VERSION) -> bytes:
    """Encode one batch as an authenticated data datagram.

    Args:
        key: Machine identity, secret and layout.
        seq: Sequence number (0 ≤ seq < 2**63), unique within the epoch and never reused.
        t0_ns: Time of the first sample [ns since the Unix epoch, machine clock].
        period_ns: Sample period [ns], 1 ≤ period_ns < 2**32.
        values: Samples, shape (n, c) with c = len(key.layout.channels), 1 ≤ n ≤ 4096, in layout
            column order [channel units]; NaN = missing. Values are quantised to the channel
            resolution (lossless for values on the grid k · resolution).
        oldest_unacked: Lowest sequence number the sender still holds unacknowledged (≤ seq;
            default seq). Lets the receiver forget what the sender no longer holds.
        epoch: The sender's epoch, 1 … 2**63 − 1 (version 2; the sender's journal keeps it).
        version: 2, or 1 for the legacy format without epoch (pass ``epoch=0``).

    Returns:
        The datagram (UDP payload).

    Raises:
        ValueError: arguments outside the ranges above.
    """
    layout = key.layout
    v = np.asarray(values, dtype=np.float64)
    c = len(layout.channels)
    if v.ndim != 2 or v.shape[1] != c:
        raise ValueError(f"values must have shape (n, {c}), got {v.shape}")
    n = v.shape[0]
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"a datagram carries 1..{MAX_SAMPLES} samples, got {n}")
    if not 1 <= period_ns < 2**32:
        raise ValueError(f"period_ns must be in [1, 2**32), got {period_ns}")
    if not -(2**63) <= t0_ns < 2**63:
        raise ValueError("t0_ns outside the signed 64-bit range")
    low = seq if oldest_unacked is None else oldest_unacked
    if not 0 <= low <= seq < (SEQ_LIMIT if version >= 2 else 2**64):
        raise ValueError(f"need 0 ≤ oldest_unacked ≤ seq < 2**63, got {low}, {seq}")
    k, missing = quantise(v, layout.resolutions)
    present = ~missing.all(axis=0)
    cols = np.flatnonzero(present)
    mask = 0
    for j in cols:
        mask |= 1 << int(j)
    out = pack_header(version, TYPE_DATA, key.wire_id, 0 if version == 1 else epoch)
    out += DATA_FIXED.pack(seq, t0_ns, period_ns, n, layout.layout_id, mask)
    put_varint(out, seq - low)
    miss = missing[:, cols]
    gappy: npt.NDArray[np.bool_] = np.asarray(miss.any(axis=0))
    k = codec.carry_through_gaps(k[:, cols], miss)  # gaps add no deltas
    if n > 1:
        d = codec.deltas(k)
        dmin = d.min(axis=0)
        widths = codec.row_widths(d.max(axis=0) - dmin)
    else:
        dmin = np.zeros(len(cols), dtype=np.int64)
        widths = [0] * len(cols)
    firsts = k[0]
    packed_bitmaps = np.packbits(miss, axis=0) if gappy.any() else None
    for i in range(len(cols)):
        out.append(FLAG_DROPOUTS if gappy[i] else 0)
        put_varint(out, codec.zigzag(int(firsts[i])))
        if n > 1:
            put_varint(out, codec.zigzag(int(dmin[i])))
            out.append(widths[i])
        if packed_bitmaps is not None and gappy[i]:
            out += packed_bitmaps[:, i].tobytes()
    if n > 1 and any(widths):
        sel = [i for i, w in enumerate(widths) if w]
        offs = (d[:, sel] - dmin[sel]).view(np.uint64).T  # channel-major rows
        out += codec.pack_rows(offs, tuple(widths[i] for i in sel))
    out += tag(key.secret, out)
    return bytes(out)


def decode_data(datagram: bytes, key: MachineKey) -> SampleBlock:
    """Authenticate and decode a data datagram (no replay check: see :class:`Receiver`).

    Args:
        datagram: UDP payload.
        key: The key registered for the datagram's wire id.

    Returns:
        The samples, values shape (n, c) in layout order; NaN where missing or not sent.

    Raises:
        DatagramError: any subclass, for any malformed, truncated, forged or mismatched input.
    """
    head, body = open_datagram(datagram, key, TYPE_DATA, "data", DATA_FIXED.size)
    return parse_data(head, body, key)


def parse_data(head: Header, body: memoryview, key: MachineKey) -> SampleBlock:
    """Decode the authenticated ``body`` (header included, tag excluded) of a data datagram whose
    HMAC the caller has verified (:func:`decode_data` does both).

    Raises:
        DatagramError: any subclass, for malformed or mismatched fields.
    """
    wid = head.wire_id
    end = len(body)
    fixed_end = head.size + DATA_FIXED.size
    if end < fixed_end:
        raise TruncatedError("data datagram shorter than its fixed fields", wid)
    seq, t0_ns, period_ns, n, layout_id, mask = DATA_FIXED.unpack_from(body, head.size)
    layout = key.layout
    c = len(layout.channels)
    if layout_id != layout.layout_id:
        raise LayoutError(f"layout id {layout_id:#010x}, machine has {layout.layout_id:#010x}",
                          wid)
    if mask >> c:
        raise LayoutError(f"channel mask {mask:#x} names channels beyond the {c} of the layout",
                          wid)
    if not 1 <= n <= MAX_SAMPLES or period_ns == 0:
        raise GarbageError(f"n = {n} samples, period {period_ns} ns: outside 1..{MAX_SAMPLES}, > 0",
                           wid)
    lag, pos = get_varint(body, fixed_end, end)
    if lag > seq:
        raise GarbageError("oldest-unacknowledged lag exceeds the sequence number", wid)
    cols = [j for j in range(c) if mask >> j & 1]
    firsts: list[int] = []
    dmins: list[int] = []
    widths: list[int] = []
    gaps: list[bytes | None] = []
    nbitmap = (n + 7) // 8
    for _ in cols:
        if pos >= end:
            raise TruncatedError("channel header runs past the end", wid)
        flags = body[pos]
        pos += 1
        if flags & ~FLAG_DROPOUTS:
            raise GarbageError(f"reserved channel flag bits set ({flags:#04x})", wid)
        z, pos = get_varint(body, pos, end)
        firsts.append(codec.unzigzag(z))
        if n > 1:
            z, pos = get_varint(body, pos, end)
            dmins.append(codec.unzigzag(z))
            if pos >= end:
                raise TruncatedError("bit width runs past the end", wid)
            w = body[pos]
            pos += 1
            if w > 64:
                raise GarbageError(f"bit width {w} > 64", wid)
            widths.append(w)
        else:
            dmins.append(0)
            widths.append(0)
        if flags & FLAG_DROPOUTS:
            if pos + nbitmap > end:
                raise TruncatedError("dropout bitmap runs past the end", wid)
            pad = 8 * nbitmap - n
            if pad and body[pos + nbitmap - 1] & ((1 << pad) - 1):
                raise GarbageError("dropout bitmap padding bits are not zero", wid)
            gaps.append(bytes(body[pos:pos + nbitmap]))
            pos += nbitmap
        else:
            gaps.append(None)
    nbits = (n - 1) * sum(widths)
    nbytes = (nbits + 7) // 8
    if end - pos < nbytes:
        raise TruncatedError(f"packed deltas need {nbytes} bytes, {end - pos} left", wid)
    if end - pos > nbytes:
        raise GarbageError(f"{end - pos - nbytes} unexpected bytes before the tag", wid)
    if nbits % 8 and body[end - 1] & ((1 << (8 - nbits % 8)) - 1):
        raise GarbageError("bit-stream padding bits are not zero", wid)
    ncol = len(cols)
    res = layout.resolutions
    if not ncol:
        return SampleBlock(machine_id=key.machine_id, seq=seq, t0_ns=t0_ns,
                           period_ns=period_ns, channels=layout.names, resolution=res,
                           values=np.full((n, c), np.nan), epoch=head.epoch,
                           steps=np.zeros((n, c), dtype=np.int64))
    k = np.empty((n, ncol), dtype=np.int64)
    k[0] = [_wrap(f) for f in firsts]
    if n > 1:
        nz = tuple(w for w in widths if w)
        offs = np.zeros((ncol, n - 1), dtype=np.uint64)
        if nz:
            offs[[i for i, w in enumerate(widths) if w]] = codec.unpack_rows(body[pos:end],
                                                                             n - 1, nz)
        dm = np.asarray([_wrap(x) & (2**64 - 1) for x in dmins], dtype=np.uint64)
        k[1:] = codec.undelta((offs.T + dm).view(np.int64), start=k[0])  # wraps mod 2**64
    miss = None
    gi = [i for i, g in enumerate(gaps) if g is not None]
    if gi:
        bm = np.unpackbits(np.frombuffer(b"".join(g for g in gaps if g is not None),
                                         dtype=np.uint8)).reshape(len(gi), -1)[:, :n]
        miss = np.zeros((n, ncol), dtype=bool)
        miss[:, gi] = bm.T.astype(bool)
        k[miss] = 0
    if ncol == c:
        steps, values = k, codec.dequantise(k, miss, res)
    else:
        steps = np.zeros((n, c), dtype=np.int64)
        steps[:, cols] = k
        values = np.full((n, c), np.nan)
        values[:, cols] = codec.dequantise(k, miss, [res[j] for j in cols])
    return SampleBlock(machine_id=key.machine_id, seq=seq, t0_ns=t0_ns, period_ns=period_ns,
                       channels=layout.names, resolution=res, values=values, epoch=head.epoch,
                       steps=steps)


def _wrap(v: int) -> int:
    """``v`` reduced to a signed 64-bit integer (two's complement)."""
    v &= 2**64 - 1
    return v - 2**64 if v >= 2**63 else v


def data_lag(datagram: bytes | memoryview) -> int:
    """``seq − oldest_unacked`` of a data datagram (not authenticated here)."""
    head = peek_header(datagram)
    lag, _ = get_varint(datagram, head.size + DATA_FIXED.size, len(datagram) - TAG_BYTES)
    return lag
