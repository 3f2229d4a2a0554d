"""Ranges whose derived data the twin worker must compute again: a known payload stored or
deleted for samples it may already have processed.

The twin worker finds samples stored behind its progress mark by its block mark
(:func:`cranetwin.storage.analytics_windows.new_blocks_before`, late data). A known payload
(:mod:`cranetwin.storage.payloads`) changes no sample block, so storing or deleting one also
records the time range it changes here, in the same transaction: one row of
``analytics_windows`` (where the worker keeps its other marks) at level :data:`REDO_LEVEL` per
range, ``t0_ns``/``t1_ns`` its first and last changed time [ns] (both inclusive, like a
block's ``t_start_ns``/``t_end_ns``), ``n`` a version raised by every request on the same
start. The worker treats each range like a late block (its windows, and those whose replay
margin reaches into it, are redone: :meth:`cranetwin.service.worker.TwinWorker._redo_late`)
and then deletes the rows it read, each only if its version is still the one read: a request
recorded while the redo ran stays and is redone at the next pass. A range ahead of the
worker's mark needs nothing (its windows are replayed with the payload when they come) and is
deleted the same way.

Changed times less than :data:`MERGE_GAP_NS` apart are recorded as one range: an import of
blocks with a payload makes one row per stretch of blocks, not one per block.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from sqlalchemy import Engine, and_, delete, func, or_, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from cranetwin.storage.analytics_windows import SEC, AnalyticsWindowRow

REDO_LEVEL = -4
"""``level_s`` of a redo request (``-1`` duty to date, ``-2`` commit-order mark, ``-3`` lift
seconds, ``0`` block mark)."""
MERGE_GAP_NS = 60 * SEC
"""Changed times at most this far apart [ns] are requested as one range."""


@dataclass(frozen=True)
class RedoRequest:
    """A range of one machine to process again.

    Attributes:
        t0_ns: First changed time [ns since the Unix epoch].
        t1_ns: Last changed time [ns] (inclusive; ≥ ``t0_ns``).
        version: Raised by every request recorded on the same ``t0_ns``.
    """

    t0_ns: int
    t1_ns: int
    version: int

    @property
    def span_s(self) -> tuple[float, float]:
        """(first, last) changed time [s since the Unix epoch]."""
        return self.t0_ns / SEC, self.t1_ns / SEC


def merged(spans_ns: Iterable[tuple[int, int]], gap_ns: int = MERGE_GAP_NS
           ) -> list[tuple[int, int]]:
    """``spans_ns`` [(first, last) ns, inclusive] sorted and joined where at most ``gap_ns``
    apart."""
    out: list[tuple[int, int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in spans_ns):
        if out and a - out[-1][1] <= gap_ns:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def request(session: Session, machine_id: str, spans_ns: Iterable[tuple[int, int]]) -> int:
    """Record that the derived data of ``spans_ns`` [(first, last) ns, inclusive] must be
    computed again, inside the caller's transaction (the one storing or deleting the payload);
    returns the rows written. A request on a start already recorded widens it to the larger
    end and raises its version."""
    spans = merged(spans_ns)
    if not spans:
        return 0
    w = AnalyticsWindowRow
    dialect = session.connection().dialect.name
    ins = (postgresql.insert(w) if dialect == "postgresql" else sqlite.insert(w)).values(
        [{"machine_id": machine_id, "level_s": REDO_LEVEL, "t0_ns": a, "t1_ns": b, "n": 1,
          "data": b"", "operating_s": 0.0, "idle_s": 0.0} for a, b in spans])
    bigger = (func.greatest if dialect == "postgresql" else func.max)(w.t1_ns,
                                                                     ins.excluded.t1_ns)
    session.execute(ins.on_conflict_do_update(
        index_elements=["machine_id", "level_s", "t0_ns"],
        set_={"t1_ns": bigger, "n": w.n + 1}))
    return len(spans)


def pending(engine: Engine, machine_ids: Sequence[str]) -> dict[str, list[RedoRequest]]:
    """The requests of ``machine_ids`` (one statement per 1000 machines): machine → requests,
    oldest start first (machines without any left out)."""
    w = AnalyticsWindowRow
    out: dict[str, list[RedoRequest]] = {}
    ids = list(machine_ids)
    with Session(engine) as s:
        for i in range(0, len(ids), 1000):
            for mid, a, b, n in s.execute(
                    select(w.machine_id, w.t0_ns, w.t1_ns, w.n)
                    .where(w.machine_id.in_(ids[i:i + 1000]), w.level_s == REDO_LEVEL)
                    .order_by(w.machine_id, w.t0_ns)):
                out.setdefault(str(mid), []).append(RedoRequest(int(a), int(b), int(n)))
    return out


def done(engine: Engine, machine_id: str, requests: Sequence[RedoRequest]) -> int:
    """Delete ``requests`` of a machine that still have the version read (module docstring);
    returns how many were."""
    if not requests:
        return 0
    w = AnalyticsWindowRow
    with Session(engine) as s, s.begin():
        res = s.execute(delete(w).where(
            w.machine_id == machine_id, w.level_s == REDO_LEVEL,
            or_(*[and_(w.t0_ns == r.t0_ns, w.n == r.version) for r in requests])))
        return int(getattr(res, "rowcount", 0) or 0)


__all__ = ["MERGE_GAP_NS", "REDO_LEVEL", "RedoRequest", "done", "merged", "pending", "request"]
