"""Per-interval summaries (count, min, max, mean per channel) at 1 s and 1 min.

Load-history queries read these instead of raw samples (a 24-hour chart of one channel is at most
1440 one-minute rows). Three sources, none of which can count a sample twice:

* **1 s, raw channels**: the per-second aggregates stored with each block
  (:func:`cranetwin.storage.blocks.per_second`), written in the block's own row, so a duplicate
  block (ignored by the unique key) adds nothing.
* **1 min, raw channels**: rows of the ``summaries`` table *recomputed* (not incremented) from the
  per-second aggregates of the minute by :func:`rollup`. Every transaction that stores a new block
  marks its minutes in ``summary_dirty``; a query computes dirty minutes on the fly from the
  blocks, so results are exact before and after the rollup runs.
* **derived channels** (``force:lift``, ...): 1-s rows written by the twin with :func:`replace`,
  which overwrites the seconds it covers and recomputes their minutes from the 1-s rows, so
  consecutive windows add up and re-running a replay is idempotent.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from sqlalchemy import (
    BigInteger,
    Float,
    ForeignKey,
    Integer,
    String,
    delete,
    func,
    insert,
    literal,
    select,
)
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.errors import StorageError
from cranetwin.samples import F64
from cranetwin.storage import bulk
from cranetwin.storage.base import Base
from cranetwin.storage.blocks import SEC, read_second_aggregates
from cranetwin.storage.dberrors import is_unavailable, unavailable

log = logging.getLogger(__name__)

LEVELS_S: tuple[int, ...] = (1, 60)
"""Stored bucket widths [s]."""
MINUTE = 60

Key = tuple[str, int, int]  # channel, level_s, bucket_s
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


class DirtyMinute(Base):
    """A minute of a machine whose 1-min raw summaries are stale (new blocks since the rollup).

    ``version`` is bumped by every writer that touches the minute, so a rollup deletes the mark
    only if no block arrived while it computed.
    """

    __tablename__ = "summary_dirty"

    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"),
                                            primary_key=True)
    minute_s: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    version: Mapped[int] = mapped_column(BigInteger, default=0)


def mark_dirty(session: Session, minutes: Iterable[tuple[int, int]]) -> None:
    """Mark (machine_pk, minute_s) pairs stale, in the caller's transaction."""
    rows = sorted({(pk, m, 0) for pk, m in minutes})
    bulk.insert_rows(session.connection(), DirtyMinute.__tablename__,
                     ("machine_pk", "minute_s", "version"), rows,
                     "ON CONFLICT (machine_pk, minute_s) DO UPDATE SET "
                     "version = summary_dirty.version + 1")


def block_minutes(machine_pk: int, t0_ns: int, t_end_ns: int) -> list[tuple[int, int]]:
    """(machine_pk, minute_s) of every minute a block spans."""
    a, b = t0_ns // (MINUTE * SEC), t_end_ns // (MINUTE * SEC)
    return [(machine_pk, int(m) * MINUTE) for m in range(a, b + 1)]


@dataclass
class _Records:
    """Flat aggregate records: bucket start [s], channel index, count, min, max, sum."""

    sec: list[npt.NDArray[np.int64]]
    col: list[npt.NDArray[np.int64]]
    n: list[npt.NDArray[np.int64]]
    lo: list[F64]
    hi: list[F64]
    sm: list[F64]

    @classmethod
    def empty(cls) -> _Records:
        return cls([], [], [], [], [], [])

    def add(self, sec: npt.NDArray[np.int64], j: int, n: npt.NDArray[np.int64], lo: F64, hi: F64,
            sm: F64) -> None:
        self.sec.append(sec)
        self.col.append(np.full(sec.shape, j, dtype=np.int64))
        self.n.append(n)
        self.lo.append(lo)
        self.hi.append(hi)
        self.sm.append(sm)


def _raw_seconds(session: Session, machine_pk: int, t0_s: int, t1_s: int,
                 col: dict[str, int] | None, recs: _Records) -> set[str]:
    """Add per-second raw records in [t0_s, t1_s) (channels in ``col``, or all: their names are
    then added to ``col``). Returns the raw channel names seen."""
    seen: set[str] = set()
    for agg in read_second_aggregates(session, machine_pk, t0_s, t1_s):
        inside = (agg.sec >= t0_s) & (agg.sec < t1_s)
        for js, ch in enumerate(agg.channels):
            seen.add(ch)
            if col is None or ch not in col:
                continue
            keep = inside & (agg.count[:, js] > 0)
            if keep.any():
                recs.add(agg.sec[keep], col[ch], agg.count[keep, js], agg.min[keep, js],
                         agg.max[keep, js], agg.sum[keep, js])
    return seen


