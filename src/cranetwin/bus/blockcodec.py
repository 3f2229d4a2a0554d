"""A :class:`~cranetwin.samples.SampleBlock` as one bus message: a small binary header, the
channel layout, and the samples as storage's own blob (:mod:`cranetwin.storage.codec`: the
integer steps the wire carried, delta/zigzag, byte planes, zlib). No float round trip and no
second quantisation: the storage writer stores exactly the steps the daemon decoded.

Layout of a message body (little endian)::

    offset  size  field
    0       2     magic b"CB"
    2       1     format version (1)
    3       1     reserved (0)
    4       8     epoch (uint64)
    12      8     seq (uint64)
    20      8     t0_ns (int64) [ns since the Unix epoch, machine clock]
    28      8     period_ns (int64) [ns]
    36      2     m, bytes of the machine id (uint16), then the id in UTF-8
    ..      2     j, bytes of the layout (uint16), then JSON [[channel, …], [resolution, …]]
                  (storage's ``channels`` and ``resolution`` columns, floats in shortest repr)
    ..      ...   storage blob of the steps, shape (n, c), with the NaN mask
"""

from __future__ import annotations

import functools
import json
import struct
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from cranetwin import codec as intcodec
from cranetwin.errors import StorageError
from cranetwin.samples import SampleBlock
from cranetwin.storage import codec as blob

MAGIC = b"CB"
VERSION = 1
_HEAD = struct.Struct("<2sBxQQqq")
_LEN = struct.Struct("<H")
_STEP_LIMIT = 2**52


class BlockCodecError(StorageError):
    """A bus message is not a block of this format (truncated, corrupt, unknown version)."""


@functools.lru_cache(maxsize=1024)
def _layout_json(channels: tuple[str, ...], resolution: tuple[float, ...]) -> bytes:
    return json.dumps([list(channels), [float(r) for r in resolution]],
                      separators=(",", ":")).encode()


@functools.lru_cache(maxsize=1024)
def _layout_of(raw: bytes) -> tuple[tuple[str, ...], tuple[float, ...]]:
    ch, res = json.loads(raw)
    return tuple(str(c) for c in ch), tuple(float(r) for r in res)


def steps_of(b: SampleBlock) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """The block's integer steps and NaN mask, shape (n, c) each.

    Raises:
        StorageError: a value is infinite or more than 2**52 steps from zero (storage would
            refuse the block as ``unstorable``).
    """
    mask = np.isnan(b.values)
    if b.steps is not None and b.steps.shape == b.values.shape:
        k = np.asarray(b.steps, dtype=np.int64)
        if k.size and not (np.all(k > -_STEP_LIMIT) and np.all(k < _STEP_LIMIT)):
            raise StorageError("steps more than 2**52 from zero")
        return k, mask
    k, mask = blob.quantise(b.values, b.resolution)
    return k, mask


def encode_blocks(blocks: Sequence[SampleBlock], level: int = 0) -> list[bytes | str]:
    """Message bodies of ``blocks`` (vectorised over blocks of equal shape).

    Args:
        level: zlib level of the storage blob (0: stored, no compression: the delta/zigzag
            byte planes alone; 1 makes messages about 2.6× smaller for about 50 µs more CPU
            per 100-sample block, see docs/BUS.md).

    Blocks must have passed :func:`cranetwin.storage.blocks.check_block`.

    Returns:
        Per block, its body, or why its values cannot be stored (one line).
    """
    out: list[bytes | str] = [""] * len(blocks)
    groups: dict[tuple[int, ...], list[tuple[int, npt.NDArray[np.int64],
                                              npt.NDArray[np.bool_]]]] = {}
    for i, b in enumerate(blocks):
        try:
            k, mask = steps_of(b)
        except StorageError as exc:
            out[i] = f"values cannot be stored: {exc}"
            continue
        groups.setdefault(k.shape, []).append((i, k, mask))
    for items in groups.values():
        blobs = blob.encode_many(np.stack([k for _, k, _ in items]),
                                 np.stack([m for _, _, m in items]), level)
        for (i, _, _), data in zip(items, blobs, strict=True):
            b = blocks[i]
            mid = b.machine_id.encode()
            lay = _layout_json(tuple(b.channels), tuple(b.resolution))
            out[i] = b"".join((_HEAD.pack(MAGIC, VERSION, int(b.epoch), int(b.seq),
                                          int(b.t0_ns), int(b.period_ns)),
                               _LEN.pack(len(mid)), mid, _LEN.pack(len(lay)), lay, data))
    return out


