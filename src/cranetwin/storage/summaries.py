"""Per-interval summaries (count, min, max, sum per channel) at 1 s and 1 min.

Load-history queries read these instead of raw samples: a 24-hour chart of one channel is at most
1440 one-minute rows. Summaries of raw channels are maintained by ``Store.write_blocks`` from the
blocks that were *newly* inserted in the same transaction, so a retransmitted block is never
counted twice. Derived channels (``force:lift``, ...) are written by the twin worker with
:func:`replace`, which overwrites the buckets it covers, so re-running a replay is idempotent too.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from sqlalchemy import (
    BigInteger,
    Float,
    ForeignKey,
    Integer,
    String,
    case,
    delete,
    func,
    insert,
    select,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.errors import StorageError
from cranetwin.samples import F64
from cranetwin.storage.base import Base

LEVELS_S: tuple[int, ...] = (1, 60)
"""Bucket widths maintained on write [s]."""

Key = tuple[int, str, int, int]  # machine_pk, channel, level_s, bucket_s
Agg = list[float]  # [count, min, max, sum]


class SummaryRow(Base):
    """Aggregate of one channel of one machine over one bucket [bucket_s, bucket_s + level_s)."""

    __tablename__ = "summaries"

    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"),
                                            primary_key=True)
    channel: Mapped[str] = mapped_column(String(64), primary_key=True)
    level_s: Mapped[int] = mapped_column(Integer, primary_key=True)
    bucket_s: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    n: Mapped[int] = mapped_column(BigInteger)
    vmin: Mapped[float] = mapped_column(Float)
    vmax: Mapped[float] = mapped_column(Float)
    vsum: Mapped[float] = mapped_column(Float)


def accumulate(acc: dict[Key, Agg], machine_pk: int, channels: Sequence[str], t_ns: npt.NDArray[
        np.int64], values: F64) -> None:
    """Add samples to in-memory bucket aggregates (NaN samples are skipped).

    Args:
        acc: Aggregates to update, keyed (machine_pk, channel, level_s, bucket_s).
        machine_pk: Machine row id.
        channels: Channel names, length c.
        t_ns: Sample times, shape (n,), non-decreasing [ns].
        values: Shape (n, c) [channel units]; NaN = missing.
    """
    if t_ns.size == 0:
        return
    ok = ~np.isnan(values)
    vmin = np.where(ok, values, np.inf)
    vmax = np.where(ok, values, -np.inf)
    vsum = np.where(ok, values, 0.0)
    cnt = ok.astype(np.int64)
    for level in LEVELS_S:
        bucket = (t_ns // (level * 1_000_000_000)) * level
        starts = np.concatenate(([0], np.flatnonzero(np.diff(bucket)) + 1))
        mins = np.minimum.reduceat(vmin, starts, axis=0)
        maxs = np.maximum.reduceat(vmax, starts, axis=0)
        sums = np.add.reduceat(vsum, starts, axis=0)
        cnts = np.add.reduceat(cnt, starts, axis=0)
        for i, b in enumerate(bucket[starts].tolist()):
            for j, ch in enumerate(channels):
                c = int(cnts[i, j])
                if c == 0:
                    continue
                key = (machine_pk, ch, level, b)
                a = acc.get(key)
                if a is None:
                    acc[key] = [c, float(mins[i, j]), float(maxs[i, j]), float(sums[i, j])]
                else:
                    a[0] += c
                    a[1] = min(a[1], float(mins[i, j]))
                    a[2] = max(a[2], float(maxs[i, j]))
                    a[3] += float(sums[i, j])


def _rows(acc: dict[Key, Agg]) -> list[dict[str, object]]:
    return [{"machine_pk": k[0], "channel": k[1], "level_s": k[2], "bucket_s": k[3],
             "n": int(a[0]), "vmin": a[1], "vmax": a[2], "vsum": a[3]} for k, a in acc.items()]


def merge(session: Session, acc: dict[Key, Agg]) -> None:
    """Add aggregates to the table (count and sum added, min/max combined) — an upsert."""
    if not acc:
        return
    dialect = session.get_bind().dialect.name
    ins = postgresql.insert(SummaryRow) if dialect == "postgresql" else sqlite.insert(SummaryRow)
    t, x = SummaryRow, ins.excluded
    stmt = ins.on_conflict_do_update(
        index_elements=["machine_pk", "channel", "level_s", "bucket_s"],
        set_={"n": t.n + x.n, "vsum": t.vsum + x.vsum,
              "vmin": case((x.vmin < t.vmin, x.vmin), else_=t.vmin),
              "vmax": case((x.vmax > t.vmax, x.vmax), else_=t.vmax)})
    session.execute(stmt, _rows(acc))


def replace(session: Session, machine_pk: int, channels: Sequence[str], t_ns: npt.NDArray[
        np.int64], values: F64) -> int:
    """Overwrite the buckets covered by ``t_ns`` with aggregates of ``values`` (derived channels).

    Buckets at both ends of the span are overwritten with what this call sees, so callers write
    whole minutes to keep the 1-min level exact.

    Returns:
        Number of bucket rows written.
    """
    acc: dict[Key, Agg] = {}
    accumulate(acc, machine_pk, channels, t_ns, values)
    for level in LEVELS_S:
        lo = int(t_ns[0] // (level * 1_000_000_000)) * level
        hi = int(t_ns[-1] // (level * 1_000_000_000)) * level
        session.execute(delete(SummaryRow).where(
            SummaryRow.machine_pk == machine_pk, SummaryRow.channel.in_(list(channels)),
            SummaryRow.level_s == level, SummaryRow.bucket_s.between(lo, hi)))
    if acc:
        session.execute(insert(SummaryRow), _rows(acc))
    return len(acc)


@dataclass(frozen=True)
class Summaries:
    """Bucketed min/max/mean of some channels of one machine.

    Attributes:
        machine_id: Machine identifier.
        bucket_s: Bucket width [s] (1, 60 or a multiple of 60).
        t_s: Bucket start times, shape (m,) [s since the epoch]; m ≤ max_points.
        channels: Channel names, length c.
        min, max, mean: Shape (m, c) [channel units]; NaN where a bucket has no sample.
        count: Samples per bucket, shape (m, c).
    """

    machine_id: str
    bucket_s: int
    t_s: F64
    channels: tuple[str, ...]
    min: F64
    max: F64
    mean: F64
    count: npt.NDArray[np.int64]


def choose_width(t0_s: float, t1_s: float, max_points: int) -> tuple[int, int, int]:
    """Pick the stored level and the bucket width so that at most ``max_points`` buckets cover
    [t0_s, t1_s).

    Returns:
        ``(level_s, width_s, origin_s)``: level read, bucket width (a multiple of it) and the
        first bucket's start (a multiple of the width).
    """
    if max_points < 1:
        raise StorageError(f"max_points must be ≥ 1, got {max_points}")
    if not t1_s > t0_s:
        raise StorageError(f"empty time range [{t0_s}, {t1_s}); expected t1 > t0")
    level = 1 if (t1_s - t0_s) <= max_points else 60
    width = level * max(1, math.ceil((t1_s - t0_s) / (level * max_points)))
    while True:
        origin = math.floor(t0_s / width) * width
        if math.ceil((t1_s - origin) / width) <= max_points:
            return level, width, origin
        width += level


def query(session: Session, machine_pk: int, machine_id: str, channels: Iterable[str],
          t0_s: float, t1_s: float, max_points: int) -> Summaries:
    """Read bucketed aggregates of [t0_s, t1_s) (buckets that start in the range's grid)."""
    chans = tuple(channels)
    level, width, origin = choose_width(t0_s, t1_s, max_points)
    m = math.ceil((t1_s - origin) / width)
    g = ((SummaryRow.bucket_s - origin) // width).label("g")  # integer division, both dialects
    stmt = (select(SummaryRow.channel, g, func.sum(SummaryRow.n), func.min(SummaryRow.vmin),
                   func.max(SummaryRow.vmax), func.sum(SummaryRow.vsum))
            .where(SummaryRow.machine_pk == machine_pk, SummaryRow.level_s == level,
                   SummaryRow.channel.in_(chans), SummaryRow.bucket_s >= origin,
                   SummaryRow.bucket_s < origin + m * width)
            .group_by(SummaryRow.channel, g))
    shape = (m, len(chans))
    vmin, vmax, vsum = np.full(shape, np.nan), np.full(shape, np.nan), np.zeros(shape)
    count = np.zeros(shape, dtype=np.int64)
    col = {c: j for j, c in enumerate(chans)}
    for ch, gi, n, lo, hi, s in session.execute(stmt):
        i, j = int(gi), col[ch]
        count[i, j], vmin[i, j], vmax[i, j], vsum[i, j] = int(n), lo, hi, s
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, vsum / np.maximum(count, 1), np.nan)
    t = origin + width * np.arange(m, dtype=np.float64)
    return Summaries(machine_id, width, t, chans, vmin, vmax, mean, count)
