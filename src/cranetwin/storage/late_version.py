"""A machine's late-data version: a number raised by every stored block that lands behind data
already stored (late data, a backfill, blocks committed out of order) and by retention.

A replay of a past window depends on the blocks stored around it, and those change after the
replay when a machine that was offline retransmits its journal (a past window's samples arrive
minutes later), when writers commit blocks out of order, or when retention drops a partition.
Samples appended in time order (a live machine) never land in a window that has already been
replayed as closed, so a result kept for a past window (the API's replay cache,
:meth:`cranetwin.service.fleet.FleetService.twin_key`) is valid while this version is unchanged
and the window ended before the newest stored block when both were read.

It is one row of ``analytics_windows`` per machine (level :data:`LEVEL`, ``t0_ns`` 0, as
:mod:`cranetwin.storage.payload_version`): ``t1_ns`` the high-water mark (the end of the newest
block any write has stored [ns]; never lowered), ``n`` the version (no row: version 0). Every
write transaction that stores blocks upserts the rows of its machines (:func:`note`, called by
:mod:`cranetwin.storage.writes`, the one path of every writer: the ingest daemon, the bus store
writer, the importer, the MQTT adapter): the version is raised when a newly stored block starts
at or before the high-water mark it finds, and the mark is raised to the newest block end.

Why that is exact under concurrent writers (PostgreSQL READ COMMITTED): the upsert holds the
row's lock until its transaction commits, so two writers of one machine pass it one after the
other, the second seeing the first's mark. A reader that read the newest block end E and the
version v in one statement (:meth:`cranetwin.storage.Store.get_machine`) and then replays a
window ending before E misses a block X overlapping the window only if X commits later; the
writer of E committed before the read, so it passed the row before X's writer (had X's writer
passed it first, E's writer would have waited for X's commit), and X's writer found a mark ≥ E
beyond X's start, raising the version above v in X's transaction.

Retention (:func:`cranetwin.storage.partitions.drop_expired`) raises every machine's version in
the transaction that drops partitions (:func:`bump_all`). Reading the version is one
primary-key lookup, a column of a statement the request makes anyway (:func:`column`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

from sqlalchemy import ScalarSelect, text
from sqlalchemy.engine import Connection
from sqlalchemy.orm import InstrumentedAttribute, Session
from sqlalchemy.sql.elements import ColumnElement, TextClause

from cranetwin.storage import analytics_windows as aw
from cranetwin.storage.blocks import MAX_SPAN_NS

LEVEL = -7
"""``level_s`` of the row (``-5`` known-payload version, ``-6`` failed span: see
:mod:`cranetwin.storage.payload_version`)."""

_COLS = "(machine_id, level_s, t0_ns, t1_ns, n, data, operating_s, idle_s)"
_NEWEST = ("(SELECT max(b.t_end_ns) FROM sample_blocks b WHERE b.machine_pk = v.pk "
           f"AND b.t_start_ns >= v.tend - {MAX_SPAN_NS})")
"""End of the machine's newest block among those that can end after ``v.tend`` (a block
ending later starts at most MAX_SPAN before its end: PostgreSQL reads only the newest
partitions)."""
_UPSERT = (
    "INSERT INTO analytics_windows " + _COLS + " SELECT v.mid, " + str(LEVEL) + ", 0, "
    "{greatest}(v.tend, coalesce(" + _NEWEST + ", v.tend)), 1, :empty, 0, 0 FROM v "
    "WHERE true ORDER BY v.mid "
    "ON CONFLICT (machine_id, level_s, t0_ns) DO UPDATE SET "
    "n = analytics_windows.n + CASE WHEN (SELECT v.tmin FROM v WHERE v.mid = "
    "excluded.machine_id) <= analytics_windows.t1_ns THEN 1 ELSE 0 END, "
    "t1_ns = {greatest}(analytics_windows.t1_ns, excluded.t1_ns)")


@functools.lru_cache(maxsize=64)
def _note_sql(dialect: str, n: int) -> TextClause:
    """The statement of :func:`note` for ``n`` machines (made once per dialect and count)."""
    if dialect == "postgresql":
        cte = ("WITH v(mid, pk, tmin, tend) AS (SELECT * FROM unnest(CAST(:mids AS text[]), "
               "CAST(:pks AS integer[]), CAST(:tmins AS bigint[]), CAST(:tends AS bigint[]))) ")
        return text(cte + _UPSERT.format(greatest="greatest"))
    values = ", ".join(f"(:m{i}, :p{i}, :a{i}, :z{i})" for i in range(n))
    return text(f"WITH v(mid, pk, tmin, tend) AS (VALUES {values}) "
                + _UPSERT.format(greatest="max"))


def note(session: Session, stored: Sequence[tuple[str, int, int, int]]) -> None:
    """Record newly stored blocks, inside the transaction that stored them (after the insert):
    per machine, raise the version when they start at or before its high-water mark, and raise
    the mark to its newest block end. One statement for all machines, rows locked in machine
    order (two writers never wait for each other crosswise).

    Args:
        stored: ``(machine id, machine primary key, earliest start [ns], latest end [ns])`` of
            the blocks this transaction stored, one entry per machine.
    """
    if not stored:
        return
    rows = sorted(stored)
    conn = session.connection()
    params: dict[str, object] = {"empty": b""}
    if conn.dialect.name == "postgresql":
        params.update(mids=[r[0] for r in rows], pks=[r[1] for r in rows],
                      tmins=[r[2] for r in rows], tends=[r[3] for r in rows])
        stmt = _note_sql("postgresql", 0)
    else:
        for i, (mid, pk, a, z) in enumerate(rows):
            params.update({f"m{i}": mid, f"p{i}": pk, f"a{i}": a, f"z{i}": z})
        stmt = _note_sql(conn.dialect.name, len(rows))
    session.execute(stmt, params)


def bump_all(conn: Connection) -> None:
    """Raise every machine's version by one, in the caller's transaction (the one dropping
    stored blocks: retention). A machine without a row gets one, with its high-water mark."""
    greatest = "greatest" if conn.dialect.name == "postgresql" else "max"
    conn.execute(text(
        "INSERT INTO analytics_windows " + _COLS + " SELECT m.machine_id, " + str(LEVEL)
        + ", 0, coalesce((SELECT max(b.t_end_ns) FROM sample_blocks b WHERE b.machine_pk = "
        "m.id), 0), 1, :empty, 0, 0 FROM machines m WHERE true ORDER BY m.machine_id "
        "ON CONFLICT (machine_id, level_s, t0_ns) DO UPDATE SET n = analytics_windows.n + 1, "
        f"t1_ns = {greatest}(analytics_windows.t1_ns, excluded.t1_ns)"), {"empty": b""})


def column(machine_id: ColumnElement[str] | InstrumentedAttribute[str]) -> ScalarSelect[int]:
    """The version as a scalar subquery of ``machine_id``, a column of the outer statement
    (read together with the newest block end: :meth:`cranetwin.storage.Store.get_machine`);
    NULL when 0."""
    return aw.counter(machine_id, LEVEL).scalar_subquery()


def read(session: Session, machine_id: str) -> int:
    """The machine's version (0 when no late block was ever stored)."""
    got = session.execute(aw.counter(machine_id, LEVEL)).scalar()
    return int(got) if got is not None else 0


__all__ = ["LEVEL", "bump_all", "column", "note", "read"]