def _parse(body: bytes) -> tuple[str, int, int, int, int, tuple[str, ...], tuple[float, ...],
                                 int]:
    """Header fields of a message body and the offset of its storage blob."""
    try:
        magic, version, epoch, seq, t0, period = _HEAD.unpack_from(body)
        if magic != MAGIC or version != VERSION:
            raise BlockCodecError(f"not a cranetwin block message (magic {magic!r}, version "
                                  f"{version})")
        pos = _HEAD.size
        (m,) = _LEN.unpack_from(body, pos)
        machine_id = body[pos + 2:pos + 2 + m].decode()
        pos += 2 + m
        (j,) = _LEN.unpack_from(body, pos)
        channels, resolution = _layout_of(bytes(body[pos + 2:pos + 2 + j]))
    except BlockCodecError:
        raise
    except (struct.error, ValueError, TypeError) as exc:
        raise BlockCodecError(f"corrupt block message: {exc}") from exc
    return machine_id, int(epoch), int(seq), int(t0), int(period), channels, resolution, \
        pos + 2 + j


def _block(head: tuple[str, int, int, int, int, tuple[str, ...], tuple[float, ...], int],
           k: npt.NDArray[np.int64], mask: npt.NDArray[np.bool_]) -> SampleBlock:
    machine_id, epoch, seq, t0, period, channels, resolution, _ = head
    if k.shape[1] != len(channels):
        raise BlockCodecError(f"block message has {k.shape[1]} columns for {len(channels)} "
                              "channels")
    values = intcodec.dequantise(k, mask, resolution)
    return SampleBlock(machine_id, seq, t0, period, channels, resolution, values, epoch=epoch,
                       steps=k)


def decode_block(body: bytes) -> SampleBlock:
    """The block of a message body (see the module docstring).

    Raises:
        BlockCodecError: Not a block message of a known version, or corrupt.
    """
    head = _parse(body)
    try:
        k, mask = blob.decode_ints(bytes(body[head[-1]:]))
    except StorageError as exc:
        raise BlockCodecError(f"corrupt block message: {exc}") from exc
    return _block(head, k, mask)


def decode_blocks(bodies: Sequence[bytes]) -> list[SampleBlock | BlockCodecError]:
    """:func:`decode_block` of many bodies, the samples decoded vectorised over blocks of
    equal shape; a body that cannot be decoded gives its error in its place."""
    out: list[SampleBlock | BlockCodecError] = []
    heads: list[tuple[int, tuple[str, int, int, int, int, tuple[str, ...], tuple[float, ...],
                                 int]]] = []
    for i, body in enumerate(bodies):
        try:
            heads.append((i, _parse(body)))
            out.append(BlockCodecError("undecided"))
        except BlockCodecError as exc:
            out.append(exc)
    try:
        ints = blob.decode_ints_many([bytes(bodies[i][h[-1]:]) for i, h in heads])
    except StorageError:  # one corrupt blob: each on its own
        for i, _ in heads:
            try:
                out[i] = decode_block(bodies[i])
            except BlockCodecError as exc:
                out[i] = exc
        return out
    res_cache: dict[tuple[float, ...], npt.NDArray[np.float64]] = {}
    for (i, head), (k, mask) in zip(heads, ints, strict=True):
        machine_id, epoch, seq, t0, period, channels, resolution, _ = head
        if k.shape[1] != len(channels):
            out[i] = BlockCodecError(f"block message has {k.shape[1]} columns for "
                                     f"{len(channels)} channels")
            continue
        res = res_cache.get(resolution)
        if res is None:
            res = res_cache[resolution] = np.asarray(resolution, dtype=np.float64)
        values = intcodec.dequantise(k, mask if mask.any() else None, res)
        out[i] = SampleBlock(machine_id, seq, t0, period, channels, resolution, values,
                             epoch=epoch, steps=k)
    return out
