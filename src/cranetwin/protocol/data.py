"""Data datagrams: a batch of regularly spaced samples of one machine (type 0x01).

Compression (lossless at sensor resolution): each value travels as the integer
k = round(v / resolution); per channel the first k is sent as a zigzag varint and the n − 1
differences d_i = k_i − k_{i−1} as fixed-width unsigned offsets ``d_i − min(d)`` of the smallest bit
width w that holds ``max(d) − min(d)`` (frame-of-reference bit packing). Smooth motion plus a few
quanta of sensor noise gives w ≈ 3–6 bits, i.e. under 1 byte per channel per sample. Missing
samples (NaN) are flagged in a per-channel dropout bitmap; a channel that is entirely missing is
left out via the channel mask. Byte layout: docs/PROTOCOL.md, "Data datagram".
"""

from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np
import numpy.typing as npt

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
    unzigzag,
    zigzag,
)
from cranetwin.samples import SampleBlock

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U64 = npt.NDArray[np.uint64]

DATA_FIXED = struct.Struct(">QqIHII")  # seq, t0_ns, period_ns, n, layout_id, channel mask
"""Fixed fields after the header (30 bytes); the lag varint follows them."""
MAX_SAMPLES = 4096
FLAG_DROPOUTS = 0x01
_K_LIMIT = 2.0**53  # |k| beyond which float64 ↔ int64 is no longer exact


