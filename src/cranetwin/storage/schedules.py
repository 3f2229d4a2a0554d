"""Service schedules: maintenance items a planner sets per machine, each with an interval on one
basis (operating hours, lifts, damage fraction or calendar days) and when it was last done.

``service_schedules`` has one row per (machine, item). ``last_done_value`` is the basis' counter
when the item was last done (hours, lifts, damage; for ``calendar_days`` the days since the
epoch of ``last_done_s``), ``last_done_s`` the time [s since the epoch]. ``due_raised_s`` is set
when the ``service_due`` event of the current interval was stored (``due_event_id``), and cleared
when the item is marked done: the claim and the event are written in one transaction, so the
event is raised once per due item however many workers look. Revision
``0005_service_schedules``.

Functions take a SQLAlchemy ``Session`` (the caller commits), like :mod:`cranetwin.storage.alarms`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from sqlalchemy import (
    Float,
    ForeignKey,
    Integer,
    String,
    UniqueConstraint,
    func,
    select,
    update,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.storage.analytics_windows import AnalyticsWindowRow
from cranetwin.storage.base import Base
from cranetwin.storage.events import EventRow
from cranetwin.storage.machines import MachineRow

BASES: tuple[str, ...] = ("operating_hours", "lifts", "damage_fraction", "calendar_days")


class ServiceScheduleRow(Base):
    """One maintenance item of one machine."""

    __tablename__ = "service_schedules"
    __table_args__ = (UniqueConstraint("machine_pk", "item",
                                       name="uq_service_schedules_machine_pk_item"),)

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    machine_pk: Mapped[int] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    item: Mapped[str] = mapped_column(String(200))
    basis: Mapped[str] = mapped_column(String(32))
    interval: Mapped[float] = mapped_column(Float)
    detail: Mapped[str | None] = mapped_column(String(128), nullable=True)
    last_done_value: Mapped[float] = mapped_column(Float)
    last_done_s: Mapped[float] = mapped_column(Float)
    last_done_by: Mapped[str | None] = mapped_column(String(200), nullable=True)
    created_s: Mapped[float] = mapped_column(Float)
    created_by: Mapped[str] = mapped_column(String(200))
    due_raised_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    due_event_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


@dataclass(frozen=True)
class Schedule:
    """A stored maintenance item (see :class:`ServiceScheduleRow`).

    Attributes:
        schedule_id: Row id.
        machine_id: Machine identifier.
        item: Name of the maintenance item (unique per machine).
        basis: One of :data:`BASES`.
        interval: Interval in the basis' unit (h, lifts, damage, days).
        detail: Fatigue detail of a ``damage_fraction`` item (None: the most damaged one).
        last_done_value: The basis' counter when last done.
        last_done_s: When last done [s since the epoch].
        last_done_by: Who marked it done (None: nobody since it was set).
        created_s: When the item was set [s since the epoch].
        created_by: Who set it.
        due_raised_s: When its ``service_due`` event was raised (None: not yet this interval).
        due_event_id: That event's id.
    """

    schedule_id: int
    machine_id: str
    item: str
    basis: str
    interval: float
    detail: str | None
    last_done_value: float
    last_done_s: float
    last_done_by: str | None
    created_s: float
    created_by: str
    due_raised_s: float | None = None
    due_event_id: int | None = None


def _schedule(r: ServiceScheduleRow, machine_id: str) -> Schedule:
    return Schedule(r.id, machine_id, r.item, r.basis, r.interval, r.detail, r.last_done_value,
                    r.last_done_s, r.last_done_by, r.created_s, r.created_by, r.due_raised_s,
                    r.due_event_id)


def _pk(session: Session, machine_id: str) -> int | None:
    return session.scalar(select(MachineRow.id).where(MachineRow.machine_id == machine_id))


def list_schedules(session: Session, machine_id: str | None = None) -> list[Schedule]:
    """Items of one machine (None: of every machine), by machine and item name."""
    stmt = (select(ServiceScheduleRow, MachineRow.machine_id)
            .join(MachineRow, MachineRow.id == ServiceScheduleRow.machine_pk)
            .order_by(MachineRow.machine_id, ServiceScheduleRow.item))
    if machine_id is not None:
        stmt = stmt.where(MachineRow.machine_id == machine_id)
    return [_schedule(r, mid) for r, mid in session.execute(stmt).all()]


def get_schedule(session: Session, machine_id: str, item: str) -> Schedule | None:
    """One item, or None."""
    return next((s for s in list_schedules(session, machine_id) if s.item == item), None)


def put_schedule(session: Session, s: Schedule) -> Schedule | None:
    """Create or replace the item ``s.item`` of ``s.machine_id`` (``schedule_id``,
    ``due_raised_s`` and ``due_event_id`` of ``s`` are ignored; replacing keeps the row's id and
    its creator, and re-arms the due event). None when the machine is unknown."""
    pk = _pk(session, s.machine_id)
    if pk is None:
        return None
    row = session.scalar(select(ServiceScheduleRow).where(
        ServiceScheduleRow.machine_pk == pk, ServiceScheduleRow.item == s.item))
    if row is None:
        row = ServiceScheduleRow(machine_pk=pk, item=s.item, created_s=s.created_s,
                                 created_by=s.created_by)
        session.add(row)
    row.basis, row.interval, row.detail = s.basis, s.interval, s.detail
    row.last_done_value, row.last_done_s, row.last_done_by = (s.last_done_value, s.last_done_s,
                                                              s.last_done_by)
    row.due_raised_s, row.due_event_id = None, None
    session.flush()
    return _schedule(row, s.machine_id)


def mark_done(session: Session, machine_id: str, item: str, value: float, t_s: float,
              by: str) -> Schedule | None:
    """Record the item done at counter ``value`` and time ``t_s`` by ``by``; its next due event
    may be raised again. None when there is no such item."""
    pk = _pk(session, machine_id)
    if pk is None:
        return None
    row = session.scalar(select(ServiceScheduleRow).where(
        ServiceScheduleRow.machine_pk == pk, ServiceScheduleRow.item == item))
    if row is None:
        return None
    row.last_done_value, row.last_done_s, row.last_done_by = value, t_s, by
    row.due_raised_s, row.due_event_id = None, None
    session.flush()
    return _schedule(row, machine_id)


def delete_schedule(session: Session, machine_id: str, item: str) -> bool:
    """Delete an item; False when there was none."""
    pk = _pk(session, machine_id)
    if pk is None:
        return False
    row = session.scalar(select(ServiceScheduleRow).where(
        ServiceScheduleRow.machine_pk == pk, ServiceScheduleRow.item == item))
    if row is None:
        return False
    session.delete(row)
    session.flush()
    return True


def raise_due(session: Session, schedule_id: int, t_s: float, severity: str,
              evidence: dict[str, Any], now_s: float) -> int | None:
    """Store the ``service_due`` event of an item, once per interval: claims the item (sets
    ``due_raised_s`` where it is unset) and inserts the event in the caller's transaction.

    Returns:
        The new event's id, or None when the item's event was raised already (or the item is
        gone).
    """
    claim = session.execute(update(ServiceScheduleRow).where(
        ServiceScheduleRow.id == schedule_id, ServiceScheduleRow.due_raised_s.is_(None))
        .values(due_raised_s=now_s))
    if int(getattr(claim, "rowcount", 0) or 0) != 1:
        return None
    pk = session.scalar(select(ServiceScheduleRow.machine_pk)
                        .where(ServiceScheduleRow.id == schedule_id))
    dialect = session.get_bind().dialect.name
    ins = postgresql.insert(EventRow) if dialect == "postgresql" else sqlite.insert(EventRow)
    event_id = None
    for k in range(10):  # an event of this time exists (an earlier interval): 1 ms later
        stmt = ins.values(machine_pk=pk, t_ns=int(round(t_s * 1e9)) + k * 1_000_000,
                          kind="service_due", severity=severity,
                          evidence_json=json.dumps(evidence)
                          ).on_conflict_do_nothing(index_elements=["machine_pk", "t_ns", "kind"]
                                                   ).returning(EventRow.id)
        event_id = session.scalar(stmt)
        if event_id is not None:
            break
    if event_id is None:
        return None
    session.execute(update(ServiceScheduleRow).where(ServiceScheduleRow.id == schedule_id)
                    .values(due_event_id=int(event_id)))
    return int(event_id)


def operating_seconds(session: Session, machine_id: str, t0_s: float, t1_s: float) -> float:
    """Operating time the twin worker counted in its minute windows inside [t0_s, t1_s) [s]."""
    w = AnalyticsWindowRow
    v = session.scalar(select(func.sum(w.operating_s)).where(
        w.machine_id == machine_id, w.level_s == 60, w.t0_ns >= int(round(t0_s * 1e9)),
        w.t1_ns <= int(round(t1_s * 1e9))))
    return float(v or 0.0)
