"""Stored analytics parts: per machine and window, what the analyses need to merge exactly.

One row per (machine, level, window start): ``level`` is the window length in seconds (60 for
the twin worker's minutes, 3600 and 86400 for roll-ups), ``data`` the serialised
:class:`cranetwin.analytics.AnalyticsPart` (the service writes and reads it; see
:mod:`cranetwin.service.history`), ``n`` the samples it covers. Writing a window again (a redone
window) replaces it. Plain functions over an engine, so the storage core is not touched.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import (
    BigInteger,
    Engine,
    Float,
    Integer,
    LargeBinary,
    Select,
    String,
    delete,
    func,
    select,
    text,
)
from sqlalchemy.orm import InstrumentedAttribute, Mapped, Session, mapped_column
from sqlalchemy.sql.elements import ColumnElement, TextClause

from cranetwin.storage.base import Base

SEC = 1_000_000_000


class AnalyticsWindowRow(Base):
    """The analytics part of one window of one machine."""

    __tablename__ = "analytics_windows"

    machine_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    level_s: Mapped[int] = mapped_column(Integer, primary_key=True)
    t0_ns: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    t1_ns: Mapped[int] = mapped_column(BigInteger)
    n: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    operating_s: Mapped[float] = mapped_column(Float, default=0.0)
    idle_s: Mapped[float] = mapped_column(Float, default=0.0)


def _ns(t_s: float) -> int:
    return int(round(t_s * SEC))


def window_row(machine_id: str, level_s: int, t0_s: float, t1_s: float, n: int, data: bytes,
               operating_s: float = 0.0, idle_s: float = 0.0) -> dict[str, Any]:
    """The row of window [t0_s, t1_s) of ``level_s`` (:func:`put_rows` writes it)."""
    return {"machine_id": machine_id, "level_s": level_s, "t0_ns": _ns(t0_s), "t1_ns": _ns(t1_s),
            "n": n, "data": data, "operating_s": operating_s, "idle_s": idle_s}


_COLUMNS = ("machine_id", "level_s", "t0_ns", "t1_ns", "n", "data", "operating_s", "idle_s")
_UPSERT = ("ON CONFLICT (machine_id, level_s, t0_ns) DO UPDATE SET "
           + ", ".join(f"{c} = EXCLUDED.{c}" for c in _COLUMNS[3:]))


def put_rows(session: Session, rows: list[dict[str, Any]]) -> None:
    """Store (or replace) rows of :func:`window_row` in one statement, inside the caller's
    transaction (a window's part, lift seconds and progress commit together)."""
    from cranetwin.storage.bulk import insert_rows

    if rows:
        insert_rows(session.connection(), "analytics_windows", _COLUMNS,
                    [tuple(r[c] for c in _COLUMNS) for r in rows], _UPSERT)


def put_window(engine: Engine, machine_id: str, level_s: int, t0_s: float, t1_s: float, n: int,
               data: bytes, operating_s: float = 0.0, idle_s: float = 0.0) -> None:
    """Store (or replace) the part of window [t0_s, t1_s) of ``level_s``, with the operating
    and idle time the twin worker counted for it (so a redone window replaces its share of the
    cumulative counters instead of adding it again)."""
    with Session(engine) as s, s.begin():
        put_rows(s, [window_row(machine_id, level_s, t0_s, t1_s, n, data, operating_s,
                                idle_s)])


def windows(engine: Engine, machine_id: str, level_s: int, t0_s: float,
            t1_s: float) -> list[tuple[float, float, int, bytes]]:
    """Windows of ``level_s`` inside [t0_s, t1_s): ``(t0 s, t1 s, n, data)``, oldest first."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns, w.t1_ns, w.n, w.data)
            .where(w.machine_id == machine_id, w.level_s == level_s, w.t0_ns >= _ns(t0_s),
                   w.t1_ns <= _ns(t1_s)).order_by(w.t0_ns))
    with Session(engine) as s:
        return [(a / SEC, b / SEC, int(n), bytes(d)) for a, b, n, d in s.execute(stmt)]


def spans(engine: Engine, machine_id: str, level_s: int, t0_s: float,
          t1_s: float) -> list[tuple[float, float]]:
    """:func:`windows` without their data: ``(t0 s, t1 s)`` inside [t0_s, t1_s), oldest
    first."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns, w.t1_ns)
            .where(w.machine_id == machine_id, w.level_s == level_s, w.t0_ns >= _ns(t0_s),
                   w.t1_ns <= _ns(t1_s)).order_by(w.t0_ns))
    with Session(engine) as s:
        return [(a / SEC, b / SEC) for a, b in s.execute(stmt)]


