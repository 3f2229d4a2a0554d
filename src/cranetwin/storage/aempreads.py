"""Reads for the ISO 15143-3 (AEMP 2.0) feed: each machine's reported hour meter with its time
and metadata, and the twin worker's operating and idle time per minute window."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

from cranetwin.storage.analytics_windows import SEC, AnalyticsWindowRow
from cranetwin.storage.machines import MachineRow

MINUTE_LEVEL = 60


@dataclass(frozen=True)
class StatusRow:
    """What a machine reported in its newest status, and its metadata.

    Attributes:
        operating_hours: The machine's hour meter [h], or None if it never reported one.
        status_s: Time of the newest status report [s since the epoch], or None.
        metadata: The machine's metadata (``name``, ``pin``, ``serial_number``,
            ``registered_t_s``, ``location_t_s``, ...).
    """

    operating_hours: float | None
    status_s: float | None
    metadata: dict[str, Any] = field(default_factory=dict)


def status_rows(engine: Engine, machine_ids: list[str]) -> dict[str, StatusRow]:
    """:class:`StatusRow` of each of ``machine_ids`` that is registered (one query)."""
    m = MachineRow
    with Session(engine) as s:
        rows = s.execute(select(m.machine_id, m.operating_hours, m.status_ns, m.meta_json)
                         .where(m.machine_id.in_(machine_ids))).all()
    return {mid: StatusRow(None if h is None else float(h), None if t is None else t / SEC,
                           json.loads(meta or "{}"))
            for mid, h, t, meta in rows}


def minute_times(engine: Engine, machine_id: str, t0_s: float,
                 t1_s: float) -> list[tuple[float, float, float, float]]:
    """The twin worker's minute windows ending in (t0_s, t1_s]: ``(start s, end s, operating s,
    idle s)``, oldest first."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns, w.t1_ns, w.operating_s, w.idle_s)
            .where(w.machine_id == machine_id, w.level_s == MINUTE_LEVEL,
                   w.t1_ns > round(t0_s * SEC), w.t1_ns <= round(t1_s * SEC))
            .order_by(w.t0_ns))
    with Session(engine) as s:
        return [(a / SEC, b / SEC, float(o), float(i)) for a, b, o, i in s.execute(stmt)]


def times_until(engine: Engine, machine_id: str, t_s: float) -> tuple[float, float]:
    """(operating s, idle s) of the minute windows ending at or before ``t_s``."""
    w = AnalyticsWindowRow
    with Session(engine) as s:
        o, i = s.execute(select(func.coalesce(func.sum(w.operating_s), 0.0),
                                func.coalesce(func.sum(w.idle_s), 0.0))
                         .where(w.machine_id == machine_id, w.level_s == MINUTE_LEVEL,
                                w.t1_ns <= round(t_s * SEC))).one()
    return float(o), float(i)
