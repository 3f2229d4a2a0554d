"""A known payload as a stored time series: ``payload_runs``.

A user's recording may weigh the load (a load cell; the import mapping's ``[payload]`` column,
docs/IMPORT.md). The series is stored per machine as *runs*, like the samples: one row holds
``n`` values at the regular times ``t_start_ns + k · period_ns`` (k = 0 … n − 1), as float64
little-endian compressed with zlib; NaN = not known at that time. The importer writes one run
per stored sample block, at exactly the block's sample times, so the series read back for a
range is the file's series at the stored samples (NaN included) and costs one row per block,
not one per sample.

Rows are keyed by (machine, t_start_ns) and inserted with ``ON CONFLICT DO NOTHING`` on both
dialects: writing the same run twice (importing the same file again) stores it once. A run
whose key is stored with other values is not overwritten (the first stays; the write counts
it as ``differing``). Runs written by different calls may overlap in time; a read then gives
each time once, from the run that starts earliest.

Deleting (:func:`delete_range`, ``cranetwin payload delete``) removes the values of a time
range, cutting a run that straddles a bound; the store records the changed times for the twin
worker in the same transaction (:mod:`cranetwin.storage.redo`), as it does for runs newly
stored. A run newly stored or deleted whole (:func:`delete`) changes the read series anywhere in
its span, not only where it is known: its NaN values hide (or, deleted, reveal) the values of a
later-starting run over the same times, so its whole span is recorded; :func:`delete_range`
leaves no value in its range, so the known values it deleted are what changed. Retention drops
the runs starting in a dropped time partition of the samples
(:func:`drop_starting_in`).

What a run may hold (:func:`check_run`): times 0 ≤ t_start ≤ t_end <
:data:`cranetwin.storage.blocks.T_LIMIT_NS`, a span of at most
:data:`cranetwin.storage.blocks.MAX_SPAN_NS` (6 h: reads bound t_start from below by it, as
for the samples), 1 ≤ n ≤ :data:`MAX_RUN`, period ≥ 1 ns when n > 1, and values that are NaN or
finite and ≥ 0 [kg] (a negative or infinite payload is refused, never clipped).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import (
    BigInteger,
    Connection,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    select,
    text,
    tuple_,
)
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.errors import StorageError
from cranetwin.storage import bulk
from cranetwin.storage.base import Base
from cranetwin.storage.blocks import MAX_SPAN_NS, T_LIMIT_NS, clamp_ns

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MAX_RUN = 100_000
"""Most values in one run (800 kB before compression)."""
TABLE = "payload_runs"
COLUMNS = ("machine_pk", "t_start_ns", "t_end_ns", "period_ns", "n", "data")


class PayloadRunRow(Base):
    """A run of known payload values of one machine (module docstring)."""

    __tablename__ = TABLE
    __table_args__ = (Index("ix_payload_runs_machine_pk_t_end_ns", "machine_pk", "t_end_ns"),)

    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"),
                                            primary_key=True)
    t_start_ns: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    t_end_ns: Mapped[int] = mapped_column(BigInteger)
    period_ns: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)


@dataclass(frozen=True)
class PayloadRun:
    """Known payload at regular times.

    Attributes:
        t0_ns: Time of the first value [ns since the Unix epoch].
        period_ns: Spacing [ns] (0 for a single value).
        payload_kg: Values [kg], shape (n,); NaN = not known.
    """

    t0_ns: int
    period_ns: int
    payload_kg: F64

    @property
    def n(self) -> int:
        return int(self.payload_kg.shape[0])

    @property
    def t_end_ns(self) -> int:
        return self.t0_ns + (self.n - 1) * self.period_ns

    def times_ns(self) -> I64:
        """The run's times [ns], shape (n,)."""
        return self.t0_ns + np.arange(self.n, dtype=np.int64) * np.int64(self.period_ns)