def window_times(engine: Engine, machine_id: str, level_s: int,
                 t0_s: float) -> tuple[float, float] | None:
    """(operating s, idle s) stored with the window of ``level_s`` starting at ``t0_s``, or None
    when no such window is stored."""
    w = AnalyticsWindowRow
    with Session(engine) as s:
        r = s.execute(select(w.operating_s, w.idle_s).where(
            w.machine_id == machine_id, w.level_s == level_s, w.t0_ns == _ns(t0_s))).first()
        return None if r is None else (float(r[0]), float(r[1]))


def window_starts(engine: Engine, machine_id: str, level_s: int, t0_s: float,
                  t1_s: float) -> list[float]:
    """Start times of the stored windows of ``level_s`` inside [t0_s, t1_s) [s]."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns).where(w.machine_id == machine_id, w.level_s == level_s,
                                  w.t0_ns >= _ns(t0_s), w.t1_ns <= _ns(t1_s)).order_by(w.t0_ns))
    with Session(engine) as s:
        return [a / SEC for a in s.scalars(stmt)]


def delete_windows(engine: Engine, machine_id: str, t0_s: float, t1_s: float,
                   levels: tuple[int, ...] = (60, 3600, 86400)) -> int:
    """Drop the windows of ``levels`` that overlap [t0_s, t1_s) (their data changed)."""
    w = AnalyticsWindowRow
    with Session(engine) as s, s.begin():
        res = s.execute(delete(w).where(w.machine_id == machine_id, w.t0_ns < _ns(t1_s),
                                        w.t1_ns > _ns(t0_s), w.level_s.in_(levels)))
        return int(getattr(res, "rowcount", 0) or 0)


def delete_window(session: Session, machine_id: str, level_s: int, t0_s: float) -> None:
    """Drop the window of ``level_s`` starting at ``t0_s`` (if any), in the caller's
    transaction."""
    w = AnalyticsWindowRow
    session.execute(delete(w).where(w.machine_id == machine_id, w.level_s == level_s,
                                    w.t0_ns == _ns(t0_s)))


MARK_LEVEL = 0
"""``level_s`` of the row that keeps a machine's block mark (``t1_ns``: the largest sample block
id the analytics have seen; SQLite, and PostgreSQL before its first commit-order mark)."""
XMARK_LEVEL = -2
"""PostgreSQL: ``level_s`` of the row that keeps a machine's commit-order mark (``t1_ns``: the
``pg_snapshot_xmin`` of the last pass; every block written by a transaction below it has been
seen). ``-1`` is the duty to date (:mod:`cranetwin.service.history`)."""


def counter(machine_id: str | ColumnElement[str] | InstrumentedAttribute[str],
            level_s: int) -> Select[int]:
    """The ``n`` of a machine's one row at ``level_s`` with ``t0_ns`` 0 (a per-machine counter:
    the known-payload version, the late-data version); no row: NULL."""
    w = AnalyticsWindowRow
    return select(w.n).where(w.machine_id == machine_id, w.level_s == level_s, w.t0_ns == 0)

def _mark(engine: Engine, machine_id: str, level: int) -> int | None:
    w = AnalyticsWindowRow
    with Session(engine) as s:
        v = s.scalar(select(w.t1_ns).where(w.machine_id == machine_id, w.level_s == level))
        return None if v is None else int(v)


def block_mark(engine: Engine, machine_id: str) -> int | None:
    """The mark of :func:`new_blocks_before` (PostgreSQL: the commit-order mark once one is
    stored, else the block id mark), or None before the first call."""
    if engine.dialect.name == "postgresql":
        x = _mark(engine, machine_id, XMARK_LEVEL)
        if x is not None:
            return x
    return _mark(engine, machine_id, MARK_LEVEL)


def mark_row(dialect: str, machine_id: str, mark: int) -> dict[str, Any]:
    """The row keeping ``mark`` (:func:`set_block_mark`; several written by :func:`put_rows`)."""
    level = XMARK_LEVEL if dialect == "postgresql" else MARK_LEVEL
    return window_row(machine_id, level, 0.0, mark / SEC, 0, b"")


def set_block_mark(engine: Engine, machine_id: str, mark: int) -> None:
    """Store the mark :func:`new_blocks_before` returned (PostgreSQL: a commit-order mark)."""
    with Session(engine) as s, s.begin():
        put_rows(s, [mark_row(engine.dialect.name, machine_id, mark)])


def new_blocks_before(engine: Engine, machine_id: str, after: int | None,
                      before_s: float) -> tuple[int | None, list[tuple[float, float]]]:
    """Blocks stored since the mark ``after`` that start before ``before_s`` (late data and
    backfills behind the twin worker's progress mark): ``(the next mark, [(t_start s, t_end s),
    ...])``. With ``after`` None only the mark is returned (the first call).

    SQLite (one writer: ids grow in commit order): the mark is the largest block id seen.
    PostgreSQL: ids are drawn when an insert runs, not when it commits, so a lower id can
    commit after a higher one was seen; the mark is instead ``pg_snapshot_xmin`` of the pass,
    and a pass takes the rows whose writing transaction (``writer_xid``, migration ``0006c``)
    lies in [previous mark, this xmin): every transaction below xmin has ended, so nothing can
    appear below the mark later. A transaction left open anywhere on the server holds xmin
    back and so delays (never loses) late blocks. A PostgreSQL mark of the earlier kind (a
    block id, from before ``0006c``) is used once: rows above that id, then the xmin mark.
    """
    from cranetwin.storage.blocks import BlockRow
    from cranetwin.storage.machines import MachineRow

    pg = engine.dialect.name == "postgresql"
    with Session(engine) as s:
        pk = s.scalar(select(MachineRow.id).where(MachineRow.machine_id == machine_id))
        if pk is None:
            return after, []
        b = BlockRow
        where: list[ColumnElement[bool] | TextClause] = [b.machine_pk == pk,
                                                         b.t_start_ns < _ns(before_s)]
        if pg:
            top = s.scalar(text("SELECT pg_snapshot_xmin(pg_current_snapshot())::text::bigint"))
            legacy = after is not None and _mark(engine, machine_id, XMARK_LEVEL) is None
            if after is None:
                return int(top), []
            where.append(b.id > after if legacy else text(
                "writer_xid >= CAST(CAST(:lo AS text) AS xid8) "
                "AND writer_xid < CAST(CAST(:hi AS text) AS xid8)").bindparams(lo=after,
                                                                              hi=int(top)))
        else:
            top = s.scalar(select(func.max(b.id)).where(b.machine_pk == pk))
            if after is None or top is None:
                return (None if top is None else int(top)), []
            where.append(b.id > after)
        rows = s.execute(select(b.t_start_ns, b.t_end_ns).where(*where)).all()
        return int(top), [(a / SEC, c / SEC) for a, c in rows]


def block_marks(engine: Engine, machine_ids: list[str]) -> dict[str, tuple[int | None, bool]]:
    """:func:`block_mark` of many machines in one statement: ``machine → (mark, legacy)``
    (``legacy``: PostgreSQL with only a block id mark, which :func:`new_blocks_before` uses
    once; None: no mark yet)."""
    w = AnalyticsWindowRow
    pg = engine.dialect.name == "postgresql"
    got: dict[str, dict[int, int]] = {}
    with Session(engine) as s:
        for mid, level, t1 in s.execute(select(w.machine_id, w.level_s, w.t1_ns).where(
                w.machine_id.in_(machine_ids), w.level_s.in_((MARK_LEVEL, XMARK_LEVEL)))):
            got.setdefault(mid, {})[int(level)] = int(t1)
    out: dict[str, tuple[int | None, bool]] = {}
    for mid in machine_ids:
        m = got.get(mid, {})
        if pg and XMARK_LEVEL in m:
            out[mid] = (m[XMARK_LEVEL], False)
        else:
            mark = m.get(MARK_LEVEL)
            out[mid] = (mark, pg and mark is not None)
    return out


def snapshot_xmin(engine: Engine) -> int:
    """PostgreSQL: ``pg_snapshot_xmin`` now (the next commit-order mark of
    :func:`new_blocks_before`)."""
    with Session(engine) as s:
        return int(s.scalar(text("SELECT pg_snapshot_xmin(pg_current_snapshot())::text::bigint")))


def snapshot(engine: Engine) -> tuple[int, str]:
    """PostgreSQL: ``pg_snapshot_xmin`` now (the next commit-order mark of
    :func:`new_blocks_before`) and the snapshot it is the xmin of (``pg_snapshot`` text:
    which transactions had committed then, :class:`Seen`)."""
    with Session(engine) as s:
        row = s.execute(text("SELECT pg_snapshot_xmin(c)::text::bigint, c::text "
                             "FROM pg_current_snapshot() AS c")).one()
        return int(row[0]), str(row[1])


@dataclass(frozen=True)
class Seen:
    """Blocks a pass has seen although their transactions lie above its mark: those committed
    in ``snapshot`` (the pass's, whose xmin is the mark) that start after ``after_s`` (s). A
    pass that read them after taking ``snapshot`` and replayed everything from before
    ``after_s`` − margin to the watermark has replayed every instant of theirs behind it with
    them, so they are not late data for the next pass. Without it, every block committed
    while any transaction on the server was open across it (a storage writer's, another
    pass's, another database's) came back as late data and redid the span holding it."""

    snapshot: str
    after_s: float


def new_blocks_before_many(engine: Engine, bounds: dict[int, tuple[int, float]],
                           top: int, seen: dict[int, Seen] | None = None,
                           ) -> dict[int, list[tuple[float, float]]]:
    """PostgreSQL, :func:`new_blocks_before` of many machines in one statement: per machine
    primary key, the blocks written by transactions in [its mark, ``top``) (a commit-order
    mark, :func:`snapshot_xmin`) that start before its ``before_s``, except those its ``seen``
    entry says the last pass has seen (:class:`Seen`). ``bounds``: machine primary key →
    (mark, before_s). Returns machine primary key → [(t_start s, t_end s), ...] (machines
    without such blocks left out)."""
    if not bounds:
        return {}
    pks = list(bounds)
    seen = seen or {}
    stmt = text(
        "SELECT b.machine_pk, b.t_start_ns, b.t_end_ns FROM unnest(CAST(:pks AS integer[]), "
        "CAST(:los AS text[]), CAST(:ts AS bigint[]), CAST(:snaps AS text[]), "
        "CAST(:afters AS bigint[])) AS v(pk, lo, t, snap, after_ns) "
        "JOIN sample_blocks b ON b.machine_pk = v.pk AND b.t_start_ns < v.t "
        "AND b.writer_xid >= CAST(v.lo AS xid8) "
        "AND b.writer_xid < CAST(CAST(:hi AS text) AS xid8) "
        "AND NOT (v.snap IS NOT NULL AND b.t_start_ns > v.after_ns AND "
        "pg_visible_in_snapshot(b.writer_xid, CAST(v.snap AS pg_snapshot)))").bindparams(
        pks=pks, los=[str(bounds[p][0]) for p in pks], ts=[_ns(bounds[p][1]) for p in pks],
        snaps=[seen[p].snapshot if p in seen else None for p in pks],
        afters=[_ns(seen[p].after_s) if p in seen else 0 for p in pks], hi=top)
    out: dict[int, list[tuple[float, float]]] = {}
    with Session(engine) as s:
        for pk, a, c in s.execute(stmt):
            out.setdefault(int(pk), []).append((a / SEC, c / SEC))
    return out
