"""Time partitions of ``sample_blocks`` on PostgreSQL: creation ahead and on demand, retention.

On PostgreSQL (revision ``0004p``) ``sample_blocks`` is a declaratively partitioned table,
``PARTITION BY RANGE (t_start_ns)``: one partition per UTC day, ISO week (from Monday) or
calendar month of block start times, named ``sample_blocks_pYYYYMMDD`` after the day it starts,
over [0, :data:`~cranetwin.storage.blocks.T_LIMIT_NS`). Rows outside that range (stored before
the write path checked times; no writer stores them now) live in ``sample_blocks_default``,
whose CHECK constraint keeps every other row out of it (and spares PostgreSQL a scan of it when
a partition is created).
The interval in force is recorded in the table's comment (``cranetwin partition interval:
month``); :func:`set_interval` changes it for partitions created from then on (existing ones
keep their range; a new one is clipped to the gap between its neighbours, so ranges never
overlap). SQLite keeps one plain table and nothing here applies to it.

Partitions are created

* on demand by every writer (:class:`Partitioner`, called by
  :meth:`cranetwin.storage.Store.write_batch` before it inserts): a block whose start time falls
  in no partition gets one first, in its own short transaction serialised by an advisory lock,
  so a backfill of old data never fails for want of a partition;
* ahead of time by :func:`maintain` (the twin worker calls it periodically): the current
  interval and ``ahead`` more, so the hot path normally finds its partition made.

Retention (:func:`drop_expired`) drops whole partitions whose range ended more than
``keep_days`` ago, except a partition that still holds samples analytics has not processed: a
block of a machine with no twin-worker watermark, or ending after the watermark minus the
replay margin (the next window's replay still reads it), or a minute marked for the 1-min
summary rollup. Such a partition is kept and reported, and dropped by a later call once the
worker has passed it. Dropping is ``DROP TABLE`` of the partition: instant, no dead tuples.
The known payload runs stored with those samples (``payload_runs``, not partitioned) go in the
same transaction: every run that starts in the dropped partition's range, whole — the rule of
the sample blocks (a block lives in the partition of its start, and one reaching past the
partition's end goes with it), so a run the importer stored for a block goes with that block.
The same transaction raises every machine's late-data version
(:func:`cranetwin.storage.late_version.bump_all`): a replay cached for a dropped window is not
served again.

The unique key is (machine_pk, epoch, seq, t_start_ns): PostgreSQL requires the partition column
in every unique key. A retransmitted block carries the same seq and the same t_start, so it still
conflicts with the stored copy and is counted a duplicate; a reused seq with another start time
is found by the writer's key probe (:func:`cranetwin.storage.blocks.probe`), which searches every
partition for the (machine, epoch, seq).
"""

from __future__ import annotations

import calendar
import datetime as dt
import logging
import re
import threading
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal, cast, get_args

from sqlalchemy import Connection, Engine

from cranetwin.errors import StorageError
from cranetwin.storage.blocks import MAX_SPAN_NS, T_LIMIT_NS

log = logging.getLogger(__name__)

Interval = Literal["day", "week", "month"]
INTERVALS: tuple[str, ...] = get_args(Interval)
DEFAULT_INTERVAL: Interval = "month"
PARENT = "sample_blocks"
SEC = 1_000_000_000
DAY_NS = 86_400 * SEC
INT63 = 2**63 - 1
_COMMENT = "cranetwin partition interval: "
_BOUND = re.compile(r"FROM \('?(-?\d+|MINVALUE)'?\) TO \('?(-?\d+|MAXVALUE)'?\)")
LOCK_TIMEOUT = "5s"
"""How long creating or dropping a partition waits for the parent table's lock."""


