"""Stored analytics parts: per machine and window, what the analyses need to merge exactly.

One row per (machine, level, window start): ``level`` is the window length in seconds (60 for
the twin worker's minutes, 3600 and 86400 for roll-ups), ``data`` the serialised
:class:`cranetwin.analytics.AnalyticsPart` (the service writes and reads it; see
:mod:`cranetwin.service.history`), ``n`` the samples it covers. Writing a window again (a redone
window) replaces it. Plain functions over an engine, so the storage core is not touched.
"""

from __future__ import annotations

from sqlalchemy import BigInteger, Engine, Integer, LargeBinary, String, delete, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Mapped, Session, mapped_column

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


def _ns(t_s: float) -> int:
    return int(round(t_s * SEC))


def put_window(engine: Engine, machine_id: str, level_s: int, t0_s: float, t1_s: float, n: int,
               data: bytes) -> None:
    """Store (or replace) the part of window [t0_s, t1_s) of ``level_s``."""
    row = {"machine_id": machine_id, "level_s": level_s, "t0_ns": _ns(t0_s), "t1_ns": _ns(t1_s),
           "n": n, "data": data}
    ins = (postgresql.insert(AnalyticsWindowRow) if engine.dialect.name == "postgresql"
           else sqlite.insert(AnalyticsWindowRow))
    stmt = ins.values(**row).on_conflict_do_update(
        index_elements=["machine_id", "level_s", "t0_ns"],
        set_={"t1_ns": row["t1_ns"], "n": n, "data": data})
    with Session(engine) as s, s.begin():
        s.execute(stmt)


def windows(engine: Engine, machine_id: str, level_s: int, t0_s: float,
            t1_s: float) -> list[tuple[float, float, int, bytes]]:
    """Windows of ``level_s`` inside [t0_s, t1_s): ``(t0 s, t1 s, n, data)``, oldest first."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns, w.t1_ns, w.n, w.data)
            .where(w.machine_id == machine_id, w.level_s == level_s, w.t0_ns >= _ns(t0_s),
                   w.t1_ns <= _ns(t1_s)).order_by(w.t0_ns))
    with Session(engine) as s:
        return [(a / SEC, b / SEC, int(n), bytes(d)) for a, b, n, d in s.execute(stmt)]


def window_starts(engine: Engine, machine_id: str, level_s: int, t0_s: float,
                  t1_s: float) -> list[float]:
    """Start times of the stored windows of ``level_s`` inside [t0_s, t1_s) [s]."""
    w = AnalyticsWindowRow
    stmt = (select(w.t0_ns).where(w.machine_id == machine_id, w.level_s == level_s,
                                  w.t0_ns >= _ns(t0_s), w.t1_ns <= _ns(t1_s)).order_by(w.t0_ns))
    with Session(engine) as s:
        return [a / SEC for a in s.scalars(stmt)]


def delete_windows(engine: Engine, machine_id: str, t0_s: float, t1_s: float) -> int:
    """Drop every window (all levels) that overlaps [t0_s, t1_s) (its data changed)."""
    w = AnalyticsWindowRow
    with Session(engine) as s, s.begin():
        res = s.execute(delete(w).where(w.machine_id == machine_id, w.t0_ns < _ns(t1_s),
                                        w.t1_ns > _ns(t0_s)))
        return int(getattr(res, "rowcount", 0) or 0)
