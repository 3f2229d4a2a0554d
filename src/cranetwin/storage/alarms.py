"""Alarm state of events: who acknowledged and who cleared an event, and when.

``event_alarms`` has at most one row per event (``event_id`` = ``events.id``, deleted with it):
acknowledgement and clearance times [s since the epoch, server clock] and by whom (the API key's
name and role). An event without a row is active and unacknowledged. Revision
``0003_event_alarms``.

Functions take a SQLAlchemy ``Session`` (the caller commits), like :mod:`cranetwin.storage.apikeys`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import Float, ForeignKey, Integer, String, and_, func, or_, select
from sqlalchemy.orm import Mapped, Session, mapped_column

from cranetwin.storage.base import Base
from cranetwin.storage.events import EventRow
from cranetwin.storage.machines import MachineRow

State = Literal["active", "unacknowledged", "acknowledged", "cleared", "all"]
STATES: tuple[str, ...] = ("active", "unacknowledged", "acknowledged", "cleared", "all")


class EventAlarmRow(Base):
    """The alarm state of one event."""

    __tablename__ = "event_alarms"

    event_id: Mapped[int] = mapped_column(Integer, ForeignKey("events.id", ondelete="CASCADE"),
                                          primary_key=True)
    acked_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    acked_by: Mapped[str | None] = mapped_column(String(200), nullable=True)
    cleared_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    cleared_by: Mapped[str | None] = mapped_column(String(200), nullable=True)


@dataclass(frozen=True)
class Alarm:
    """An event with its alarm state.

    Attributes:
        event_id: The event's id (``events.id``).
        machine_id: Machine identifier.
        t_s: Event time [s since the epoch].
        kind: Event kind.
        severity: ``info``, ``warning`` or ``critical``.
        evidence: The event's evidence.
        acked_s, acked_by: Acknowledged when [s since the epoch] and by whom (None: not yet).
        cleared_s, cleared_by: Cleared when and by whom (None: active).
    """

    event_id: int
    machine_id: str
    t_s: float
    kind: str
    severity: str
    evidence: dict[str, Any]
    acked_s: float | None = None
    acked_by: str | None = None
    cleared_s: float | None = None
    cleared_by: str | None = None


def _filters(machine_ids: Sequence[str] | None, severities: Sequence[str] | None,
             kinds: Sequence[str] | None, t0_s: float | None, t1_s: float | None,
             state: str) -> list[Any]:
    cond: list[Any] = []
    if machine_ids:
        cond.append(MachineRow.machine_id.in_(list(machine_ids)))
    if severities:
        cond.append(EventRow.severity.in_(list(severities)))
    if kinds:
        cond.append(EventRow.kind.in_(list(kinds)))
    if t0_s is not None:
        cond.append(EventRow.t_ns >= int(round(t0_s * 1e9)))
    if t1_s is not None:
        cond.append(EventRow.t_ns < int(round(t1_s * 1e9)))
    cleared = EventAlarmRow.cleared_s.is_not(None)
    acked = EventAlarmRow.acked_s.is_not(None)
    if state == "active":
        cond.append(or_(EventAlarmRow.event_id.is_(None), ~cleared))
    elif state == "unacknowledged":
        cond.append(or_(EventAlarmRow.event_id.is_(None), and_(~acked, ~cleared)))
    elif state == "acknowledged":
        cond.append(and_(acked, ~cleared))
    elif state == "cleared":
        cond.append(cleared)
    return cond


def list_alarms(session: Session, *, machine_ids: Sequence[str] | None = None,
                severities: Sequence[str] | None = None, kinds: Sequence[str] | None = None,
                t0_s: float | None = None, t1_s: float | None = None, state: str = "active",
                limit: int = 50, offset: int = 0) -> tuple[int, list[Alarm]]:
    """Events matching every given filter with their alarm state, newest first: (how many match
    in all, the page ``offset`` … ``offset + limit``)."""
    base = (select(EventRow, MachineRow.machine_id, EventAlarmRow)
            .join(MachineRow, MachineRow.id == EventRow.machine_pk)
            .outerjoin(EventAlarmRow, EventAlarmRow.event_id == EventRow.id))
    cond = _filters(machine_ids, severities, kinds, t0_s, t1_s, state)
    if cond:
        base = base.where(*cond)
    total = int(session.scalar(select(func.count()).select_from(base.subquery())) or 0)
    rows = session.execute(base.order_by(EventRow.t_ns.desc(), EventRow.id.desc())
                           .limit(limit).offset(offset)).all()
    return total, [_alarm(ev, mid, st) for ev, mid, st in rows]


def _alarm(ev: EventRow, machine_id: str, st: EventAlarmRow | None) -> Alarm:
    return Alarm(ev.id, machine_id, ev.t_ns / 1e9, ev.kind, ev.severity,
                 json.loads(ev.evidence_json or "{}"),
                 st.acked_s if st else None, st.acked_by if st else None,
                 st.cleared_s if st else None, st.cleared_by if st else None)


def get_alarm(session: Session, event_id: int) -> Alarm | None:
    """One event with its alarm state, or None when there is no such event."""
    row = session.execute(select(EventRow, MachineRow.machine_id, EventAlarmRow)
                          .join(MachineRow, MachineRow.id == EventRow.machine_pk)
                          .outerjoin(EventAlarmRow, EventAlarmRow.event_id == EventRow.id)
                          .where(EventRow.id == event_id)).first()
    return None if row is None else _alarm(*row)


def set_alarm_state(session: Session, event_id: int, action: Literal["acknowledge", "clear"],
                    by: str, now_s: float) -> Alarm | None:
    """Acknowledge or clear an event (clearing also acknowledges one not yet acknowledged).
    Doing it again keeps the first time and user. None when there is no such event (caller
    commits)."""
    if session.get(EventRow, event_id) is None:
        return None
    st = session.get(EventAlarmRow, event_id)
    if st is None:
        st = EventAlarmRow(event_id=event_id)
        session.add(st)
    if st.acked_s is None:
        st.acked_s, st.acked_by = now_s, by
    if action == "clear" and st.cleared_s is None:
        st.cleared_s, st.cleared_by = now_s, by
    session.flush()
    return get_alarm(session, event_id)


def kinds_in_use(session: Session) -> list[str]:
    """Every event kind stored (for the filter menus)."""
    return sorted(k for (k,) in session.execute(select(EventRow.kind).distinct()))
