"""Zigzag mapping and per-channel deltas of integer steps.

Zigzag maps signed to unsigned 64-bit integers so that small magnitudes get small codes:
``z = (v << 1) ^ (v >> 63)``, i.e. 0, −1, 1, −2, … → 0, 1, 2, 3, … (the same as Protocol
Buffers). Arithmetic on deltas wraps modulo 2**64 (numpy integer arrays wrap silently), so any
int64 series round-trips.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

I64 = npt.NDArray[np.int64]
U64 = npt.NDArray[np.uint64]
Mask = npt.NDArray[np.bool_]

_U64_MAX = 2**64 - 1


def zigzag(v: int) -> int:
    """Map a signed 64-bit integer to unsigned: 0, −1, 1, −2 → 0, 1, 2, 3."""
    return ((v << 1) ^ (v >> 63)) & _U64_MAX


def unzigzag(z: int) -> int:
    """Inverse of :func:`zigzag`."""
    return (z >> 1) ^ -(z & 1)


def zigzag_array(d: I64, *, in_place: bool = False) -> U64:
    """:func:`zigzag` elementwise on an int64 array.

    Args:
        d: Any shape.
        in_place: Overwrite ``d`` (which must be a writeable int64 array) and return it viewed
            as uint64: no new array of ``d``'s size.
    """
    sign = d >> 63  # 0 or -1 (all bits set)
    z = d if in_place else d.copy()
    z <<= 1
    z ^= sign
    return z.view(np.uint64)


def unzigzag_array(z: U64) -> I64:
    """:func:`unzigzag` elementwise on a uint64 array."""
    return (z >> np.uint64(1)).view(np.int64) ^ -(z & np.uint64(1)).view(np.int64)


def deltas(k: I64, axis: int = 0, *, first: bool = False) -> I64:
    """Differences along ``axis`` (wrapping modulo 2**64).

    Args:
        k: Integer steps.
        axis: The time axis.
        first: Keep the first element as the difference from 0 (same length as ``k``);
            otherwise the result is one shorter along ``axis``.
    """
    if first:  # d[0] = k[0], then the differences: one new array, no padded copy of k
        k = np.asarray(k, dtype=np.int64)
        out = np.empty(k.shape, dtype=np.int64)
        head = [slice(None)] * k.ndim
        tail, prev = list(head), list(head)
        head[axis], tail[axis], prev[axis] = slice(0, 1), slice(1, None), slice(None, -1)
        out[tuple(head)] = k[tuple(head)]
        np.subtract(k[tuple(tail)], k[tuple(prev)], out=out[tuple(tail)])
        return out
    return np.diff(k, axis=axis)


def undelta(d: I64, axis: int = 0, start: I64 | None = None) -> I64:
    """Inverse of :func:`deltas`: cumulative sums along ``axis`` (wrapping), plus ``start``.

    Args:
        d: Differences.
        axis: The time axis.
        start: Value before the first difference (broadcast against one slice of ``d``), or None
            for 0 (the inverse of ``deltas(k, first=True)``).
    """
    out = np.cumsum(d, axis=axis)
    if start is not None:
        out += start if axis == 0 else np.expand_dims(start, axis)
    return out


def carry_through_gaps(k: I64, missing: Mask) -> I64:
    """``k`` with each missing sample replaced by the previous present one of its channel (the
    first present one for leading gaps), so gaps add no deltas; shape (n, c), time along axis 0.
    Channels missing throughout keep their values.
    """
    if not missing.any():
        return k
    n = k.shape[0]
    idx = np.where(missing, 0, np.arange(n)[:, None])
    np.maximum.accumulate(idx, axis=0, out=idx)
    idx = np.maximum(idx, np.argmax(~missing, axis=0)[None, :])
    return np.take_along_axis(k, idx, axis=0)