def _day(t_ns: int) -> dt.date:
    return dt.date(1970, 1, 1) + dt.timedelta(days=t_ns // DAY_NS)


def _ns(d: dt.date) -> int:
    return (d - dt.date(1970, 1, 1)).days * DAY_NS


def aligned(t_ns: int, interval: Interval) -> tuple[int, int]:
    """The [lo, hi) range [ns] of ``interval`` (UTC day, ISO week from Monday, calendar month)
    that holds ``t_ns`` (0 ≤ t_ns < :data:`~cranetwin.storage.blocks.T_LIMIT_NS`); hi is
    capped at that limit (times past it belong to the default partition)."""
    d = _day(t_ns)
    if interval == "day":
        lo, hi = d, d + dt.timedelta(days=1)
    elif interval == "week":
        lo = d - dt.timedelta(days=d.weekday())
        hi = lo + dt.timedelta(days=7)
    elif interval == "month":
        lo = d.replace(day=1)
        hi = lo + dt.timedelta(days=calendar.monthrange(lo.year, lo.month)[1])
    else:
        raise StorageError(f"partition interval {interval!r}; expected one of {INTERVALS}")
    return _ns(lo), min(_ns(hi), T_LIMIT_NS)


def name_of(lo_ns: int) -> str:
    """Name of the partition starting at ``lo_ns``: ``sample_blocks_pYYYYMMDD``."""
    return f"{PARENT}_p{_day(lo_ns):%Y%m%d}"


@dataclass(frozen=True, order=True)
class Partition:
    """One partition: rows with lo_ns ≤ t_start_ns < hi_ns."""

    lo_ns: int
    hi_ns: int
    name: str


def is_partitioned(conn: Connection) -> bool:
    """Whether ``sample_blocks`` is a partitioned table here (PostgreSQL at ``0004p``)."""
    if conn.dialect.name != "postgresql":
        return False
    kind = conn.exec_driver_sql(
        "SELECT c.relkind FROM pg_class c WHERE c.oid = to_regclass(%s)", (PARENT,)).scalar()
    return kind == "p"


def list_partitions(conn: Connection) -> list[Partition]:
    """The partitions of ``sample_blocks``, ordered by range."""
    rows = conn.exec_driver_sql(
        "SELECT c.relname, pg_get_expr(c.relpartbound, c.oid) FROM pg_inherits i "
        "JOIN pg_class c ON c.oid = i.inhrelid WHERE i.inhparent = to_regclass(%s)",
        (PARENT,)).all()
    out = []
    for name, bound in rows:
        if str(bound) == "DEFAULT":
            continue
        m = _BOUND.search(str(bound))
        if m is None:
            raise StorageError(f"partition {name} of {PARENT} has an unexpected bound {bound}")
        lo = 0 if m[1] == "MINVALUE" else int(m[1])
        hi = INT63 if m[2] == "MAXVALUE" else int(m[2])
        out.append(Partition(lo, hi, str(name)))
    return sorted(out)


def get_interval(conn: Connection) -> Interval:
    """The interval recorded in the table's comment (default :data:`DEFAULT_INTERVAL`)."""
    c = conn.exec_driver_sql("SELECT obj_description(to_regclass(%s), 'pg_class')",
                             (PARENT,)).scalar()
    if isinstance(c, str) and c.startswith(_COMMENT) and c[len(_COMMENT):] in INTERVALS:
        return cast(Interval, c[len(_COMMENT):])
    return DEFAULT_INTERVAL


def set_interval(conn: Connection, interval: str) -> None:
    """Record ``interval`` for partitions created from now on (existing ones keep theirs)."""
    if interval not in INTERVALS:
        raise StorageError(f"partition interval {interval!r}; expected one of {INTERVALS}")
    conn.exec_driver_sql(f"COMMENT ON TABLE {PARENT} IS '{_COMMENT}{interval}'")


def _lock_key(conn: Connection) -> int:
    """Advisory-lock key serialising partition changes of this schema's table."""
    schema = conn.exec_driver_sql("SELECT current_schema()").scalar()
    return zlib.crc32(f"cranetwin.partitions:{schema}".encode()) & 0x7FFF_FFFF


def _covering(parts: list[Partition], t_ns: int) -> Partition | None:
    for p in parts:
        if p.lo_ns <= t_ns < p.hi_ns:
            return p
    return None


def _new_range(parts: list[Partition], t_ns: int, interval: Interval) -> tuple[int, int]:
    """The aligned range around ``t_ns``, clipped to the gap between existing partitions."""
    lo, hi = aligned(t_ns, interval)
    for p in parts:
        if p.hi_ns <= t_ns:
            lo = max(lo, p.hi_ns)
        elif p.lo_ns > t_ns:
            hi = min(hi, p.lo_ns)
    return lo, hi


def create_covering(conn: Connection, times_ns: Iterable[int],
                    interval: Interval | None = None) -> list[Partition]:
    """Create the partitions missing for block start times ``times_ns`` (those in
    [0, :data:`~cranetwin.storage.blocks.T_LIMIT_NS`); others are ignored), inside the caller's
    transaction (which should commit soon: it holds the parent's lock until then).

    Returns:
        Every partition after the call.
    """
    conn.exec_driver_sql("SELECT pg_advisory_xact_lock(%s)", (_lock_key(conn),))
    conn.exec_driver_sql(f"SET LOCAL lock_timeout = '{LOCK_TIMEOUT}'")
    parts = list_partitions(conn)
    iv = interval if interval is not None else get_interval(conn)
    for t in sorted(set(times_ns)):
        if not 0 <= t < T_LIMIT_NS or _covering(parts, t) is not None:
            continue
        lo, hi = _new_range(parts, t, iv)
        name = name_of(lo)
        conn.exec_driver_sql(f'CREATE TABLE "{name}" PARTITION OF {PARENT} '
                             f"FOR VALUES FROM ({lo}) TO ({hi})")
        log.info("created partition %s [%s, %s)", name, _day(lo), _day(hi))
        parts = sorted([*parts, Partition(lo, hi, name)])
    return parts


DEFAULT_PARTITION = f"{PARENT}_default"
NO_PARTITION = ("no partition of relation", f'relation "{DEFAULT_PARTITION}" violates check')
"""Texts of the database errors of a row whose time partition does not exist."""


def create_default(conn: Connection) -> None:
    """Create the default partition for rows outside [0, T_LIMIT_NS) (migration)."""
    conn.exec_driver_sql(
        f'CREATE TABLE "{DEFAULT_PARTITION}" PARTITION OF {PARENT} DEFAULT')
    conn.exec_driver_sql(
        f'ALTER TABLE "{DEFAULT_PARTITION}" ADD CONSTRAINT ck_{DEFAULT_PARTITION}_outside '
        f"CHECK (t_start_ns < 0 OR t_start_ns >= {T_LIMIT_NS})")


@dataclass
class Partitioner:
    """A writer's cache of the partitions that exist, creating the missing ones on demand.

    Thread-safe; one per :class:`~cranetwin.storage.Store`. A partition dropped by retention
    elsewhere stays in the cache: a block written into its range fails with "no partition",
    and :meth:`forget` (the store calls it then) makes the next call create it again.
    """

    engine: Engine
    _parts: list[Partition] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def ensure(self, times_ns: Iterable[int]) -> int:
        """Make sure a partition exists for every block start time in ``times_ns`` (times
        outside [0, :data:`~cranetwin.storage.blocks.T_LIMIT_NS`) are ignored: such blocks are
        refused anyway); returns how many were created (0 on the usual call, which touches no
        database)."""
        with self._lock:
            missing = [t for t in set(times_ns)
                       if 0 <= t < T_LIMIT_NS and _covering(self._parts, t) is None]
            if not missing:
                return 0
            with self.engine.connect() as conn:  # read only: made ahead by another process?
                self._parts = list_partitions(conn)
            missing = [t for t in missing if _covering(self._parts, t) is None]
            if not missing:
                return 0
            before = len(self._parts)
            with self.engine.begin() as conn:
                self._parts = create_covering(conn, missing)
            return max(0, len(self._parts) - before)

    def forget(self) -> None:
        """Drop the cache (the next :meth:`ensure` re-reads the partitions)."""
        with self._lock:
            self._parts = []


@dataclass(frozen=True)
class RetentionResult:
    """What :func:`drop_expired` did.

    Attributes:
        dropped: Names of the partitions dropped.
        kept: (name, why) of expired partitions kept because analytics has not processed them.
        payload_runs: Known payload runs deleted with the dropped partitions (those starting
            in their ranges, :func:`cranetwin.storage.payloads.drop_starting_in`).
    """

    dropped: list[str]
    kept: list[tuple[str, str]]
    payload_runs: int = 0


def _unprocessed(conn: Connection, p: Partition, margin_s: float) -> str | None:
    """Why partition ``p`` may not be dropped yet, or None."""
    row = conn.exec_driver_sql(  # one index probe (machine, t_end) per machine
        "SELECT m.machine_id, p.watermark_s FROM machines m "
        "LEFT JOIN twin_progress p ON p.machine_id = m.machine_id "
        f'CROSS JOIN LATERAL (SELECT max(b.t_end_ns) AS t FROM "{p.name}" b '
        "WHERE b.machine_pk = m.id) x "
        "WHERE x.t IS NOT NULL AND (p.watermark_s IS NULL "
        "OR x.t >= ((p.watermark_s - %s) * 1000000000.0)::bigint) LIMIT 1",
        (float(margin_s),)).first()
    if row is not None:
        wm = "no twin-worker progress" if row[1] is None else f"watermark {row[1]:.0f} s"
        return f"machine {row[0]} has samples not yet processed ({wm})"
    dirty = conn.exec_driver_sql(
        "SELECT count(*) FROM summary_dirty WHERE minute_s >= %s AND minute_s < %s",
        (p.lo_ns // SEC - 60, min(INT63, p.hi_ns + MAX_SPAN_NS) // SEC)).scalar()
    if dirty:
        return f"{dirty} minute(s) wait for the 1-min summary rollup"
    return None


def drop_expired(engine: Engine, keep_days: float, now_s: float,
                 margin_s: float = 0.0) -> RetentionResult:
    """Drop the partitions whose range ended more than ``keep_days`` before ``now_s`` and whose
    samples analytics has processed (see the module docstring).

    Args:
        engine: PostgreSQL engine (SQLite: nothing is dropped).
        keep_days: Retention [days] (> 0).
        now_s: Current time [s since the epoch].
        margin_s: Replay margin of the twin worker (``twin_margin_s``) [s].
    """
    if keep_days <= 0:
        raise StorageError(f"retention of {keep_days} days; expected > 0")
    cutoff = int((now_s - keep_days * 86400.0) * SEC)
    from cranetwin.storage import late_version
    from cranetwin.storage.payloads import drop_starting_in

    dropped: list[str] = []
    kept: list[tuple[str, str]] = []
    runs = 0
    with engine.begin() as conn:
        if not is_partitioned(conn):
            return RetentionResult([], [])
        conn.exec_driver_sql("SELECT pg_advisory_xact_lock(%s)", (_lock_key(conn),))
        conn.exec_driver_sql(f"SET LOCAL lock_timeout = '{LOCK_TIMEOUT}'")
        has_payload = conn.exec_driver_sql(
            "SELECT to_regclass('payload_runs') IS NOT NULL").scalar()
        for p in list_partitions(conn):
            if p.hi_ns > cutoff:
                continue
            why = _unprocessed(conn, p, margin_s)
            if why is not None:
                kept.append((p.name, why))
                log.warning("retention: partition %s kept: %s", p.name, why)
                continue
            conn.exec_driver_sql(f'DROP TABLE "{p.name}"')
            n = drop_starting_in(conn, p.lo_ns, p.hi_ns) if has_payload else 0
            runs += n
            dropped.append(p.name)
            log.info("retention: dropped partition %s (and %d known payload run(s))", p.name, n)
        if dropped:  # a replay kept for a window of theirs is stale: in this transaction
            late_version.bump_all(conn)
    return RetentionResult(dropped, kept, runs)


def maintain(engine: Engine, now_s: float, *, ahead: int = 2, interval: str | None = None,
             keep_days: float | None = None, margin_s: float = 0.0) -> RetentionResult:
    """Periodic upkeep: record ``interval`` (when given), create the partitions of the current
    interval and ``ahead`` more, and apply retention when ``keep_days`` is set. A no-op on
    SQLite."""
    with engine.begin() as conn:
        if not is_partitioned(conn):
            return RetentionResult([], [])
        if interval is not None and interval != get_interval(conn):
            set_interval(conn, interval)
        iv = get_interval(conn)
        t = int(now_s * SEC)
        times = []
        for _ in range(ahead + 1):
            times.append(t)
            t = aligned(t, iv)[1]
        create_covering(conn, times, iv)
    if keep_days is None:
        return RetentionResult([], [])
    return drop_expired(engine, keep_days, now_s, margin_s)