def _minute_from_seconds(session: Session, machine_pk: int, minute_s: int,
                         corrupt: list[int] | None = None) -> dict[str, Agg]:
    """Exact 1-min aggregates of the raw channels, computed from the blocks' per-second ones
    (rows whose summary cannot be decoded are skipped, their ids appended to ``corrupt``)."""
    recs = _Records.empty()
    names: dict[str, int] = {}
    for agg in read_second_aggregates(session, machine_pk, minute_s, minute_s + MINUTE, corrupt):
        for ch in agg.channels:
            names.setdefault(ch, len(names))
    _raw_seconds(session, machine_pk, minute_s, minute_s + MINUTE, names, recs)
    out: dict[str, Agg] = {}
    if not recs.sec:
        return out
    col, n = np.concatenate(recs.col), np.concatenate(recs.n)
    lo, hi, sm = np.concatenate(recs.lo), np.concatenate(recs.hi), np.concatenate(recs.sm)
    for ch, j in names.items():
        sel = col == j
        if sel.any():
            out[ch] = [int(n[sel].sum()), float(lo[sel].min()), float(hi[sel].max()),
                       float(sm[sel].sum())]
    return out


@dataclass(frozen=True)
class RollupCounts:
    """What one :func:`rollup` did.

    Attributes:
        rolled: Machine-minutes whose 1-min raw summaries were recomputed.
        skipped: Machine-minutes that could not be rolled up: logged and dropped from
            ``summary_dirty`` (their stored 1-min rows stay as they were).
        corrupt: Block rows whose per-second summary could not be decoded (left out of their
            minute, logged).
    """

    rolled: int
    skipped: int
    corrupt: int


_UPSERT = ("ON CONFLICT (machine_pk, channel, level_s, bucket_s) DO UPDATE SET "
           "n = excluded.n, vmin = excluded.vmin, vmax = excluded.vmax, vsum = excluded.vsum")
_SUMMARY_COLUMNS = ("machine_pk", "channel", "level_s", "bucket_s", "n", "vmin", "vmax", "vsum")

Dirty = tuple[int, int, int]  # machine_pk, minute_s, version


def _write_minutes(factory: Callable[[], Session], done: Sequence[tuple[Dirty, dict[str, Agg]]],
                   dropped: Sequence[Dirty]) -> None:
    """One transaction: upsert the recomputed minutes, delete their marks and those of
    ``dropped`` (each only if its version is unchanged: a block that arrived meanwhile keeps
    its minute dirty)."""
    with factory() as s, s.begin():
        rows = [(pk, ch, MINUTE, minute, a[0], a[1], a[2], a[3])
                for (pk, minute, _), aggs in done for ch, a in aggs.items()]
        bulk.insert_rows(s.connection(), SummaryRow.__tablename__, _SUMMARY_COLUMNS, rows,
                         _UPSERT)
        for pk, minute, version in [d for d, _ in done] + list(dropped):
            s.execute(delete(DirtyMinute).where(
                DirtyMinute.machine_pk == pk, DirtyMinute.minute_s == minute,
                DirtyMinute.version == version))


