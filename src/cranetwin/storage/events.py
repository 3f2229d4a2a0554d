"""Events found by analytics (overload, end-stop impact, over-pressure, ...), with evidence.

Unique on (machine, time, kind): writing the same event again (a replay re-run) stores it once;
a window the twin worker processes again replaces its events (:func:`replace_in`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

from sqlalchemy import (
    BigInteger,
    ForeignKey,
    Index,
    String,
    Text,
    UniqueConstraint,
    delete,
    select,
)
from sqlalchemy.orm import Mapped, mapped_column

from cranetwin.errors import StorageError
from cranetwin.storage.base import Base


class EventRow(Base):
    """One event of one machine."""

    __tablename__ = "events"
    __table_args__ = (UniqueConstraint("machine_pk", "t_ns", "kind"),
                      Index("ix_events_machine_t", "machine_pk", "t_ns"))

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    t_ns: Mapped[int] = mapped_column(BigInteger)
    kind: Mapped[str] = mapped_column(String(64))
    severity: Mapped[str] = mapped_column(String(16))
    evidence_json: Mapped[str] = mapped_column(Text, default="{}")


SEVERITIES = ("info", "warning", "critical")


@dataclass(frozen=True)
class Event:
    """An event as analytics produce it and the API shows it.

    Attributes:
        machine_id: Machine identifier.
        t_s: Event time [s since the epoch, machine clock].
        kind: e.g. ``overload``, ``end_stop_impact``, ``over_pressure``, ``overspeed``.
        severity: ``info``, ``warning`` or ``critical``.
        evidence: JSON-serialisable details (measured value, limit, channel, ...).
    """

    machine_id: str
    t_s: float
    kind: str
    severity: str = "warning"
    evidence: dict[str, Any] = field(default_factory=dict)


@lru_cache(maxsize=2)
def insert_ignoring_stored(dialect: str) -> Any:
    """The insert of event rows that skips those already stored (same machine, time, kind),
    returning the new rows' ids (execute it with a list of row dicts)."""
    from sqlalchemy.dialects import postgresql, sqlite

    ins = postgresql.insert(EventRow) if dialect == "postgresql" else sqlite.insert(EventRow)
    return ins.on_conflict_do_nothing(
        index_elements=["machine_pk", "t_ns", "kind"]).returning(EventRow.id)


def add_in(session: Any, machine_pk: int, events: list[Event]) -> int:
    """Store events of one machine inside the caller's transaction (see
    :meth:`cranetwin.storage.Store.add_events`); returns how many were new."""
    if not events:
        return 0
    for e in events:
        if e.severity not in SEVERITIES:
            raise StorageError(f"event severity {e.severity!r} must be one of {SEVERITIES}")
    from cranetwin.storage.bulk import insert_rows

    rows = [(machine_pk, int(round(e.t_s * 1e9)), e.kind, e.severity, json.dumps(e.evidence))
            for e in events]
    return len(insert_rows(session.connection(), "events", _COLUMNS, rows, _IGNORE_STORED))


def replace_in(session: Any, machine_pk: int, t0_ns: int, t1_ns: int, kinds: Sequence[str],
               events: list[Event]) -> int:
    """Store ``events`` of one machine, found anew for [t0_ns, t1_ns), inside the caller's
    transaction, and delete the events of ``kinds`` stored in that range that are not among
    them (same time and kind): a window processed again replaces its events. An event found
    again keeps its row (its id and alarm state); a deleted one takes its alarm state with it.
    Returns how many were new."""
    keep = {(int(round(e.t_s * 1e9)), e.kind) for e in events}
    r = EventRow
    stale = [int(i) for i, t, k in session.execute(
        select(r.id, r.t_ns, r.kind).where(r.machine_pk == machine_pk, r.t_ns >= t0_ns,
                                           r.t_ns < t1_ns, r.kind.in_(list(kinds))))
             if (int(t), str(k)) not in keep]
    if stale:
        session.execute(delete(r).where(r.id.in_(stale)))
    return add_in(session, machine_pk, events)


def add_many(session: Any, events: list[tuple[int, list[Event]]]) -> int:
    """:func:`add_in` of several machines, ``(machine_pk, events)`` each, in one statement."""
    rows = []
    for pk, evs in events:
        for e in evs:
            if e.severity not in SEVERITIES:
                raise StorageError(f"event severity {e.severity!r} must be one of {SEVERITIES}")
            rows.append((pk, int(round(e.t_s * 1e9)), e.kind, e.severity,
                         json.dumps(e.evidence)))
    if not rows:
        return 0
    from cranetwin.storage.bulk import insert_rows

    return len(insert_rows(session.connection(), "events", _COLUMNS, rows, _IGNORE_STORED))


_COLUMNS = ("machine_pk", "t_ns", "kind", "severity", "evidence_json")
_IGNORE_STORED = "ON CONFLICT (machine_pk, t_ns, kind) DO NOTHING RETURNING id"


def to_event(machine_id: str, row: EventRow) -> Event:
    """Public view of an event row."""
    return Event(machine_id, row.t_ns / 1e9, row.kind, row.severity, json.loads(row.evidence_json))