@dataclass(frozen=True)
class PayloadSeries:
    """A stored known payload over a range, as :meth:`cranetwin.storage.Store.read_payload`
    returns it.

    Attributes:
        machine_id: The machine.
        t_ns: Times [ns since the Unix epoch], shape (n,), strictly increasing.
        payload_kg: Payload at them [kg], shape (n,); NaN = not known.
    """

    machine_id: str
    t_ns: I64
    payload_kg: F64

    @property
    def t_s(self) -> F64:
        """Times [s since the Unix epoch], shape (n,)."""
        return self.t_ns.astype(np.float64) / 1e9

    @property
    def n(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def known(self) -> bool:
        """Some value is known (not NaN)."""
        return bool(np.isfinite(self.payload_kg).any())


@dataclass(frozen=True)
class PayloadWrite:
    """What :meth:`cranetwin.storage.Store.write_payload` did.

    Attributes:
        stored: Runs newly stored.
        duplicate: Runs already stored with the same values.
        differing: Runs whose (machine, start) is stored with other values (kept as stored).
        values_stored: Values of the runs newly stored (NaN ones included).
        new_starts: Start times [ns] of the runs newly stored (for
            :meth:`cranetwin.storage.Store.delete_payload_runs`).
    """

    stored: int = 0
    duplicate: int = 0
    differing: int = 0
    values_stored: int = 0
    new_starts: tuple[int, ...] = ()


def check_run(run: PayloadRun) -> str | None:
    """Why ``run`` cannot be stored (module docstring), or None."""
    v = np.asarray(run.payload_kg)
    if v.ndim != 1 or not 1 <= v.shape[0] <= MAX_RUN:
        return f"a run holds 1..{MAX_RUN} values in shape (n,), not {v.shape}"
    if v.shape[0] > 1 and run.period_ns < 1:
        return f"period {run.period_ns} ns; at least 1 ns"
    if run.t0_ns < 0 or run.t_end_ns >= T_LIMIT_NS:
        return f"times [{run.t0_ns}, {run.t_end_ns}] ns outside [0, {T_LIMIT_NS})"
    if run.t_end_ns - run.t0_ns > MAX_SPAN_NS:
        return f"run spans {(run.t_end_ns - run.t0_ns) / 1e9:.0f} s; at most " \
               f"{MAX_SPAN_NS // 10**9} s"
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(np.isinf(v) | (v < 0))
    if bad.size:
        i = int(bad[0])
        return (f"payload {v[i]!r} kg at {run.t0_ns + i * run.period_ns} ns: a payload is "
                "finite and ≥ 0 (NaN = not known)")
    return None


def runs_of(t_ns: I64, payload_kg: F64) -> list[PayloadRun]:
    """Cut a series into runs of equal spacing (each at most :data:`MAX_RUN` values and
    :data:`~cranetwin.storage.blocks.MAX_SPAN_NS` long); the same series always gives the
    same runs.

    Args:
        t_ns: Times [ns], shape (n,), strictly increasing.
        payload_kg: Values [kg], shape (n,).

    Raises:
        StorageError: Shapes differ or times are not strictly increasing.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(payload_kg, dtype=np.float64)
    if t.ndim != 1 or v.shape != t.shape:
        raise StorageError(f"payload shape {v.shape} must equal the times' shape {t.shape} (n,)")
    n = t.shape[0]
    d = np.diff(t)
    if np.any(d <= 0):
        raise StorageError("payload times must be strictly increasing")
    # end (exclusive, in d) of the stretch of equal spacings holding each d index
    ends = np.concatenate((np.flatnonzero(np.diff(d) != 0) + 1, [d.shape[0]]))
    out: list[PayloadRun] = []
    i = 0
    while i < n:
        if i == n - 1:
            out.append(PayloadRun(int(t[i]), 0, v[i:i + 1].copy()))
            break
        e = int(ends[np.searchsorted(ends, i, side="right")])  # d[i:e] equal: times i..e
        p = int(d[i])
        step = max(1, min(MAX_RUN, MAX_SPAN_NS // p + 1))
        for a in range(i, e + 1, step):
            b = min(e + 1, a + step)
            out.append(PayloadRun(int(t[a]), p if b - a > 1 else 0, v[a:b].copy()))
        i = e + 1
    return out


def _encode(v: F64) -> bytes:
    return zlib.compress(np.ascontiguousarray(v, dtype="<f8").tobytes(), 1)


def _decode(data: bytes, n: int) -> F64:
    v = np.frombuffer(zlib.decompress(data), dtype="<f8")
    if v.shape[0] != n:
        raise StorageError(f"a stored payload run holds {v.shape[0]} values, not {n}")
    return v.astype(np.float64)


def write(session: Session, machine_pk: int, runs: Sequence[PayloadRun]) -> PayloadWrite:
    """Insert ``runs`` of one machine in the caller's transaction (module docstring).

    Raises:
        StorageError: A run cannot be stored (:func:`check_run`); nothing is inserted.
    """
    if not runs:
        return PayloadWrite()
    rows: list[tuple[object, ...]] = []
    for r in runs:
        why = check_run(r)
        if why is not None:
            raise StorageError(f"payload run at {r.t0_ns} ns not stored: {why}")
        rows.append((machine_pk, int(r.t0_ns), int(r.t_end_ns), int(r.period_ns), r.n,
                     _encode(r.payload_kg)))
    conn = session.connection()
    new = {int(t) for (t,) in bulk.insert_rows(
        conn, TABLE, COLUMNS, rows,
        "ON CONFLICT (machine_pk, t_start_ns) DO NOTHING RETURNING t_start_ns")}
    old = [r for r in runs if r.t0_ns not in new]
    stored = {}
    row = PayloadRunRow
    for i in range(0, len(old), 5000):
        keys = [(machine_pk, r.t0_ns) for r in old[i:i + 5000]]
        stored.update({int(t): (int(p), int(n), bytes(data)) for t, p, n, data in session.execute(
            select(row.t_start_ns, row.period_ns, row.n, row.data)
            .where(tuple_(row.machine_pk, row.t_start_ns).in_(keys)))})
    same = 0
    for r in old:
        got = stored.get(r.t0_ns)
        if got is not None and got[0] == r.period_ns and got[1] == r.n and np.array_equal(
                _decode(got[2], got[1]), r.payload_kg, equal_nan=True):
            same += 1
    return PayloadWrite(len(new), same, len(old) - same,
                        sum(r.n for r in runs if r.t0_ns in new), tuple(sorted(new)))


def delete(session: Session, machine_pk: int, starts: Sequence[int]) -> PayloadDelete:
    """Delete the runs of a machine that start at ``starts`` [ns], whole, in the caller's
    transaction."""
    row = PayloadRunRow
    gone = values = known = 0
    changed: list[tuple[int, int]] = []
    for i in range(0, len(starts), 5000):
        chunk = [int(t) for t in starts[i:i + 5000]]
        for t_start, period, n, data in session.execute(
                select(row.t_start_ns, row.period_ns, row.n, row.data)
                .where(row.machine_pk == machine_pk, row.t_start_ns.in_(chunk))):
            run = PayloadRun(int(t_start), int(period), _decode(bytes(data), int(n)))
            values += run.n
            known += int(np.count_nonzero(np.isfinite(run.payload_kg)))
            changed.append((run.t0_ns, run.t_end_ns))  # NaN too: it may have hidden a value
        gone += session.query(row).filter(row.machine_pk == machine_pk,
                                          row.t_start_ns.in_(chunk)).delete(
            synchronize_session=False)
    return PayloadDelete(gone, 0, values, known, tuple(changed))


@dataclass(frozen=True)
class PayloadDelete:
    """What :func:`delete_range` did.

    Attributes:
        runs_deleted: Runs deleted whole.
        runs_cut: Runs that straddled a bound of the range: their values inside it deleted,
            those outside stored again as runs of their own.
        values_deleted: Values deleted (NaN ones included).
        known_deleted: Known (not NaN) values deleted.
        changed_ns: (first, last) time [ns] of each stretch of known values deleted
            (:func:`delete_range`), or of each run deleted whole (:func:`delete`; module
            docstring): what :func:`cranetwin.storage.redo.request` records.
    """

    runs_deleted: int = 0
    runs_cut: int = 0
    values_deleted: int = 0
    known_deleted: int = 0
    changed_ns: tuple[tuple[int, int], ...] = ()


def _overlapping(machine_pk: int, t0_ns: int, t1_ns: int) -> Any:
    """The runs of a machine holding a time in [t0_ns, t1_ns), oldest first."""
    row = PayloadRunRow
    return (select(row.t_start_ns, row.period_ns, row.n, row.data)
            .where(row.machine_pk == machine_pk, row.t_start_ns <= clamp_ns(t1_ns - 1),
                   row.t_end_ns >= clamp_ns(t0_ns),
                   row.t_start_ns >= clamp_ns(clamp_ns(t0_ns) - MAX_SPAN_NS))
            .order_by(row.t_start_ns))


def delete_range(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> PayloadDelete:
    """Delete the stored values of a machine with t0_ns ≤ t < t1_ns, in the caller's
    transaction: a run inside the range goes whole; a run straddling a bound is cut there (its
    values outside the range are stored again, as one run before the range — same start, so
    the same key — and one after it)."""
    row = PayloadRunRow
    gone: list[int] = []
    pieces: list[PayloadRun] = []
    cut = values = known = 0
    changed: list[tuple[int, int]] = []
    for t_start, period, n, data in session.execute(_overlapping(machine_pk, t0_ns, t1_ns)):
        run = PayloadRun(int(t_start), int(period), _decode(bytes(data), int(n)))
        t = run.times_ns()
        inside = (t >= t0_ns) & (t < t1_ns)
        if not inside.any():
            continue
        gone.append(run.t0_ns)
        values += int(np.count_nonzero(inside))
        k = inside & np.isfinite(run.payload_kg)
        known += int(np.count_nonzero(k))
        if k.any():
            changed.append((int(t[k][0]), int(t[k][-1])))
        for keep in (t < t0_ns, t >= t1_ns):
            idx = np.flatnonzero(keep)
            if idx.size:
                pieces.append(PayloadRun(int(t[idx[0]]), run.period_ns if idx.size > 1 else 0,
                                         run.payload_kg[idx].copy()))
        cut += int(not inside.all())
    for i in range(0, len(gone), 5000):
        session.query(row).filter(row.machine_pk == machine_pk,
                                  row.t_start_ns.in_(gone[i:i + 5000])).delete(
            synchronize_session=False)
    if pieces:
        write(session, machine_pk, pieces)
    return PayloadDelete(len(gone) - cut, cut, values, known, tuple(changed))


@dataclass(frozen=True)
class Stretch:
    """Stored runs of one machine following each other without a gap (:func:`stretches`).

    Attributes:
        t_first_ns, t_last_ns: First and last stored time [ns since the Unix epoch].
        runs: Runs in it.
        values: Values stored (NaN ones included).
        known: Known (not NaN) values.
        min_kg, max_kg: Smallest and largest known value [kg] (NaN when none is known).
    """

    t_first_ns: int
    t_last_ns: int
    runs: int
    values: int
    known: int
    min_kg: float
    max_kg: float


GAP_PERIODS = 5
"""Runs are one stretch when the next starts at most this many of their sample periods after
the previous ends (the replay's gap limit, docs/IMPORT.md)."""


def stretches(session: Session, machine_pk: int, t0_ns: int, t1_ns: int) -> list[Stretch]:
    """The stored series of a machine over [t0_ns, t1_ns) as stretches of runs (runs
    starting in the range, whole; read in batches, one run decoded at a time)."""
    row = PayloadRunRow
    stmt = (select(row.t_start_ns, row.period_ns, row.n, row.data)
            .where(row.machine_pk == machine_pk, row.t_start_ns >= clamp_ns(t0_ns),
                   row.t_start_ns < clamp_ns(t1_ns))
            .order_by(row.t_start_ns).execution_options(yield_per=1000))
    out: list[Stretch] = []
    cur: list[Any] | None = None  # first, last, runs, values, known, min, max, period
    for t_start, period, n, data in session.execute(stmt):
        v = _decode(bytes(data), int(n))
        fin = v[np.isfinite(v)]
        lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (np.nan, np.nan)
        end = int(t_start) + (int(n) - 1) * int(period)
        if cur is not None and int(t_start) - cur[1] <= GAP_PERIODS * max(cur[7], int(period)):
            cur[1] = max(cur[1], end)
            cur[2] += 1
            cur[3] += int(n)
            cur[4] += int(fin.size)
            cur[5] = float(np.fmin(cur[5], lo))
            cur[6] = float(np.fmax(cur[6], hi))
            cur[7] = int(period)
            continue
        if cur is not None:
            out.append(Stretch(*cur[:7]))
        cur = [int(t_start), end, 1, int(n), int(fin.size), lo, hi, int(period)]
    if cur is not None:
        out.append(Stretch(*cur[:7]))
    return out


def drop_starting_in(conn: Connection, lo_ns: int, hi_ns: int) -> int:
    """Delete the runs of every machine that start in [lo_ns, hi_ns) (retention drops a time
    partition of the samples, :func:`cranetwin.storage.partitions.drop_expired`: a run goes
    with the partition its start falls in, as a sample block does); returns how many."""
    res = conn.execute(text(
        "DELETE FROM payload_runs WHERE machine_pk IN (SELECT id FROM machines) "
        "AND t_start_ns >= :lo AND t_start_ns < :hi"), {"lo": int(lo_ns), "hi": int(hi_ns)})
    return int(getattr(res, "rowcount", 0) or 0)


def read(session: Session, machine_id: str, machine_pk: int, t0_ns: int,
         t1_ns: int) -> PayloadSeries:
    """The stored known payload of a machine with t0_ns ≤ t < t1_ns, oldest first (a time
    held by two runs once, from the run starting earlier)."""
    ts: list[I64] = []
    vs: list[F64] = []
    for t_start, period, n, data in session.execute(_overlapping(machine_pk, t0_ns, t1_ns)):
        run = PayloadRun(int(t_start), int(period), _decode(bytes(data), int(n)))
        ts.append(run.times_ns())
        vs.append(run.payload_kg)
    if not ts:
        return PayloadSeries(machine_id, np.zeros(0, dtype=np.int64), np.zeros(0))
    t = np.concatenate(ts)
    v = np.concatenate(vs)
    keep = (t >= t0_ns) & (t < t1_ns)
    t_u, first = np.unique(t[keep], return_index=True)  # sorted; first = earliest run's
    return PayloadSeries(machine_id, t_u.astype(np.int64), v[keep][first])


def stored_ranges(session: Session, machine_pks: Sequence[int]) -> dict[int, tuple[int, int]]:
    """Per machine primary key, (first run start, last run end) [ns] of its stored runs, in one
    statement (an index probe per machine each way, as for the blocks' data ranges); machines
    without runs are left out."""
    from sqlalchemy import func

    from cranetwin.storage.machines import MachineRow

    row, m = PayloadRunRow, MachineRow
    lo = select(func.min(row.t_start_ns)).where(row.machine_pk == m.id).scalar_subquery()
    hi = select(func.max(row.t_end_ns)).where(row.machine_pk == m.id).scalar_subquery()
    out: dict[int, tuple[int, int]] = {}
    for i in range(0, len(machine_pks), 5000):
        pks = [int(p) for p in machine_pks[i:i + 5000]]
        for pk, a, z in session.execute(select(m.id, lo, hi).where(m.id.in_(pks))):
            if a is not None:
                out[int(pk)] = (int(a), int(z))
    return out


__all__ = ["GAP_PERIODS", "MAX_RUN", "PayloadDelete", "PayloadRun", "PayloadRunRow",
           "PayloadSeries", "PayloadWrite", "Stretch", "check_run", "delete", "delete_range",
           "drop_starting_in", "read", "runs_of", "stored_ranges", "stretches",
           "write"]
