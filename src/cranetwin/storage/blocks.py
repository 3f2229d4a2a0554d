"""Raw samples, stored as compressed blocks: one row per received datagram, not one per sample.

A row holds one :class:`~cranetwin.samples.SampleBlock` (``n`` regularly spaced samples of one
machine) as the run the wire carried: t0, period, channel layout and the integer steps
(``SampleBlock.steps`` when the block has them, as decoded from the datagram; otherwise ``values``
quantised once), compressed by :mod:`cranetwin.storage.codec`, plus its per-second summary
(count, min, max, sum of the steps per channel for every whole second the block touches), so that
1-s load history never decodes raw samples. Rows are unique on (machine, epoch, seq) (on
PostgreSQL, where the table is partitioned by t_start_ns, on (machine, epoch, seq, t_start_ns):
:mod:`cranetwin.storage.partitions`), and inserted with ``ON CONFLICT DO NOTHING`` on both
dialects, so writing a block twice (a retransmission, a replayed batch after a crash: the same
seq and the same t_start) stores it once. Range reads also bound t_start from below by the
longest block span, so PostgreSQL reads only the partitions that can hold a match.

What a row may hold (:func:`check_block`, :func:`block_rows`; anything else is refused before it
reaches the database): sample times 0 ≤ t0 ≤ t_end < :data:`T_LIMIT_NS` (2262-04-10, one day
below the signed 64-bit ns limit, so every second and minute bucket around a block and every
query bound next to it is representable), a span t_end − t0 of at most :data:`MAX_SPAN_NS`
(6 h; a datagram spans at most 4096 × (2**32 − 1) ns ≈ 4.9 h, and the per-second summary
grows with the span), period ≥ 1 ns, 1 ≤ n < 2**31, seq and epoch in [0, 2**63 − 1], 1..64
distinct channel names of at most 64 characters, finite resolutions > 0, and finite values
(NaN = missing) within 2**52 resolution steps of zero (for blocks with steps: |steps| < 2**52).
"""

from __future__ import annotations

import functools
import json
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import (
    BigInteger,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    Text,
    UniqueConstraint,
    select,
    text,
    tuple_,
)
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin import codec as intcodec
from cranetwin.samples import F64, SampleBlock
from cranetwin.storage import bulk, codec
from cranetwin.storage.base import Base

log = logging.getLogger(__name__)

I64 = npt.NDArray[np.int64]
SEC = 1_000_000_000
INT63 = 2**63 - 1
"""Largest signed 64-bit integer (BIGINT)."""
T_LIMIT_NS = 2**63 - 86_400 * SEC
"""Sample times must be below this [ns since the Unix epoch] (2262-04-10)."""
MAX_SPAN_NS = 6 * 3600 * SEC
"""Longest block, t_end − t0 [ns]."""
MAX_N = 2**31 - 1
MAX_CHANNELS = 64
MAX_CHANNEL_NAME = 64
_VALUE_LIMIT = 2.0**52
_STEP_LIMIT = 2**52


