"""Events of one machine page by page, filtered by kind and severity (keyset paging)."""

from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy import and_, or_, select
from sqlalchemy.orm import Session

from cranetwin.storage.blocks import clamp_ns
from cranetwin.storage.events import Event, EventRow, to_event
from cranetwin.storage.machines import get_row


def _ns(t_s: float) -> int:
    x = float(t_s) * 1e9
    return clamp_ns(round(x) if abs(x) < 2.0**63 else x)


def events_page(session: Session, machine_id: str, t0_s: float, t1_s: float, *,
                kinds: Sequence[str] | None = None, severities: Sequence[str] | None = None,
                after: tuple[int, int] | None = None,
                limit: int = 1000) -> list[tuple[int, int, Event]]:
    """Events with t0_s ≤ t < t1_s, oldest first (by time, then row id), at most ``limit``.

    Args:
        session: An ORM session on the store's engine.
        machine_id: The machine.
        t0_s, t1_s: The range [s since the epoch].
        kinds, severities: Keep only these (None: all).
        after: ``(t_ns, id)`` of the last event of the previous page: start after it.
        limit: Most events returned.

    Returns:
        ``(t_ns, id, event)`` per event; the last one's ``(t_ns, id)`` is the next ``after``.

    Raises:
        UnknownMachineError: No such machine.
    """
    pk = get_row(session, machine_id).id
    stmt = select(EventRow).where(EventRow.machine_pk == pk, EventRow.t_ns >= _ns(t0_s),
                                  EventRow.t_ns < _ns(t1_s))
    if kinds is not None:
        stmt = stmt.where(EventRow.kind.in_(list(kinds)))
    if severities is not None:
        stmt = stmt.where(EventRow.severity.in_(list(severities)))
    if after is not None:
        t, i = after
        stmt = stmt.where(or_(EventRow.t_ns > t, and_(EventRow.t_ns == t, EventRow.id > i)))
    stmt = stmt.order_by(EventRow.t_ns, EventRow.id).limit(limit)
    return [(int(r.t_ns), int(r.id), to_event(machine_id, r)) for r in session.scalars(stmt)]