def rollup(factory: Callable[[], Session], before_s: float | None = None) -> RollupCounts:
    """Recompute stale 1-min raw summaries (minutes ending at or before ``before_s``, or all).

    Never stops at one bad row: a block row whose summary cannot be decoded is left out of its
    minute (logged, counted); a minute that cannot be computed or whose write the database
    rejects is logged, counted and dropped from ``summary_dirty`` while the others roll up.
    Reads in one transaction, writes in another (per minute only if the batch write is
    rejected).

    Raises:
        StorageUnavailableError: The database is unavailable; nothing was written.
        StorageError: Another database failure.
    """
    stmt = select(DirtyMinute.machine_pk, DirtyMinute.minute_s, DirtyMinute.version)
    if before_s is not None:
        stmt = stmt.where(DirtyMinute.minute_s + MINUTE <= before_s)
    done: list[tuple[Dirty, dict[str, Agg]]] = []
    dropped: list[Dirty] = []
    corrupt: list[int] = []
    try:
        with factory() as s:
            dirty = [(int(a), int(b), int(c)) for a, b, c in s.execute(stmt).all()]
            for d in dirty:
                pk, minute, _ = d
                try:
                    done.append((d, _minute_from_seconds(s, pk, minute, corrupt)))
                except SQLAlchemyError as exc:
                    if is_unavailable(exc):
                        raise
                    s.rollback()  # PostgreSQL: the failed statement aborted the transaction
                    log.warning("rollup: machine pk %d minute %d s cannot be rolled up, dropped "
                                "from summary_dirty: %s", pk, minute, exc)
                    dropped.append(d)
                except Exception as exc:  # one bad minute must not stop the others
                    log.warning("rollup: machine pk %d minute %d s cannot be rolled up, dropped "
                                "from summary_dirty: %r", pk, minute, exc)
                    dropped.append(d)
        if not done and not dropped:
            return RollupCounts(0, 0, len(set(corrupt)))
        try:
            _write_minutes(factory, done, dropped)
        except (SQLAlchemyError, OverflowError) as exc:
            if is_unavailable(exc):
                raise
            log.warning("rollup: batch write of %d minute(s) rejected (%s); writing them one by "
                        "one", len(done), str(exc).splitlines()[0])
            kept = []
            for d, aggs in done:
                try:
                    _write_minutes(factory, [(d, aggs)], [])
                    kept.append(d)
                except (SQLAlchemyError, OverflowError) as one:
                    if is_unavailable(one):
                        raise
                    log.warning("rollup: machine pk %d minute %d s rejected by the database, "
                                "dropped from summary_dirty: %s", d[0], d[1],
                                str(one).splitlines()[0])
                    dropped.append(d)
            done = [(d, a) for d, a in done if d in kept]
            _write_minutes(factory, [], dropped)
    except SQLAlchemyError as exc:
        if is_unavailable(exc):
            raise unavailable("summary rollup", exc) from exc
        raise StorageError(f"summary rollup failed: {exc}") from exc
    return RollupCounts(len(done), len(dropped), len(set(corrupt)))