class BlockRow(Base):
    """A compressed run of samples of one machine (one datagram's worth).

    The mapping is SQLite's table; on PostgreSQL the table is partitioned by ``t_start_ns``
    with primary key (id, t_start_ns) and unique key (machine_pk, epoch, seq, t_start_ns)
    (migration ``0004p``). Queries use the same columns on both.
    """

    __tablename__ = "sample_blocks"
    __table_args__ = (
        UniqueConstraint("machine_pk", "epoch", "seq"),
        Index("ix_sample_blocks_machine_t_start", "machine_pk", "t_start_ns"),
        Index("ix_sample_blocks_machine_t_end", "machine_pk", "t_end_ns"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    epoch: Mapped[int] = mapped_column(BigInteger, server_default=text("0"))
    seq: Mapped[int] = mapped_column(BigInteger)
    t_start_ns: Mapped[int] = mapped_column(BigInteger)
    t_end_ns: Mapped[int] = mapped_column(BigInteger)
    period_ns: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int] = mapped_column(Integer)
    channels: Mapped[str] = mapped_column(Text)  # JSON list of names
    resolution: Mapped[str] = mapped_column(Text)  # JSON list of steps
    summary: Mapped[bytes] = mapped_column(LargeBinary)  # per-second aggregates, see module doc
    data: Mapped[bytes] = mapped_column(LargeBinary)


COLUMNS = ("machine_pk", "epoch", "seq", "t_start_ns", "t_end_ns", "period_ns", "n", "channels",
           "resolution", "summary", "data")


def per_second(k: I64, mask: npt.NDArray[np.bool_] | None, t0_ns: npt.NDArray[np.int64],
               period_ns: npt.NDArray[np.int64]) -> list[I64]:
    """Aggregates of quantised samples per whole second, for B equally shaped blocks.

    Each statistic is one ``reduceat`` over all blocks along time, channel-major (a segment is
    one second of one block); without missing samples the counts are the segment lengths and no
    masked copy of ``k`` is made. Fastest when ``k`` (and ``mask``) are (B, n, c) views of
    contiguous channel-major arrays of shape (c, B, n), as :func:`block_rows` passes them.

    Args:
        k: Quantised values, shape (B, n, c); mask: missing samples, shape (B, n, c), or None
            when no sample is missing.
        t0_ns: First sample time of each block, shape (B,) [ns].
        period_ns: Sample period of each block, shape (B,) [ns].

    Returns:
        Per block, shape (4·m, c) for the m seconds from floor(t0 / 1 s): rows [0, m) counts,
        [m, 2m) minima, [2m, 3m) maxima, [3m, 4m) sums of k (wrapping modulo 2**64); min = max
        = 0 where count is 0.
    """
    nb, n, c = k.shape
    sec = (t0_ns[:, None] + np.arange(n, dtype=np.int64) * period_ns[:, None]) // SEC
    idx = sec - sec[:, :1]
    change = np.ones((nb, n), dtype=bool)
    change[:, 1:] = idx[:, 1:] != idx[:, :-1]
    starts = np.flatnonzero(change.ravel())
    seg_b, seg_row = starts // n, idx.ravel()[starts]
    m_max = int(idx[:, -1].max()) + 1
    flat_k = np.ascontiguousarray(k.transpose(2, 0, 1)).reshape(c, nb * n)  # (c, B·n)
    out = np.zeros((nb, 4, m_max, c), dtype=np.int64)
    if mask is None or not mask.any():
        out[seg_b, 0, seg_row] = np.diff(starts, append=nb * n)[:, None]
        out[seg_b, 1, seg_row] = np.minimum.reduceat(flat_k, starts, axis=1).T
        out[seg_b, 2, seg_row] = np.maximum.reduceat(flat_k, starts, axis=1).T
        out[seg_b, 3, seg_row] = np.add.reduceat(flat_k, starts, axis=1).T
    else:
        flat_m = np.ascontiguousarray(mask.transpose(2, 0, 1)).reshape(c, nb * n)
        big = np.iinfo(np.int64).max
        out[seg_b, 0, seg_row] = np.add.reduceat((~flat_m).astype(np.int64), starts, axis=1).T
        out[seg_b, 1, seg_row] = np.minimum.reduceat(np.where(flat_m, big, flat_k), starts,
                                                     axis=1).T
        out[seg_b, 2, seg_row] = np.maximum.reduceat(np.where(flat_m, -big, flat_k), starts,
                                                     axis=1).T
        out[seg_b, 3, seg_row] = np.add.reduceat(np.where(flat_m, 0, flat_k), starts, axis=1).T
        empty = out[:, 0] == 0
        out[:, 1][empty] = 0
        out[:, 2][empty] = 0
    ms = idx[:, -1] + 1
    return [out[b, :, :ms[b]].reshape(4 * int(ms[b]), c) for b in range(nb)]


@functools.lru_cache(maxsize=1024)
def _layout(channels: tuple[str, ...], resolution: tuple[float, ...]) -> tuple[str, str]:
    return (json.dumps(list(channels), separators=(",", ":")),
            json.dumps(list(resolution), separators=(",", ":")))


@functools.lru_cache(maxsize=1024)
def _layout_problem(channels: tuple[object, ...], resolution: tuple[object, ...]) -> str | None:
    """What is wrong with a channel layout, or None (cached: a fleet has a few layouts)."""
    c = len(channels)
    if not 1 <= c <= MAX_CHANNELS or len(resolution) != c:
        return (f"{c} channel names, {len(resolution)} resolutions; expected equal counts in "
                f"1..{MAX_CHANNELS}")
    if (len(set(channels)) != c
            or not all(isinstance(ch, str) and 1 <= len(ch) <= MAX_CHANNEL_NAME
                       for ch in channels)):
        return f"channel names must be distinct strings of 1..{MAX_CHANNEL_NAME} characters"
    for r in resolution:
        if (isinstance(r, bool) or not isinstance(r, int | float | np.floating | np.integer)
                or not (math.isfinite(float(r)) and float(r) > 0)):
            return f"resolutions must be finite and > 0, got {list(resolution)}"
    return None


def _int(v: object) -> int | None:
    if isinstance(v, int) and not isinstance(v, bool):
        return v
    return int(v) if isinstance(v, np.integer) else None


def check_block(b: SampleBlock) -> str | None:
    """Why ``b`` cannot be stored (one line for logs), or None if it may be.

    Checks everything but the sample values (see the module docstring for the limits); cheap, no
    pass over the samples: :func:`block_rows` checks those, vectorised over many blocks.
    """
    epoch, seq, t0, period = (_int(b.epoch), _int(b.seq), _int(b.t0_ns), _int(b.period_ns))
    if epoch is None or seq is None or t0 is None or period is None:
        return (f"epoch, seq, t0_ns and period_ns must be integers, got {type(b.epoch).__name__}, "
                f"{type(b.seq).__name__}, {type(b.t0_ns).__name__}, "
                f"{type(b.period_ns).__name__}")
    if not 0 <= epoch <= INT63:
        return f"epoch {epoch} outside [0, 2**63 - 1]"
    if not 0 <= seq <= INT63:
        return f"seq {seq} outside [0, 2**63 - 1]"
    values = b.values
    if (not isinstance(values, np.ndarray) or values.ndim != 2
            or values.dtype.kind not in "fiu"):
        return "values must be a real 2-D array (samples × channels)"
    n, c = values.shape
    steps = b.steps
    if steps is not None and (not isinstance(steps, np.ndarray) or steps.shape != values.shape
                              or steps.dtype.kind not in "iu"):
        return "steps must be an integer array of the values' shape (samples × channels)"
    if not 1 <= n <= MAX_N:
        return f"{n} samples; expected 1..{MAX_N}"
    if period < 1:
        return f"period {period} ns; expected ≥ 1 ns"
    try:
        layout = _layout_problem(tuple(b.channels), tuple(b.resolution))
    except TypeError:  # unhashable names or resolutions
        return "channel names must be strings and resolutions numbers"
    if layout is not None:
        return layout
    if len(b.channels) != c:
        return f"{c} value columns for {len(b.channels)} channels"
    t_end = t0 + (n - 1) * period
    if t0 < 0 or t_end >= T_LIMIT_NS:
        return f"sample times [{t0}, {t_end}] ns outside [0, {T_LIMIT_NS}) ns"
    if t_end - t0 > MAX_SPAN_NS:
        return f"block spans {(t_end - t0) / SEC:.0f} s; at most {MAX_SPAN_NS // SEC} s"
    return None


GROUP_VALUES = 1 << 18
"""Most values (samples × channels) :func:`block_rows` encodes in one vectorised pass: a
datagram's blocks by the thousand, an import's 6000-sample blocks a few at a time. Each pass's
arrays (a few MB) stay in the CPU cache and in memory the allocator reuses; one pass over a
whole batch of large blocks spent more time in fresh pages (page faults) than in arithmetic."""


def block_rows(items: Sequence[tuple[int, SampleBlock]]) -> list[tuple[object, ...] | str]:
    """Column values (in :data:`COLUMNS` order) for (machine_pk, block) pairs: compresses the
    samples and their per-second summaries, vectorised over blocks of equal shape (at most
    :data:`GROUP_VALUES` values per pass).

    The blocks must have passed :func:`check_block`.

    Returns:
        Per item, its row, or why its values cannot be stored (an infinite value, or one more
        than 2**52 resolution steps from zero); one such block does not affect the others.
    """
    groups: dict[tuple[int, int, bool], list[int]] = {}
    for i, (_, b) in enumerate(items):
        n, c = b.values.shape
        wire = b.steps is not None and b.steps.shape == (n, c)
        groups.setdefault((n, c, wire), []).append(i)
    out: list[tuple[object, ...] | str] = [""] * len(items)
    for (n, c, _), idxs in groups.items():
        per = max(1, GROUP_VALUES // (n * c))
        for a in range(0, len(idxs), per):
            _group_rows(items, idxs[a:a + per], out)
    return out


def _channel_major(arrays: list[npt.NDArray[Any]], dtype: type) -> npt.NDArray[Any]:
    """B arrays of shape (n, c) as one C-contiguous array of shape (c, B, n) and ``dtype`` (cast
    as ``astype`` does)."""
    n, c = arrays[0].shape
    out: npt.NDArray[Any] = np.empty((c, len(arrays), n), dtype=dtype)
    np.stack([a.T for a in arrays], axis=1, out=out, casting="unsafe")
    return out


def _group_rows(items: Sequence[tuple[int, SampleBlock]], idxs: list[int],
                out: list[tuple[object, ...] | str]) -> None:
    """:func:`block_rows` of the blocks ``items[i]`` for i in ``idxs`` (all of one shape (n, c),
    all with the wire's steps or all without), into ``out[i]``. Arrays are channel-major, shape
    (c, B, n): each block's channel is a contiguous run of samples, as the blob and the
    summaries take them."""
    blks = [items[i][1] for i in idxs]
    n, c = blks[0].values.shape
    missing = np.isnan(np.stack([b.values for b in blks], dtype=np.float64, casting="unsafe"))
    mask = (np.ascontiguousarray(missing.transpose(2, 0, 1)) if missing.any()
            else np.zeros((c, len(blks), n), dtype=bool))
    wire = [st for b in blks if (st := b.steps) is not None and st.shape == b.values.shape]
    if len(wire) == len(blks):  # the wire's steps, kept as they are
        k = _channel_major(wire, np.int64)
        ok = (np.ones(len(blks), dtype=bool) if -_STEP_LIMIT < k.min() and k.max() < _STEP_LIMIT
              else np.all((k > -_STEP_LIMIT) & (k < _STEP_LIMIT), axis=(0, 2)))
    else:
        res = np.array([np.asarray(b.resolution, dtype=np.float64) for b in blks]).T[:, :, None]
        values = _channel_major([b.values for b in blks], np.float64)
        scaled = np.rint(np.where(mask, 0.0, values) / res)
        ok = (np.ones(len(blks), dtype=bool)
              if -_VALUE_LIMIT < scaled.min() and scaled.max() < _VALUE_LIMIT  # ±inf fail here
              else np.all(np.abs(scaled) < _VALUE_LIMIT, axis=(0, 2)))
        k = scaled.astype(np.int64) if ok.all() else np.where(
            ok[None, :, None], scaled, 0.0).astype(np.int64)
    good = idxs
    if not ok.all():
        for bad in np.flatnonzero(~ok).tolist():
            out[idxs[bad]] = "values are infinite or too large for their resolution"
        if not ok.any():
            return
        good = [i for i, g in zip(idxs, ok.tolist(), strict=True) if g]
        k = np.ascontiguousarray(k[:, ok, :])
        mask = np.ascontiguousarray(mask[:, ok, :])
    kb = k.transpose(1, 2, 0)  # (B, n, c) views of the channel-major arrays
    mb = mask.transpose(1, 2, 0) if mask.any() else None
    data = codec.encode_many(kb, mb, strategy=codec.BLOCK_STRATEGY)
    t0s = [int(items[i][1].t0_ns) for i in good]
    periods = [int(items[i][1].period_ns) for i in good]
    t0 = np.array(t0s, dtype=np.int64)
    period = np.array(periods, dtype=np.int64)
    secs = (t0 + (n - 1) * period) // SEC - t0 // SEC + 1
    spans = np.unique(secs)
    if spans.size == 1:
        summ = per_second(kb, mb, t0, period)
    else:  # equal spans together: a long block pads no short one
        summ = [np.zeros((0, 0), dtype=np.int64)] * len(good)
        for m in spans:
            sel = np.flatnonzero(secs == m)
            for jj, agg in zip(sel.tolist(),
                               per_second(kb[sel], None if mb is None else mb[sel], t0[sel],
                                          period[sel]),
                               strict=True):
                summ[jj] = agg
    for j, i in enumerate(good):
        pk, b = items[i]
        ch, r = b.channels, b.resolution
        chans, resj = _layout(ch if type(ch) is tuple else tuple(ch),
                              r if type(r) is tuple else tuple(float(x) for x in r))
        t0j, pj = t0s[j], periods[j]
        out[i] = (pk, int(b.epoch), int(b.seq), t0j, t0j + (n - 1) * pj, pj, n, chans, resj,
                  codec.encode_plain(summ[j]), data[j])


Key = tuple[int, int, int]
"""Identity of a stored block: (machine_pk, epoch, seq)."""


def insert_new(session: Session, rows: Sequence[tuple[object, ...]]) -> set[Key]:
    """Insert block rows, ignoring those whose (machine, epoch, seq) is already stored.

    Returns:
        The (machine_pk, epoch, seq) keys that were newly inserted.
    """
    conn = session.connection()
    target = ("machine_pk, epoch, seq, t_start_ns" if conn.dialect.name == "postgresql"
              else "machine_pk, epoch, seq")
    got = bulk.insert_rows(conn, BlockRow.__tablename__, COLUMNS, rows,
                           f"ON CONFLICT ({target}) DO NOTHING RETURNING machine_pk, epoch, seq")
    return {(int(a), int(b), int(c)) for a, b, c in got}


def stored_shapes(session: Session, keys: Sequence[Key]) -> dict[Key, tuple[int, int, int]]:
    """(t_start_ns, n, period_ns) of those of ``keys`` that are stored (one query per 5000)."""
    out: dict[Key, tuple[int, int, int]] = {}
    b = BlockRow
    for i in range(0, len(keys), 5000):
        chunk = list(keys[i:i + 5000])
        stmt = (select(b.machine_pk, b.epoch, b.seq, b.t_start_ns, b.n, b.period_ns)
                .where(tuple_(b.machine_pk, b.epoch, b.seq).in_(chunk)))
        for pk, ep, sq, t0, n, per in session.execute(stmt):
            out[(int(pk), int(ep), int(sq))] = (int(t0), int(n), int(per))
    return out


@dataclass(frozen=True)
class ProbeHit:
    """What is stored where a new block would go.

    Attributes:
        same_key: (t_start_ns, n, period_ns) of the stored block with the new block's
            (machine, epoch, seq), or None.
        overlap: (epoch, seq) of a stored block of the machine whose time range [t_start, t_end]
            intersects the new block's, or None (exact while stored blocks do not overlap each
            other, which :meth:`cranetwin.storage.Store.write_batch` maintains).
    """

    same_key: tuple[int, int, int] | None
    overlap: tuple[int, int] | None


_PROBE_PG = (
    "SELECT v.i, k.t_start_ns, k.n, k.period_ns, o.epoch, o.seq "
    "FROM unnest(%b::int[], %b::int[], %b::bigint[], %b::bigint[], %b::bigint[], "
    "%b::bigint[]) AS v(i, pk, epoch, seq, t0, t1) "
    "LEFT JOIN sample_blocks k ON k.machine_pk = v.pk AND k.epoch = v.epoch AND k.seq = v.seq "
    "LEFT JOIN LATERAL (SELECT b.epoch, b.seq, b.t_start_ns FROM sample_blocks b "
    "WHERE b.machine_pk = v.pk AND b.t_end_ns >= v.t0 "
    f"AND b.t_start_ns >= v.t0 - {MAX_SPAN_NS} ORDER BY b.t_end_ns LIMIT 1) o "
    "ON o.t_start_ns <= v.t1 "
    "WHERE k.id IS NOT NULL OR o.seq IS NOT NULL")
_PROBE_SQLITE = (
    "WITH v(i, pk, epoch, seq, t0, t1) AS (VALUES {rows}) "
    "SELECT v.i, k.t_start_ns, k.n, k.period_ns, o.epoch, o.seq FROM v "
    "LEFT JOIN sample_blocks k ON k.machine_pk = v.pk AND k.epoch = v.epoch AND k.seq = v.seq "
    "LEFT JOIN sample_blocks o ON o.id = (SELECT b.id FROM sample_blocks b "
    "WHERE b.machine_pk = v.pk AND b.t_end_ns >= v.t0 ORDER BY b.t_end_ns LIMIT 1) "
    "AND o.t_start_ns <= v.t1 "
    "WHERE k.id IS NOT NULL OR o.id IS NOT NULL")
_PROBE_ROWS = 5000


def probe(conn: Connection, items: Sequence[tuple[int, int, int, int, int, int]]
          ) -> dict[int, ProbeHit]:
    """For many new blocks at once: the stored block with the same key, and a stored block that
    overlaps in time (two index probes per block, one statement per 5000 blocks).

    The overlap probe takes, per new block [t0, t1], the stored block of the machine with the
    smallest t_end ≥ t0 (index (machine, t_end)) and reports it if it starts at or before t1.

    Args:
        conn: Connection inside the caller's transaction.
        items: (i, machine_pk, epoch, seq, t0_ns, t_end_ns) per new block; ``i`` is the
            caller's label, returned as the key.

    Returns:
        Label → hit, for the blocks with at least one hit only (none in the usual case).
    """
    pg = conn.dialect.name == "postgresql"
    out: dict[int, ProbeHit] = {}
    for a in range(0, len(items), _PROBE_ROWS):
        chunk = items[a:a + _PROBE_ROWS]
        if pg:  # one array per column: a fixed statement, nothing for the driver to parse
            sql = _PROBE_PG
            params: tuple[Any, ...] = tuple(list(c) for c in zip(*chunk, strict=True))
        else:
            sql = _PROBE_SQLITE.format(rows=",".join(["(?,?,?,?,?,?)"] * len(chunk)))
            params = tuple(v for r in chunk for v in r)
        for i, k_t0, k_n, k_per, o_ep, o_seq in conn.exec_driver_sql(sql, params).all():
            out[int(i)] = ProbeHit(
                None if k_t0 is None else (int(k_t0), int(k_n), int(k_per)),
                None if o_seq is None else (int(o_ep), int(o_seq)))
    return out


@dataclass(frozen=True)
class StoredBlock:
    """A block read back from the table: the run the wire carried.

    Attributes:
        seq: Sequence number.
        t0_ns: First sample time [ns]; period_ns: sample period [ns].
        channels, resolution: Channel layout.
        steps: Integer steps, shape (n, len(channels)), 0 where ``missing``.
        missing: Missing samples, shape (n, len(channels)).
    """

    seq: int
    t0_ns: int
    period_ns: int
    channels: tuple[str, ...]
    resolution: tuple[float, ...]
    steps: I64
    missing: npt.NDArray[np.bool_]

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.steps.shape[0])

    @property
    def values(self) -> F64:
        """``steps · resolution``, shape (n, len(channels)) [channel units]; NaN where missing."""
        return intcodec.dequantise(self.steps, self.missing, self.resolution)

    def times_ns(self) -> I64:
        """Sample times ``t0_ns + k · period_ns``, shape (n,) [ns]."""
        return self.t0_ns + np.arange(self.n, dtype=np.int64) * self.period_ns


def clamp_ns(t_ns: int | float) -> int:
    """``t_ns`` limited to the signed 64-bit range (a query bound far outside any stored time
    selects the same rows, and a database never sees an integer it cannot hold)."""
    if isinstance(t_ns, float):
        if math.isnan(t_ns):
            raise ValueError("a time bound is NaN")
        if not math.isfinite(t_ns):
            return INT63 if t_ns > 0 else -INT63 - 1
    return max(-INT63 - 1, min(INT63, int(t_ns)))


def read_range(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> list[StoredBlock]:
    """Blocks of a machine that overlap [t0_ns, t1_ns], ordered by start time."""
    stmt = (select(BlockRow.seq, BlockRow.t_start_ns, BlockRow.period_ns, BlockRow.channels,
                   BlockRow.resolution, BlockRow.data)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns <= clamp_ns(t1_ns),
                   BlockRow.t_end_ns >= clamp_ns(t0_ns),
                   BlockRow.t_start_ns >= clamp_ns(clamp_ns(t0_ns) - MAX_SPAN_NS))
            .order_by(BlockRow.t_start_ns, BlockRow.epoch, BlockRow.seq))
    return [_stored(*row) for row in session.execute(stmt)]


def spans(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> list[tuple[int, int]]:
    """(t_start_ns, t_end_ns) of the blocks of a machine that overlap [t0_ns, t1_ns] (their first
    and last sample time [ns], inclusive), ordered by start; nothing decoded."""
    stmt = (select(BlockRow.t_start_ns, BlockRow.t_end_ns)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns <= clamp_ns(t1_ns),
                   BlockRow.t_end_ns >= clamp_ns(t0_ns),
                   BlockRow.t_start_ns >= clamp_ns(clamp_ns(t0_ns) - MAX_SPAN_NS))
            .order_by(BlockRow.t_start_ns))
    return [(int(a), int(b)) for a, b in session.execute(stmt)]


def _stored(seq: int, t0: int, period: int, chans: str, res: str, data: bytes) -> StoredBlock:
    resolution = tuple(float(r) for r in json.loads(res))
    steps, missing = codec.decode_ints(data)
    if steps.shape[1] != len(resolution):
        raise codec.CodecError(f"block seq {seq}: {steps.shape[1]} channels stored, "
                               f"{len(resolution)} resolutions")
    return StoredBlock(int(seq), int(t0), int(period), tuple(json.loads(chans)), resolution,
                       steps, missing)


def read_ranges(session: Session, bounds: dict[int, tuple[int, int]],
                ) -> dict[int, list[StoredBlock]]:
    """:func:`read_range` of many machines in one statement (PostgreSQL; one per machine
    elsewhere): machine primary key → (t0_ns, t1_ns) → its blocks, ordered as there."""
    if session.get_bind().dialect.name != "postgresql":
        return {pk: read_range(session, pk, a, z) for pk, (a, z) in bounds.items()}
    pks = list(bounds)
    lo = [clamp_ns(bounds[p][0]) for p in pks]
    stmt = text(
        "SELECT b.machine_pk, b.seq, b.t_start_ns, b.period_ns, b.channels, b.resolution, b.data "
        "FROM unnest(CAST(:pks AS integer[]), CAST(:los AS bigint[]), CAST(:his AS bigint[]), "
        "CAST(:from_ AS bigint[])) AS v(pk, lo, hi, from_) JOIN sample_blocks b "
        "ON b.machine_pk = v.pk AND b.t_start_ns <= v.hi AND b.t_end_ns >= v.lo "
        "AND b.t_start_ns >= v.from_ "
        "ORDER BY b.machine_pk, b.t_start_ns, b.epoch, b.seq").bindparams(
        pks=pks, los=lo, his=[clamp_ns(bounds[p][1]) for p in pks],
        from_=[clamp_ns(x - MAX_SPAN_NS) for x in lo])
    out: dict[int, list[StoredBlock]] = {pk: [] for pk in pks}
    for pk, *row in session.execute(stmt):
        out[int(pk)].append(_stored(*row))
    return out


@dataclass(frozen=True)
class SecondAggregates:
    """Per-second aggregates of one block, in channel units.

    Attributes:
        sec: Second of each row, shape (m,) [s since the epoch].
        channels: Channel names, length c.
        count: Shape (m, c); min, max, sum: shape (m, c) [channel units] (0 where count is 0).
    """

    sec: I64
    channels: tuple[str, ...]
    count: I64
    min: F64
    max: F64
    sum: F64


def read_second_aggregates(session: Session, machine_pk: int, t0_s: int, t1_s: int,
                           corrupt: list[int] | None = None) -> Iterator[SecondAggregates]:
    """Per-second aggregates of the blocks overlapping seconds [t0_s, t1_s) (whole blocks; the
    caller drops seconds outside). Reads the summary column only, never the samples.

    A row whose summary, channel list or resolutions cannot be decoded (or disagree in shape) is
    skipped with a warning, and its row id appended to ``corrupt`` when given: one damaged row
    never makes a range unreadable.
    """
    stmt = (select(BlockRow.id, BlockRow.t_start_ns, BlockRow.channels, BlockRow.resolution,
                   BlockRow.summary)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns < clamp_ns(t1_s * SEC),
                   BlockRow.t_end_ns >= clamp_ns(t0_s * SEC),
                   BlockRow.t_start_ns >= clamp_ns(clamp_ns(t0_s * SEC) - MAX_SPAN_NS)))
    for row_id, t0, chans, res, blob in session.execute(stmt):
        try:
            k = codec.decode_plain(blob)
            names = tuple(json.loads(chans))
            r = np.asarray(json.loads(res), dtype=np.float64)
            m = k.shape[0] // 4
            if k.ndim != 2 or k.shape[0] != 4 * m or k.shape[1] != len(names):
                raise ValueError(f"summary shape {k.shape} does not fit {len(names)} channels")
            if r.shape != (len(names),):
                raise ValueError(f"{r.shape} resolutions for {len(names)} channels")
        except (codec.CodecError, ValueError, TypeError) as exc:  # JSONDecodeError is a ValueError
            log.warning("sample block row %s (machine pk %s): summary unreadable, skipped: %s",
                        row_id, machine_pk, exc)
            if corrupt is not None:
                corrupt.append(int(row_id))
            continue
        sec = int(t0) // SEC + np.arange(m, dtype=np.int64)
        yield SecondAggregates(sec, names, k[:m], k[m:2 * m] * r, k[2 * m:3 * m] * r,
                               k[3 * m:] * r)
