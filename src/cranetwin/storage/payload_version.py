"""A machine's known-payload version: a number raised by every change of its stored payload.

A replay depends on the known payload stored for its samples (:mod:`cranetwin.storage.
payloads`), so a result kept from an earlier replay (the API's replay cache,
:meth:`cranetwin.service.fleet.FleetService.twin_key`) is valid only while that payload is
the same. The payload may be changed by any process on the database (an import, ``cranetwin
payload delete``, another API process), so "the same" cannot be told by a message to the
process holding the result; it is told by this version, kept in the database and raised in the
transaction that changes the payload (:meth:`cranetwin.storage.Store.write_payload_runs`,
:meth:`~cranetwin.storage.Store.delete_payload`, :meth:`~cranetwin.storage.Store.
delete_payload_runs`): a result made after reading version v is valid while the version is
still v.

It is one row of ``analytics_windows`` (where the redo requests of the same change are kept,
:mod:`cranetwin.storage.redo`) per machine: level :data:`VERSION_LEVEL`, ``t0_ns`` 0, ``n``
the version (no row: version 0). Reading it is one primary-key lookup, alone (:func:`read`)
or as a column of a statement a request makes anyway (:func:`column`). The row is never
deleted (machines are not), so a version is never used twice for a machine.
"""

from __future__ import annotations

from sqlalchemy import ScalarSelect
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import InstrumentedAttribute, Session
from sqlalchemy.sql.elements import ColumnElement

from cranetwin.storage import analytics_windows as aw
from cranetwin.storage.analytics_windows import AnalyticsWindowRow

VERSION_LEVEL = -5
"""``level_s`` of the version row (``-1`` duty to date, ``-2`` commit-order mark, ``-3`` lift
seconds, ``-4`` redo request, ``0`` block mark)."""


def bump(session: Session, machine_id: str) -> None:
    """Raise the machine's version by one, inside the caller's transaction (the one changing
    its stored payload)."""
    w = AnalyticsWindowRow
    dialect = session.connection().dialect.name
    ins = (postgresql.insert(w) if dialect == "postgresql" else sqlite.insert(w)).values(
        machine_id=machine_id, level_s=VERSION_LEVEL, t0_ns=0, t1_ns=0, n=1, data=b"",
        operating_s=0.0, idle_s=0.0)
    session.execute(ins.on_conflict_do_update(index_elements=["machine_id", "level_s", "t0_ns"],
                                              set_={"n": w.n + 1}))


def column(machine_id: ColumnElement[str] | InstrumentedAttribute[str]) -> ScalarSelect[int]:
    """The version as a scalar subquery of ``machine_id``, a column of the outer statement
    (read together with it: :meth:`cranetwin.storage.Store.get_machine`); NULL when 0."""
    return aw.counter(machine_id, VERSION_LEVEL).scalar_subquery()


def read(session: Session, machine_id: str) -> int:
    """The machine's version (0 when its payload never changed)."""
    got = session.execute(aw.counter(machine_id, VERSION_LEVEL)).scalar()
    return int(got) if got is not None else 0


__all__ = ["VERSION_LEVEL", "bump", "column", "read"]