def _buckets(t_ns: npt.NDArray[np.int64], values: F64,
             level: int) -> tuple[list[int], npt.NDArray[np.int64], F64, F64, F64]:
    """Aggregates of samples ``t_ns`` (n,) [ns], ``values`` (n, c) over the buckets of
    ``level`` [s] they touch (NaN samples skipped): bucket starts (m,) [s], and counts, minima,
    maxima and sums, each (m, c); a bucket-channel without samples has count 0."""
    ok = ~np.isnan(values)
    bucket = (t_ns // (level * SEC)) * level
    starts = np.concatenate(([0], np.flatnonzero(np.diff(bucket)) + 1))
    return (bucket[starts].tolist(), np.add.reduceat(ok.astype(np.int64), starts, axis=0),
            np.minimum.reduceat(np.where(ok, values, np.inf), starts, axis=0),
            np.maximum.reduceat(np.where(ok, values, -np.inf), starts, axis=0),
            np.add.reduceat(np.where(ok, values, 0.0), starts, axis=0))


def accumulate(acc: dict[Key, Agg], channels: Sequence[str], t_ns: npt.NDArray[np.int64],
               values: F64) -> None:
    """Add samples to in-memory 1-s and 1-min bucket aggregates (NaN samples are skipped).

    Args:
        acc: Aggregates to update, keyed (channel, level_s, bucket_s).
        channels: Channel names, length c.
        t_ns: Sample times, shape (n,), non-decreasing [ns].
        values: Shape (n, c) [channel units]; NaN = missing.
    """
    if t_ns.size == 0:
        return
    for level in LEVELS_S:
        buckets, cnts, mins, maxs, sums = _buckets(t_ns, values, level)
        for i, b in enumerate(buckets):
            for j, ch in enumerate(channels):
                if cnts[i, j] > 0:
                    acc[(ch, level, b)] = [int(cnts[i, j]), float(mins[i, j]),
                                           float(maxs[i, j]), float(sums[i, j])]


_COLUMNS = ("machine_pk", "channel", "level_s", "bucket_s", "n", "vmin", "vmax", "vsum")


def _second_rows(machine_pk: int, channels: Sequence[str], t_ns: npt.NDArray[np.int64],
                 values: F64) -> list[tuple[int, str, int, int, int, float, float, float]]:
    """The 1-s bucket rows (``_COLUMNS`` order) of samples ``t_ns`` (n,) [ns], ``values``
    (n, c): :func:`_buckets` at level 1, the rows built column-wise (a span of a minute is
    ≈ 10³ rows)."""
    buckets, cnts, mins, maxs, sums = _buckets(t_ns, values, 1)
    bi, ci = np.nonzero(cnts > 0)
    b = [buckets[i] for i in bi.tolist()]
    names = [channels[j] for j in ci.tolist()]
    return list(zip([machine_pk] * len(b), names, [1] * len(b), b,
                    cnts[bi, ci].tolist(), mins[bi, ci].tolist(), maxs[bi, ci].tolist(),
                    sums[bi, ci].tolist(), strict=True))


_PG_DELETE = ("DELETE FROM summaries WHERE machine_pk = %s AND channel = ANY(%s) AND "
              "((level_s = 1 AND bucket_s BETWEEN %s AND %s) OR "
              f"(level_s = {MINUTE} AND bucket_s >= %s AND bucket_s < %s))")
_PG_MINUTES = ("INSERT INTO summaries (machine_pk, channel, level_s, bucket_s, n, vmin, vmax, "
               f"vsum) SELECT machine_pk, channel, {MINUTE}, (bucket_s / {MINUTE}) * {MINUTE} "
               "AS minute, sum(n), min(vmin), max(vmax), sum(vsum) FROM summaries "
               "WHERE machine_pk = %s AND channel = ANY(%s) AND level_s = 1 AND bucket_s >= %s "
               "AND bucket_s < %s GROUP BY machine_pk, channel, minute")


def replace(session: Session, machine_pk: int, channels: Sequence[str],
            t_ns: npt.NDArray[np.int64], values: F64) -> int:
    """Store aggregates of derived channels: the 1-s buckets that ``t_ns`` touches are
    overwritten, then every 1-min bucket those seconds fall in is recomputed from all its 1-s
    buckets (so consecutive windows build up whole minutes, and re-running a window changes
    nothing). Windows should start and end on whole seconds: a partly covered second at either
    end holds only what this call saw.

    Returns:
        Number of 1-s bucket rows written.
    """
    from cranetwin.storage.bulk import insert_rows

    rows = _second_rows(machine_pk, channels, t_ns, values)
    lo = int(t_ns[0] // SEC)
    hi = int(t_ns[-1] // SEC)
    chans = list(channels)
    m_lo, m_hi = (lo // MINUTE) * MINUTE, (hi // MINUTE) * MINUTE + MINUTE
    conn = session.connection()
    if conn.dialect.name == "postgresql":  # fixed statements, no SQL built per window
        conn.exec_driver_sql(_PG_DELETE, (machine_pk, chans, lo, hi, m_lo, m_hi))
        insert_rows(conn, "summaries", _COLUMNS, rows)
        conn.exec_driver_sql(_PG_MINUTES, (machine_pk, chans, m_lo, m_hi))
        return len(rows)
    t = SummaryRow
    session.execute(delete(t).where(t.machine_pk == machine_pk, t.channel.in_(chans),
                                    t.level_s == 1, t.bucket_s.between(lo, hi)))
    insert_rows(conn, "summaries", _COLUMNS, rows)
    session.execute(delete(t).where(t.machine_pk == machine_pk, t.channel.in_(chans),
                                    t.level_s == MINUTE, t.bucket_s >= m_lo,
                                    t.bucket_s < m_hi))
    minute = ((t.bucket_s // MINUTE) * MINUTE).label("minute")
    agg = (select(t.machine_pk, t.channel, literal(MINUTE), minute, func.sum(t.n),
                  func.min(t.vmin), func.max(t.vmax), func.sum(t.vsum))
           .where(t.machine_pk == machine_pk, t.channel.in_(chans), t.level_s == 1,
                  t.bucket_s >= m_lo, t.bucket_s < m_hi)
           .group_by(t.machine_pk, t.channel, minute))
    session.execute(insert(t).from_select(
        ["machine_pk", "channel", "level_s", "bucket_s", "n", "vmin", "vmax", "vsum"], agg))
    return len(rows)


_PG_DELETE_MANY = (
    "DELETE FROM summaries s USING unnest(%s::integer[], %s::bigint[], %s::bigint[], "
    "%s::bigint[], %s::bigint[]) AS r(pk, lo, hi, m_lo, m_hi) WHERE s.machine_pk = r.pk AND "
    "s.channel = ANY(%s) AND ((s.level_s = 1 AND s.bucket_s BETWEEN r.lo AND r.hi) OR "
    f"(s.level_s = {MINUTE} AND s.bucket_s >= r.m_lo AND s.bucket_s < r.m_hi))")
_PG_MINUTES_MANY = (
    "INSERT INTO summaries (machine_pk, channel, level_s, bucket_s, n, vmin, vmax, vsum) "
    f"SELECT s.machine_pk, s.channel, {MINUTE}, (s.bucket_s / {MINUTE}) * {MINUTE} AS minute, "
    "sum(s.n), min(s.vmin), max(s.vmax), sum(s.vsum ORDER BY s.bucket_s) FROM summaries s "
    "JOIN unnest("
    "%s::integer[], %s::bigint[], %s::bigint[]) AS r(pk, m_lo, m_hi) ON s.machine_pk = r.pk "
    "AND s.bucket_s >= r.m_lo AND s.bucket_s < r.m_hi WHERE s.channel = ANY(%s) AND "
    "s.level_s = 1 GROUP BY s.machine_pk, s.channel, minute")


def replace_many(session: Session, channels: Sequence[str],
                 spans: Sequence[tuple[int, npt.NDArray[np.int64], F64]]) -> int:
    """:func:`replace` of several spans (of one or several machines, the same derived
    channels) in three statements on PostgreSQL (one :func:`replace` per span elsewhere).
    A minute's sum adds its seconds in time order, as :func:`replace`'s index scan does (the
    same float8 sum to the last bit).

    Args:
        channels: Channel names, length c.
        spans: (machine primary key, sample times (n,) [ns], values (n, c)) per span; the
            spans of one machine do not overlap (their 1-s buckets are distinct).

    Returns:
        Number of 1-s bucket rows written.
    """
    from cranetwin.storage.bulk import insert_rows

    spans = [sp for sp in spans if sp[1].size]
    conn = session.connection()
    if conn.dialect.name != "postgresql":
        return sum(replace(session, pk, channels, t_ns, v) for pk, t_ns, v in spans)
    if not spans:
        return 0
    rows: list[tuple[int, str, int, int, int, float, float, float]] = []
    pk_r: list[int] = []
    lo_r: list[int] = []
    hi_r: list[int] = []
    mlo_r: list[int] = []
    mhi_r: list[int] = []
    minutes: dict[int, list[tuple[int, int]]] = {}
    for pk, t_ns, values in spans:
        rows += _second_rows(pk, channels, t_ns, values)
        lo, hi = int(t_ns[0] // SEC), int(t_ns[-1] // SEC)
        m_lo, m_hi = (lo // MINUTE) * MINUTE, (hi // MINUTE) * MINUTE + MINUTE
        for col, v in zip((pk_r, lo_r, hi_r, mlo_r, mhi_r), (pk, lo, hi, m_lo, m_hi),
                          strict=True):
            col.append(v)
        minutes.setdefault(pk, []).append((m_lo, m_hi))
    chans = list(channels)
    conn.exec_driver_sql(_PG_DELETE_MANY, (pk_r, lo_r, hi_r, mlo_r, mhi_r, chans))
    insert_rows(conn, "summaries", _COLUMNS, rows)
    m_pk: list[int] = []
    m_lo_r: list[int] = []
    m_hi_r: list[int] = []
    for pk, ranges in minutes.items():  # each minute recomputed once: ranges merged
        merged: list[list[int]] = []
        for a, z in sorted(ranges):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], z)
            else:
                merged.append([a, z])
        for a, z in merged:
            m_pk.append(pk)
            m_lo_r.append(a)
            m_hi_r.append(z)
    conn.exec_driver_sql(_PG_MINUTES_MANY, (m_pk, m_lo_r, m_hi_r, chans))
    return len(rows)


@dataclass(frozen=True)
class Summaries:
    """Bucketed min/max/mean of some channels of one machine.

    Attributes:
        machine_id: Machine identifier.
        bucket_s: Bucket width [s] (1, 60 or a multiple of either).
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

    Raises:
        StorageError: ``max_points < 1`` or an empty range.
    """
    if max_points < 1:
        raise StorageError(f"max_points must be ≥ 1, got {max_points}")
    if not t1_s > t0_s:
        raise StorageError(f"empty time range [{t0_s}, {t1_s}); expected t1 > t0")
    level = 1 if (t1_s - t0_s) <= max_points else MINUTE
    width = level * max(1, math.ceil((t1_s - t0_s) / (level * max_points)))
    while True:
        origin = math.floor(t0_s / width) * width
        if math.ceil((t1_s - origin) / width) <= max_points:
            return level, width, origin
        width += level



def _stored_rows(session: Session, machine_pk: int, level: int, chans: tuple[str, ...],
                 col: dict[str, int], origin: int, end: int, stale: dict[int, set[str]],
                 recs: _Records) -> None:
    """Add the stored ``level`` rows of ``chans`` in [origin, end) to ``recs``, one channel per
    query, fetched as plain column tuples (Core, no ORM rows) straight into numpy arrays.

    Rows of a minute in ``stale`` whose channel was recomputed from the blocks are skipped.
    """
    t = SummaryRow.__table__.c
    conn = session.connection()
    for ch in dict.fromkeys(chans):  # each channel once (a repeated name fills its last column)
        stmt = (select(t.bucket_s, t.n, t.vmin, t.vmax, t.vsum)
                .where(t.machine_pk == machine_pk, t.level_s == level, t.channel == ch,
                       t.bucket_s >= origin, t.bucket_s < end))
        rows = conn.execute(stmt).fetchall()
        if not rows:
            continue
        b, n, lo, hi, sm = zip(*rows, strict=True)
        sec = np.fromiter(b, dtype=np.int64, count=len(rows))
        cnt = np.fromiter(n, dtype=np.int64, count=len(rows))
        vlo = np.fromiter(lo, dtype=np.float64, count=len(rows))
        vhi = np.fromiter(hi, dtype=np.float64, count=len(rows))
        vsm = np.fromiter(sm, dtype=np.float64, count=len(rows))
        skip = [m for m, names in stale.items() if ch in names]
        if skip:  # superseded by the on-the-fly recomputation from the blocks
            keep = ~np.isin(sec, np.asarray(skip, dtype=np.int64))
            sec, cnt, vlo, vhi, vsm = sec[keep], cnt[keep], vlo[keep], vhi[keep], vsm[keep]
        recs.add(sec, col[ch], cnt, vlo, vhi, vsm)

def query(session: Session, machine_pk: int, machine_id: str, channels: Iterable[str],
          t0_s: float, t1_s: float, max_points: int) -> Summaries:
    """Bucketed aggregates over the bucket grid covering [t0_s, t1_s) (whole buckets)."""
    chans = tuple(channels)
    col = {c: j for j, c in enumerate(chans)}
    level, width, origin = choose_width(t0_s, t1_s, max_points)
    m = math.ceil((t1_s - origin) / width)
    end = origin + m * width
    recs = _Records.empty()
    stale: dict[int, set[str]] = {}  # dirty minute → raw channels recomputed for it
    if level == 1:
        _raw_seconds(session, machine_pk, origin, end, col, recs)
    else:
        dirty = session.scalars(select(DirtyMinute.minute_s).where(
            DirtyMinute.machine_pk == machine_pk, DirtyMinute.minute_s >= origin,
            DirtyMinute.minute_s < end)).all()
        for minute in dirty:
            aggs = _minute_from_seconds(session, machine_pk, int(minute))
            stale[int(minute)] = set(aggs)
            for ch, a in aggs.items():
                if ch in col:
                    recs.add(np.array([minute], dtype=np.int64), col[ch],
                             np.array([a[0]], dtype=np.int64), np.array([a[1]]),
                             np.array([a[2]]), np.array([a[3]]))
    _stored_rows(session, machine_pk, level, chans, col, origin, end, stale, recs)
    shape = (m, len(chans))
    vmin, vmax = np.full(shape, np.inf), np.full(shape, -np.inf)
    vsum, count = np.zeros(shape), np.zeros(shape, dtype=np.int64)
    if recs.sec:
        g = (np.concatenate(recs.sec) - origin) // width
        j = np.concatenate(recs.col)
        np.add.at(count, (g, j), np.concatenate(recs.n))
        np.minimum.at(vmin, (g, j), np.concatenate(recs.lo))
        np.maximum.at(vmax, (g, j), np.concatenate(recs.hi))
        np.add.at(vsum, (g, j), np.concatenate(recs.sm))
    has = count > 0
    mean = np.where(has, vsum / np.maximum(count, 1), np.nan)
    vmin[~has] = np.nan
    vmax[~has] = np.nan
    t = origin + width * np.arange(m, dtype=np.float64)
    return Summaries(machine_id, width, t, chans, vmin, vmax, mean, count)
