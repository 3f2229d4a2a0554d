"""Storage's block rows against a plain per-block oracle: the vectorised encoding (channel-major
passes over groups of blocks) stores exactly the bytes the layout in
``cranetwin.storage.codec``'s docstring describes (deflated with the run-length strategy; with
the default strategy, byte for byte what was written before it), they decode to the block's
steps and mask, and the per-second summaries are exactly what a loop over seconds and channels
computes; any batch, cut into any groups, gives every block the row it gets alone (streaming =
batch)."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cranetwin.samples import SampleBlock
from cranetwin.storage import blocks, codec

pytestmark = pytest.mark.timeout(120)

SEC = 10**9


def _oracle_blob(k: np.ndarray, mask: np.ndarray) -> tuple[bytes, bytes]:
    """Header and (uncompressed) body of the blob of the codec's docstring, built plane by
    plane with shifts (no views)."""
    n, c = k.shape
    kt = k.T.astype(np.int64)
    d = np.diff(kt, axis=1, prepend=np.zeros((c, 1), dtype=np.int64)).reshape(-1)
    z = ((d << 1) ^ (d >> 63)).view(np.uint64)
    top = int(z.max(initial=0))
    width = next(w for w in (1, 2, 4, 8) if top < 2 ** (8 * w))
    body = b"".join(((z >> np.uint64(8 * p)) & np.uint64(0xFF)).astype(np.uint8).tobytes()
                    for p in range(width))
    if mask.any():
        body += np.packbits(mask.T.reshape(-1)).tobytes()
    return struct.pack("<BBBxII", 1, width, int(mask.any()), n, c), body


def _oracle_summary(k: np.ndarray, mask: np.ndarray, t0: int, period: int) -> np.ndarray:
    """Count, min, max, sum per whole second and channel, by loops."""
    n, c = k.shape
    sec = (t0 + np.arange(n, dtype=np.int64) * period) // SEC
    m = int(sec[-1] - sec[0]) + 1
    out = np.zeros((4, m, c), dtype=np.int64)
    for i in range(m):
        for j in range(c):
            sel = (sec == sec[0] + i) & ~mask[:, j]
            if sel.any():
                v = k[sel, j]
                out[:, i, j] = sel.sum(), v.min(), v.max(), v.sum()
    return out.reshape(4 * m, c)


def _deflate_rle(body: bytes) -> bytes:
    z = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    return z.compress(body) + z.flush()


@st.composite
def _batches(draw: st.DrawFn) -> list[SampleBlock]:
    """Blocks of a few shapes: with the wire's steps or values only, with and without missing
    samples,
    periods from 10 ms to 1.7 s (blocks of one shape spanning different numbers of seconds),
    deltas that need 1 to 8 bytes, and now and then an unstorable (infinite) block."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    shapes = draw(st.lists(st.tuples(st.integers(1, 40), st.integers(1, 4)), min_size=1,
                           max_size=3))
    out = []
    for seq in range(draw(st.integers(1, 14))):
        n, c = shapes[seq % len(shapes)]
        res = tuple(float(r) for r in rng.choice([1e-4, 0.25, 1.0, 5000.0], size=c))
        scale = int(rng.choice([3, 300, 70_000, 2**40]))
        k = np.cumsum(rng.integers(-scale, scale + 1, size=(n, c)), axis=0)
        mask = rng.random((n, c)) < float(rng.choice([0.0, 0.0, 0.2, 1.0]))
        k[mask] = 0
        values = k * np.asarray(res)
        values[mask] = np.nan
        steps = k if rng.random() < 0.5 else None  # the wire's (values = steps · resolution)
        if steps is None and rng.random() < 0.1:
            values[rng.integers(n), rng.integers(c)] = np.inf
        period = int(rng.choice([10_000_000, 300_000_000, 1_700_000_000]))
        t0 = 1_767_225_600 * SEC + int(rng.integers(0, 5 * SEC))
        out.append(SampleBlock("m", seq, t0, period, tuple(f"ch{j}" for j in range(c)), res,
                               values, epoch=7, steps=steps))
    return out


@settings(max_examples=80, deadline=None)
@given(batch=_batches(), group=st.integers(1, 400))
def test_block_rows_store_the_oracles_bytes_in_any_grouping(batch: list[SampleBlock],
                                                            group: int) -> None:
    items = [(3, b) for b in batch]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(blocks, "GROUP_VALUES", group)  # groups of a few blocks, or one each
        rows = blocks.block_rows(items)
    alone = [blocks.block_rows([it])[0] for it in items]
    assert rows == alone
    for b, row in zip(batch, rows, strict=True):
        if np.isinf(b.values).any():
            assert isinstance(row, str) and "infinite" in row
            continue
        assert not isinstance(row, str)
        mask = np.isnan(b.values)
        k = b.steps if b.steps is not None else np.rint(
            np.where(mask, 0.0, b.values) / np.asarray(b.resolution)).astype(np.int64)
        summary, data = row[9], row[10]
        head, body = _oracle_blob(k, mask)
        assert data[:12] == head and zlib.decompress(data[12:]) == body
        assert data == head + _deflate_rle(body)  # storage's strategy, level 1
        # the encoder's default strategy: the bytes written before the run-length strategy
        assert codec.encode_many(k[None], mask[None])[0] == head + zlib.compress(body, 1)
        assert np.array_equal(codec.decode_plain(summary),
                              _oracle_summary(k, mask, b.t0_ns, b.period_ns))
        kk, mm = codec.decode_ints(data)
        assert np.array_equal(kk, k) and np.array_equal(mm, mask)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), nb=st.integers(1, 5), n=st.integers(1, 300),
       c=st.integers(1, 4))
def test_per_second_without_a_mask_equals_the_masked_form(seed: int, nb: int, n: int,
                                                          c: int) -> None:
    rng = np.random.default_rng(seed)
    k = rng.integers(-(2**62), 2**62, size=(nb, n, c))  # sums wrap modulo 2**64 alike
    t0 = rng.integers(0, 10 * SEC, size=nb)
    period = np.full(nb, int(rng.choice([1_000_000, 10_000_000, 400_000_000])))
    got = blocks.per_second(k, None, t0, period)
    masked = blocks.per_second(k, np.zeros(k.shape, dtype=bool), t0, period)
    for b in range(nb):
        assert np.array_equal(got[b], masked[b])
        assert np.array_equal(got[b], _oracle_summary(k[b], np.zeros((n, c), dtype=bool),
                                                      int(t0[b]), int(period[b])))
