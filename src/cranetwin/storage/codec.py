"""Compression of sample arrays for the ``sample_blocks`` table: the blob around
:mod:`cranetwin.codec`'s integer transforms.

Values are quantised at the channel resolution to integers (lossless for values that are
multiples of the resolution, as sensors send them), differenced along time per channel,
zigzag-mapped to unsigned integers of the smallest width that holds them (1, 2, 4 or 8 bytes),
byte-shuffled (all low bytes, then the next byte plane, ...) and deflated with zlib. Missing
samples (NaN) are kept as a packed bit mask. Storage writes its blocks with zlib's run-length
strategy (:data:`BLOCK_STRATEGY`): the planes are runs of zeros and near-random low bytes, which
back-references barely shorten (the default strategy's search took half of an import's CPU);
any deflate stream inflates alike, so every blob, whatever strategy wrote it, decodes the same.
Layout of the blob::

    offset  size  field
    0       1     format version (1)
    1       1     integer width w in bytes (1, 2, 4, 8)
    2       1     flags: bit 0 = NaN mask present
    3       1     reserved (0)
    4       4     n, samples (uint32, little endian)
    8       4     c, channels (uint32, little endian)
    12      ...   zlib( shuffled zigzag deltas, channel-major: c*n*w bytes
                        [+ packbits(mask, channel-major): ceil(c*n/8) bytes] )
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from cranetwin import codec as intcodec
from cranetwin.errors import StorageError

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

VERSION = 1
BLOCK_STRATEGY = zlib.Z_RLE
"""zlib strategy of the blocks storage writes (:func:`cranetwin.storage.blocks.block_rows`):
on the bench's 1 h recording 2× faster than the default and 7 % smaller, on a simulated one
1.7× faster and 8 % smaller."""
_HEAD = struct.Struct("<BBBxII")
_LIMIT = 2.0**52  # |quantised value| beyond which float64 → int64 is no longer exact


class CodecError(StorageError):
    """A stored block could not be encoded or decoded."""


def quantise(values: F64, resolution: Sequence[float]) -> tuple[I64, npt.NDArray[np.bool_]]:
    """Integers k with values ≈ k · resolution, and the NaN mask
    (:func:`cranetwin.codec.quantise` within storage's ±2**52 steps).

    Returns:
        ``(k, mask)``, both shape (n, c); k is 0 where mask (NaN) is set.

    Raises:
        CodecError: Shapes disagree, a resolution is not positive, or a value is infinite or too
            large to quantise exactly.
    """
    try:
        return intcodec.quantise(values, resolution, limit=_LIMIT)
    except intcodec.QuantiseError as exc:
        raise CodecError(str(exc)) from exc


def encode(values: F64, resolution: Sequence[float], level: int = 6) -> bytes:
    """Compress sample values (quantise, delta, zigzag, byte-shuffle, zlib).

    Args:
        values: Shape (n, c) [channel units], multiples of ``resolution``; NaN = missing.
        resolution: Quantisation step per channel, length c.
        level: zlib level (1 fastest … 9 smallest).

    Returns:
        The blob described in the module docstring.
    """
    k, mask = quantise(values, resolution)
    return encode_ints(k, mask, level)


def encode_ints(k: I64, mask: npt.NDArray[np.bool_] | None = None, level: int = 6) -> bytes:
    """Compress an integer array, shape (n, c), with an optional missing-value mask (n, c)."""
    return encode_many(k[None], None if mask is None else mask[None], level)[0]


def decode_ints(blob: bytes) -> tuple[I64, npt.NDArray[np.bool_]]:
    """Inverse of the integer part of :func:`encode`.

    Returns:
        ``(k, mask)``, shape (n, c): quantised values and NaN mask.

    Raises:
        CodecError: The blob is truncated, corrupt or of an unknown version.
    """
    if len(blob) < _HEAD.size:
        raise CodecError(f"block blob of {len(blob)} bytes is shorter than its header")
    version, width, flags, n, c = _HEAD.unpack_from(blob)
    if version != VERSION or width not in (1, 2, 4, 8):
        raise CodecError(f"unknown block format version {version} / width {width}")
    try:
        body = zlib.decompress(blob[_HEAD.size:])
    except zlib.error as exc:
        raise CodecError(f"corrupt block blob: {exc}") from exc
    nplane = n * c * width
    nmask = (n * c + 7) // 8 if flags & 1 else 0
    if len(body) != nplane + nmask:
        raise CodecError(f"block body has {len(body)} bytes, expected {nplane + nmask}")
    z = intcodec.from_byte_planes(body, width, n * c).reshape(c, n)
    k = intcodec.undelta(intcodec.unzigzag_array(z), axis=1).T
    if nmask:
        bits = np.frombuffer(body, dtype=np.uint8, offset=nplane)
        mask = np.unpackbits(bits, count=n * c).astype(bool).reshape(c, n).T
    else:
        mask = np.zeros((n, c), dtype=bool)
    return np.ascontiguousarray(k), mask


def decode_ints_many(blobs: Sequence[bytes]) -> list[tuple[I64, npt.NDArray[np.bool_]]]:
    """:func:`decode_ints` of many blobs, vectorised over blobs of equal shape and width (the
    inverse of :func:`encode_many`; a stream of small blocks decodes at a fraction of the cost
    of one call each). The arrays returned may be views of a shared buffer, and masks of
    blocks without missing samples one shared read-only array: copy before writing.

    Raises:
        CodecError: A blob is truncated, corrupt or of an unknown version (nothing decoded).
    """
    groups: dict[tuple[int, int, int], list[tuple[int, bytes, int]]] = {}
    for i, blob in enumerate(blobs):
        if len(blob) < _HEAD.size:
            raise CodecError(f"block blob of {len(blob)} bytes is shorter than its header")
        version, width, flags, n, c = _HEAD.unpack_from(blob)
        if version != VERSION or width not in (1, 2, 4, 8) or flags & ~1:
            raise CodecError(f"unknown block format version {version} / width {width}")
        try:
            body = zlib.decompress(blob[_HEAD.size:])
        except zlib.error as exc:
            raise CodecError(f"corrupt block blob: {exc}") from exc
        nmask = (n * c + 7) // 8 if flags & 1 else 0
        if len(body) != n * c * width + nmask:
            raise CodecError(f"block body has {len(body)} bytes, expected {n * c * width + nmask}")
        groups.setdefault((n, c, width), []).append((i, body, nmask))
    out: list[tuple[I64, npt.NDArray[np.bool_]]] = [None] * len(blobs)  # type: ignore[list-item]
    for (n, c, width), items in groups.items():
        nplane = n * c * width
        planes = np.stack([np.frombuffer(body, dtype=np.uint8, count=nplane)
                           for _, body, _ in items]).reshape(len(items), width, n * c)
        le = np.dtype(f"<u{width}")
        z = np.ascontiguousarray(planes.transpose(0, 2, 1)).view(le).reshape(
            len(items), c, n).astype(np.uint64)
        k = np.ascontiguousarray(  # (B, n, c); each k[j] a contiguous view
            np.cumsum(intcodec.unzigzag_array(z), axis=2).transpose(0, 2, 1))
        none = np.zeros((n, c), dtype=bool)
        none.flags.writeable = False  # shared by the blocks without missing samples
        for j, (i, body, nmask) in enumerate(items):
            if nmask:
                bits = np.frombuffer(body, dtype=np.uint8, offset=nplane)
                mask = np.unpackbits(bits, count=n * c).astype(bool).reshape(c, n).T
            else:
                mask = none
            out[i] = (k[j], mask)
    return out


def decode(blob: bytes, resolution: Sequence[float]) -> F64:
    """Decompress a blob back to values, shape (n, c) [channel units], NaN where missing."""
    k, mask = decode_ints(blob)
    if len(resolution) != k.shape[1]:
        raise CodecError(f"blob has {k.shape[1]} channels, {len(resolution)} resolutions given")
    return intcodec.dequantise(k, mask, resolution)


def _deflate(body: bytes | memoryview, level: int, strategy: int) -> bytes:
    if strategy == zlib.Z_DEFAULT_STRATEGY:
        return zlib.compress(body, level)
    z = zlib.compressobj(level, zlib.DEFLATED, 15, 8, strategy)
    return z.compress(body) + z.flush()


def encode_many(k: I64, mask: npt.NDArray[np.bool_] | None, level: int = 1,
                strategy: int = zlib.Z_DEFAULT_STRATEGY) -> list[bytes]:
    """Blobs of B equally shaped integer arrays at once (vectorised over blocks).

    One pass per stage over all blocks, each writing one array: channel-major deltas, zigzag in
    place, the byte planes of the blocks of each width, then zlib per block. Fastest when ``k``
    is a (B, n, c) view of a contiguous channel-major array of shape (c, B, n) (as
    :func:`cranetwin.storage.blocks.block_rows` passes it): no transposing copy then.

    Args:
        k: Integer steps, shape (B, n, c); mask: missing samples, shape (B, n, c), or None when
            no sample is missing.
        level: zlib level (0 stored … 1 fastest … 9 smallest).
        strategy: zlib strategy (storage's blocks: :data:`BLOCK_STRATEGY`).

    Returns:
        B blobs; ``decode_ints(blobs[i])`` gives back ``(k[i], mask[i])``.
    """
    nb, n, c = k.shape
    kt = np.ascontiguousarray(k.transpose(2, 0, 1))  # (c, B, n): time last, per channel
    z = intcodec.zigzag_array(intcodec.deltas(kt, axis=2, first=True), in_place=True)
    top = z.max(axis=(0, 2)) if z.size else np.zeros(nb, dtype=np.uint64)
    has_mask = (np.zeros(nb, dtype=bool) if mask is None
                else np.asarray(mask.any(axis=(1, 2))))
    width_of = [intcodec.byte_width(int(t)) for t in top.tolist()]
    widths = np.array(width_of, dtype=np.int64)
    out: list[bytes] = [b""] * nb
    # (not np.unique: it imports numpy.ma on first use, ≈ 50 ms of the first batch's CPU)
    for width in sorted(set(width_of)):
        sel = widths == width
        idx = np.flatnonzero(sel)
        zs = z if sel.all() else z[:, idx, :]
        planes = intcodec.block_byte_planes(zs, width)  # (B', width · c · n) bytes
        for row, b in enumerate(idx.tolist()):
            head = _HEAD.pack(VERSION, width, int(has_mask[b]), n, c)
            if has_mask[b]:
                assert mask is not None
                body = planes[row].tobytes() + np.packbits(mask[b].T.reshape(-1)).tobytes()
                out[b] = head + _deflate(body, level, strategy)
            else:
                out[b] = head + _deflate(memoryview(planes[row]), level, strategy)
    return out


def encode_plain(k: I64) -> bytes:
    """Small integer arrays (summaries), shape (r, c): header + zlib of little-endian int64."""
    r, c = k.shape
    return _HEAD.pack(VERSION, 8, 0x80, r, c) + zlib.compress(k.astype("<i8").tobytes(), 1)


def decode_plain(blob: bytes) -> I64:
    """Inverse of :func:`encode_plain`.

    Raises:
        CodecError: Truncated or corrupt blob.
    """
    if len(blob) < _HEAD.size:
        raise CodecError(f"summary blob of {len(blob)} bytes is shorter than its header")
    version, _, flags, r, c = _HEAD.unpack_from(blob)
    try:
        body = zlib.decompress(blob[_HEAD.size:])
    except zlib.error as exc:
        raise CodecError(f"corrupt summary blob: {exc}") from exc
    if version != VERSION or flags != 0x80 or len(body) != 8 * r * c:
        raise CodecError("summary blob has an unknown format or a wrong length")
    return np.frombuffer(body, dtype="<i8").reshape(r, c).astype(np.int64)
