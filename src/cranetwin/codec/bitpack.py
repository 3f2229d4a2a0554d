"""Bit packing of unsigned integers: frame-of-reference rows (wire) and byte planes (storage).

Rows (:func:`pack_rows`): R rows of n1 values, row r of fixed width w_r bits, written row after
row, each value most significant bit first, the stream padded with zero bits to a whole byte.
With values ``d − min(d)`` of a channel's deltas and ``w = bit_length(max(d) − min(d))`` this is
frame-of-reference packing: smooth sensor signals need 3–6 bits per sample.

Byte planes (:func:`byte_planes`, :func:`block_byte_planes`): values of w bytes (1, 2, 4 or 8)
stored as all low bytes, then all next bytes, …, which a general-purpose compressor (zlib) then
squeezes well.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numpy.typing as npt

I64 = npt.NDArray[np.int64]
U64 = npt.NDArray[np.uint64]
U8 = npt.NDArray[np.uint8]

_PLAN_CACHE_BITS = 16384  # plans of larger (rare, > 2 KB) bit streams are not cached
_PLANE_TYPES = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def row_widths(span: I64 | U64) -> list[int]:
    """Bit width of each row: ``bit_length(span)`` (0 for a span of 0).

    Args:
        span: ``max − min`` of each row's values, shape (R,), non-negative (as unsigned).
    """
    return [int(x).bit_length() for x in np.asarray(span).astype(np.uint64)]


def _make_bit_plan(n1: int, widths: tuple[int, ...]) -> tuple[I64, U64, I64]:
    """Where the bits of rows of ``widths`` (each repeated n1 times) sit in a packed stream.

    Returns:
        ``(starts, shift, row)``: first bit of each value, shape (R·n1,); left shift of each bit
        within its value, shape (nbits,); value index of each bit, shape (nbits,).
    """
    w_rows = np.repeat(np.asarray(widths, dtype=np.int64), n1)
    starts = np.cumsum(w_rows) - w_rows
    row = np.repeat(np.arange(w_rows.size), w_rows)
    shift = (w_rows[row] - 1 - (np.arange(row.size) - starts[row])).astype(np.uint64)
    for arr in (starts, shift, row):
        arr.flags.writeable = False
    return starts, shift, row


_cached_bit_plan = lru_cache(maxsize=4096)(_make_bit_plan)


def _bit_plan(n1: int, widths: tuple[int, ...]) -> tuple[I64, U64, I64]:
    """:func:`_make_bit_plan`, cached for datagram-sized streams (memory bound ≈ 4096 × 260 KB
    worst case, typically a few MB)."""
    if n1 * sum(widths) <= _PLAN_CACHE_BITS:
        return _cached_bit_plan(n1, widths)
    return _make_bit_plan(n1, widths)


def pack_rows(vals: U64, widths: tuple[int, ...]) -> bytes:
    """Pack rows of unsigned values at fixed widths (module docstring).

    Args:
        vals: Shape (R, n1); row r's values must be below 2**widths[r].
        widths: Bit width of each row, 1..64, length R.

    Returns:
        ceil(n1 · Σ widths / 8) bytes.
    """
    n1 = vals.shape[1]
    if not widths or n1 == 0:
        return b""
    _, shift, row = _bit_plan(n1, widths)
    flat = np.ascontiguousarray(vals, dtype=np.uint64).ravel()
    bits = ((flat[row] >> shift) & np.uint64(1)).astype(np.uint8)
    return np.packbits(bits).tobytes()


def unpack_rows(buf: bytes | memoryview, n1: int, widths: tuple[int, ...]) -> U64:
    """Inverse of :func:`pack_rows`.

    Args:
        buf: At least ceil(n1 · Σ widths / 8) bytes (the caller checks length and padding).
        n1: Values per row.
        widths: Bit width of each row, 1..64.

    Returns:
        Shape (len(widths), n1).
    """
    if not widths or n1 == 0:
        return np.zeros((len(widths), n1), dtype=np.uint64)
    starts, shift, _ = _bit_plan(n1, widths)
    nbits = n1 * sum(widths)
    bits = np.unpackbits(np.frombuffer(buf, dtype=np.uint8), count=nbits)
    return np.add.reduceat(bits.astype(np.uint64) << shift, starts).reshape(len(widths), n1)


def byte_width(top: int) -> int:
    """Smallest of 1, 2, 4, 8 bytes that holds the unsigned value ``top``."""
    return next(w for w in (1, 2, 4, 8) if top < 2 ** (8 * w))


def byte_planes(z: U64, width: int) -> U8:
    """Values as byte planes, each row separately.

    Args:
        z: Shape (..., m); values below 2**(8·width).
        width: 1, 2, 4 or 8 [bytes].

    Returns:
        Shape (..., width · m): row's low bytes (little-endian byte 0) of all m values, then
        byte 1 of all values, and so on.
    """
    lead, m = z.shape[:-1], z.shape[-1]
    b = z.astype(np.dtype(_PLANE_TYPES[width]).newbyteorder("<"))
    planes = b.view(np.uint8).reshape(*lead, m, width)
    return np.ascontiguousarray(np.swapaxes(planes, -1, -2)).reshape(*lead, width * m)


def block_byte_planes(z: U64, width: int) -> U8:
    """:func:`byte_planes` of many blocks held channel-major side by side, in one pass.

    Args:
        z: Shape (c, B, n): block b's values are ``z[:, b, :]``, in (channel, sample) order.
        width: 1, 2, 4 or 8 [bytes]; every value below 2**(8·width).

    Returns:
        Shape (B, width · c · n): row b is ``byte_planes(z[:, b, :].reshape(-1), width)``.
    """
    c, nb, n = z.shape
    b = z.astype(np.dtype(_PLANE_TYPES[width]).newbyteorder("<"), copy=False)
    planes = b.view(np.uint8).reshape(c, nb, n, width).transpose(1, 3, 0, 2)
    return np.ascontiguousarray(planes).reshape(nb, width * c * n)


def from_byte_planes(buf: bytes | memoryview, width: int, count: int) -> U64:
    """Inverse of :func:`byte_planes` for one row: ``count`` values of ``width`` bytes from the
    first ``width · count`` bytes of ``buf``; shape (count,)."""
    planes = np.frombuffer(buf, dtype=np.uint8, count=width * count).reshape(width, count)
    le = np.dtype(_PLANE_TYPES[width]).newbyteorder("<")
    return np.ascontiguousarray(planes.T).view(le).reshape(count).astype(np.uint64)
