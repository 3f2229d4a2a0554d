"""Raw samples, stored as compressed blocks: one row per received datagram, not one per sample.

A row holds one :class:`~cranetwin.samples.SampleBlock` (``n`` regularly spaced samples of one
machine) compressed by :mod:`cranetwin.storage.codec`, plus its per-second summary (count, min,
max, sum of the quantised values per channel for every whole second the block touches), so that
1-s load history never decodes raw samples. Rows are unique on (machine, seq), and inserted with
``ON CONFLICT DO NOTHING`` on both dialects, so writing a block twice (a retransmission, a
replayed batch after a crash) stores it once.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

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
)
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.samples import F64, SampleBlock
from cranetwin.storage import bulk, codec
from cranetwin.storage.base import Base

I64 = npt.NDArray[np.int64]
SEC = 1_000_000_000


class BlockRow(Base):
    """A compressed run of samples of one machine (one datagram's worth)."""

    __tablename__ = "sample_blocks"
    __table_args__ = (
        UniqueConstraint("machine_pk", "seq"),
        Index("ix_sample_blocks_machine_t_start", "machine_pk", "t_start_ns"),
        Index("ix_sample_blocks_machine_t_end", "machine_pk", "t_end_ns"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(BigInteger)
    t_start_ns: Mapped[int] = mapped_column(BigInteger)
    t_end_ns: Mapped[int] = mapped_column(BigInteger)
    period_ns: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int] = mapped_column(Integer)
    channels: Mapped[str] = mapped_column(Text)  # JSON list of names
    resolution: Mapped[str] = mapped_column(Text)  # JSON list of steps
    summary: Mapped[bytes] = mapped_column(LargeBinary)  # per-second aggregates, see module doc
    data: Mapped[bytes] = mapped_column(LargeBinary)


COLUMNS = ("machine_pk", "seq", "t_start_ns", "t_end_ns", "period_ns", "n", "channels",
           "resolution", "summary", "data")


def per_second(k: I64, mask: npt.NDArray[np.bool_], t0_ns: npt.NDArray[np.int64],
               period_ns: npt.NDArray[np.int64]) -> list[I64]:
    """Aggregates of quantised samples per whole second, for B equally shaped blocks.

    Args:
        k: Quantised values, shape (B, n, c); mask: missing samples, shape (B, n, c).
        t0_ns: First sample time of each block, shape (B,) [ns].
        period_ns: Sample period of each block, shape (B,) [ns].

    Returns:
        Per block, shape (4·m, c) for the m seconds from floor(t0 / 1 s): rows [0, m) counts,
        [m, 2m) minima, [2m, 3m) maxima, [3m, 4m) sums of k; min = max = 0 where count is 0.
    """
    nb, n, c = k.shape
    sec = (t0_ns[:, None] + np.arange(n, dtype=np.int64) * period_ns[:, None]) // SEC
    idx = sec - sec[:, :1]
    change = np.ones((nb, n), dtype=bool)
    change[:, 1:] = idx[:, 1:] != idx[:, :-1]
    starts = np.flatnonzero(change.ravel())
    flat_k, flat_m = k.reshape(nb * n, c), mask.reshape(nb * n, c)
    big = np.iinfo(np.int64).max
    seg_b, seg_row = starts // n, idx.ravel()[starts]
    m_max = int(idx[:, -1].max()) + 1
    out = np.zeros((nb, 4, m_max, c), dtype=np.int64)
    out[seg_b, 0, seg_row] = np.add.reduceat((~flat_m).astype(np.int64), starts, axis=0)
    out[seg_b, 1, seg_row] = np.minimum.reduceat(np.where(flat_m, big, flat_k), starts, axis=0)
    out[seg_b, 2, seg_row] = np.maximum.reduceat(np.where(flat_m, -big, flat_k), starts, axis=0)
    out[seg_b, 3, seg_row] = np.add.reduceat(np.where(flat_m, 0, flat_k), starts, axis=0)
    empty = out[:, 0] == 0
    out[:, 1][empty] = 0
    out[:, 2][empty] = 0
    ms = idx[:, -1] + 1
    return [out[b, :, :ms[b]].reshape(4 * int(ms[b]), c) for b in range(nb)]


@functools.lru_cache(maxsize=1024)
def _layout(channels: tuple[str, ...], resolution: tuple[float, ...]) -> tuple[str, str]:
    return (json.dumps(list(channels), separators=(",", ":")),
            json.dumps(list(resolution), separators=(",", ":")))


def block_rows(items: Sequence[tuple[int, SampleBlock]]) -> list[tuple[object, ...]]:
    """Column values (in :data:`COLUMNS` order) for (machine_pk, block) pairs: compresses the
    samples and their per-second summaries, vectorised over blocks of equal shape."""
    groups: dict[tuple[int, int], list[int]] = {}
    for i, (_, b) in enumerate(items):
        groups.setdefault(b.values.shape, []).append(i)
    out: list[tuple[object, ...]] = [()] * len(items)
    for idxs in groups.values():
        bl = [items[i][1] for i in idxs]
        values = np.stack([b.values for b in bl])
        res = np.stack([np.asarray(b.resolution, dtype=np.float64) for b in bl])[:, None, :]
        mask = np.isnan(values)
        if not np.all(res > 0):
            raise codec.CodecError("resolutions must be > 0")
        scaled = np.rint(np.where(mask, 0.0, values) / res)
        if not np.all(np.abs(scaled) < 2.0**52):
            raise codec.CodecError("values are infinite or too large for their resolution")
        k = scaled.astype(np.int64)
        data = codec.encode_many(k, mask)
        summ = per_second(k, mask, np.array([b.t0_ns for b in bl], dtype=np.int64),
                          np.array([b.period_ns for b in bl], dtype=np.int64))
        for j, i in enumerate(idxs):
            pk, b = items[i]
            out[i] = (pk, b.seq, b.t0_ns, b.t_end_ns, b.period_ns, b.n,
                      *_layout(b.channels, b.resolution), codec.encode_plain(summ[j]), data[j])
    return out


def insert_new(session: Session, rows: Sequence[tuple[object, ...]]) -> set[tuple[int, int]]:
    """Insert block rows, ignoring (machine, seq) already stored.

    Returns:
        The (machine_pk, seq) keys that were newly inserted.
    """
    got = bulk.insert_rows(session.connection(), BlockRow.__tablename__, COLUMNS, rows,
                           "ON CONFLICT (machine_pk, seq) DO NOTHING RETURNING machine_pk, seq")
    return {(int(a), int(b)) for a, b in got}


@dataclass(frozen=True)
class StoredBlock:
    """A block read back from the table.

    Attributes:
        seq: Sequence number.
        t0_ns: First sample time [ns]; period_ns: sample period [ns].
        channels, resolution: Channel layout.
        values: Shape (n, len(channels)) [channel units].
    """

    seq: int
    t0_ns: int
    period_ns: int
    channels: tuple[str, ...]
    resolution: tuple[float, ...]
    values: F64

    def times_ns(self) -> I64:
        """Sample times, shape (n,) [ns]."""
        return self.t0_ns + np.arange(self.values.shape[0], dtype=np.int64) * self.period_ns


def read_range(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> list[StoredBlock]:
    """Blocks of a machine that overlap [t0_ns, t1_ns], ordered by start time."""
    stmt = (select(BlockRow.seq, BlockRow.t_start_ns, BlockRow.period_ns, BlockRow.channels,
                   BlockRow.resolution, BlockRow.data)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns <= t1_ns,
                   BlockRow.t_end_ns >= t0_ns)
            .order_by(BlockRow.t_start_ns, BlockRow.seq))
    out = []
    for seq, t0, period, chans, res, data in session.execute(stmt):
        resolution = tuple(float(r) for r in json.loads(res))
        out.append(StoredBlock(int(seq), int(t0), int(period), tuple(json.loads(chans)),
                               resolution, codec.decode(data, resolution)))
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


def read_second_aggregates(session: Session, machine_pk: int, t0_s: int,
                           t1_s: int) -> Iterator[SecondAggregates]:
    """Per-second aggregates of the blocks overlapping seconds [t0_s, t1_s) (whole blocks; the
    caller drops seconds outside). Reads the summary column only, never the samples."""
    stmt = (select(BlockRow.t_start_ns, BlockRow.channels, BlockRow.resolution, BlockRow.summary)
            .where(BlockRow.machine_pk == machine_pk, BlockRow.t_start_ns < t1_s * SEC,
                   BlockRow.t_end_ns >= t0_s * SEC))
    for t0, chans, res, blob in session.execute(stmt):
        k = codec.decode_plain(blob)
        m = k.shape[0] // 4
        r = np.asarray(json.loads(res), dtype=np.float64)
        sec = int(t0) // SEC + np.arange(m, dtype=np.int64)
        yield SecondAggregates(sec, tuple(json.loads(chans)), k[:m], k[m:2 * m] * r,
                               k[2 * m:3 * m] * r, k[3 * m:] * r)