def quantise(values: F64, resolution: tuple[float, ...]) -> tuple[I64, npt.NDArray[np.bool_]]:
    """Integers on the sensor grid, k = round(v / resolution), and the missing mask.

    Args:
        values: Shape (n, c) [channel units]; NaN = missing.
        resolution: Quantisation step per channel, length c [channel units].

    Returns:
        ``(k, missing)``, both shape (n, c); k is 0 where missing.

    Raises:
        ValueError: shapes disagree, or a value is infinite or beyond ±2**53 quanta.
    """
    v = np.asarray(values, dtype=np.float64)
    res = np.asarray(resolution, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != res.shape[0]:
        raise ValueError(f"values shape {v.shape} does not match {res.shape[0]} channels")
    missing = np.isnan(v)
    q = np.round(np.where(missing, 0.0, v) / res)
    if not np.all(np.abs(q) < _K_LIMIT):
        raise ValueError("values are infinite or beyond ±2**53 quanta of their resolution")
    return q.astype(np.int64), missing


def on_grid(values: F64, resolution: tuple[float, ...]) -> F64:
    """``values`` snapped to the sensor grid exactly as a decoder returns them (k · resolution)."""
    k, missing = quantise(values, resolution)
    out = k.astype(np.float64) * np.asarray(resolution, dtype=np.float64)
    out[missing] = np.nan
    return out


def _bit_width(span: int) -> int:
    return int(span).bit_length()


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
    k = k[:, cols]
    miss = missing[:, cols]
    gappy: npt.NDArray[np.bool_] = np.asarray(miss.any(axis=0))
    if gappy.any():  # carry the previous value through gaps (deltas 0), the first valid backwards
        rows = np.arange(n)[:, None]
        idx = np.where(miss, 0, rows)
        np.maximum.accumulate(idx, axis=0, out=idx)
        idx = np.maximum(idx, np.argmax(~miss, axis=0)[None, :])
        k = np.take_along_axis(k, idx, axis=0)
    if n > 1:
        d = np.diff(k, axis=0)
        dmin = d.min(axis=0)
        span = d.max(axis=0) - dmin
        widths = [int(x).bit_length() for x in span]
    else:
        dmin = np.zeros(len(cols), dtype=np.int64)
        widths = [0] * len(cols)
    firsts = k[0]
    packed_bitmaps = np.packbits(miss, axis=0) if gappy.any() else None
    for i in range(len(cols)):
        out.append(FLAG_DROPOUTS if gappy[i] else 0)
        put_varint(out, zigzag(int(firsts[i])))
        if n > 1:
            put_varint(out, zigzag(int(dmin[i])))
            out.append(widths[i])
        if packed_bitmaps is not None and gappy[i]:
            out += packed_bitmaps[:, i].tobytes()
    if n > 1 and any(widths):
        w_arr = np.asarray(widths, dtype=np.int64)
        sel = w_arr > 0
        offs = (d[:, sel] - dmin[sel]).astype(np.uint64).T.ravel()  # channel-major rows
        out += np.packbits(_row_bits(offs, n - 1, tuple(int(w) for w in w_arr[sel]))).tobytes()
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
        firsts.append(unzigzag(z))
        if n > 1:
            z, pos = get_varint(body, pos, end)
            dmins.append(unzigzag(z))
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
    if not ncol:
        return SampleBlock(machine_id=key.machine_id, seq=seq, t0_ns=t0_ns,
                           period_ns=period_ns, channels=layout.names,
                           resolution=layout.resolutions, values=np.full((n, c), np.nan),
                           epoch=head.epoch)
    k = np.empty((n, ncol), dtype=np.int64)
    k[0] = [_wrap(f) for f in firsts]
    if n > 1:
        nz = tuple(w for w in widths if w)
        offs = np.zeros((ncol, n - 1), dtype=np.uint64)
        if nz:
            starts, shift, _ = _bit_plan(n - 1, nz)
            bits = np.unpackbits(np.frombuffer(body[pos:end], dtype=np.uint8), count=nbits)
            vals_nz = np.add.reduceat(bits.astype(np.uint64) << shift, starts)
            offs[[i for i, w in enumerate(widths) if w]] = vals_nz.reshape(-1, n - 1)
        dm = np.asarray([_wrap(x) & (2**64 - 1) for x in dmins], dtype=np.uint64)
        with np.errstate(over="ignore"):
            d = (offs.T + dm).view(np.int64)
            k[1:] = k[0] + np.cumsum(d, axis=0)
    res = np.asarray(layout.resolutions, dtype=np.float64)
    vals = k.astype(np.float64) * (res if ncol == c else res[cols])
    gi = [i for i, g in enumerate(gaps) if g is not None]
    if gi:
        bm = np.unpackbits(np.frombuffer(b"".join(g for g in gaps if g is not None),
                                         dtype=np.uint8)).reshape(len(gi), -1)[:, :n]
        sub = vals[:, gi]
        sub[bm.T.astype(bool)] = np.nan
        vals[:, gi] = sub
    if ncol == c:
        values = vals
    else:
        values = np.full((n, c), np.nan)
        values[:, cols] = vals
    return SampleBlock(machine_id=key.machine_id, seq=seq, t0_ns=t0_ns, period_ns=period_ns,
                       channels=layout.names, resolution=layout.resolutions, values=values,
                       epoch=head.epoch)


_PLAN_CACHE_BITS = 16384  # plans of larger (rare, > 2 KB) bit streams are not cached


def _bit_plan(n1: int, widths: tuple[int, ...]) -> tuple[I64, U64, I64]:
    """:func:`_make_bit_plan`, cached for datagram-sized streams (memory bound ≈ 4096 × 260 KB
    worst case, typically a few MB)."""
    if n1 * sum(widths) <= _PLAN_CACHE_BITS:
        return _cached_bit_plan(n1, widths)
    return _make_bit_plan(n1, widths)


def _make_bit_plan(n1: int, widths: tuple[int, ...]) -> tuple[I64, U64, I64]:
    """Where the bits of rows of ``widths`` (each repeated n1 times) sit in a packed stream.

    Returns:
        ``(starts, shift, row)``: first bit of each row, shape (R,); left shift of each bit
        within its row value, shape (nbits,); row of each bit, shape (nbits,).
    """
    w_rows = np.repeat(np.asarray(widths, dtype=np.int64), n1)
    starts = np.cumsum(w_rows) - w_rows
    row = np.repeat(np.arange(w_rows.size), w_rows)
    shift = (w_rows[row] - 1 - (np.arange(row.size) - starts[row])).astype(np.uint64)
    for arr in (starts, shift, row):
        arr.flags.writeable = False
    return starts, shift, row


_cached_bit_plan = lru_cache(maxsize=4096)(_make_bit_plan)


def _row_bits(vals: U64, n1: int, widths: tuple[int, ...]) -> npt.NDArray[np.uint8]:
    """Bits of each value (rows of ``widths``, n1 values each), most significant first."""
    _, shift, row = _bit_plan(n1, widths)
    return ((vals[row] >> shift) & np.uint64(1)).astype(np.uint8)


def _wrap(v: int) -> int:
    """``v`` reduced to a signed 64-bit integer (two's complement)."""
    v &= 2**64 - 1
    return v - 2**64 if v >= 2**63 else v


def data_lag(datagram: bytes | memoryview) -> int:
    """``seq − oldest_unacked`` of a data datagram (not authenticated here)."""
    head = peek_header(datagram)
    lag, _ = get_varint(datagram, head.size + DATA_FIXED.size, len(datagram) - TAG_BYTES)
    return lag
