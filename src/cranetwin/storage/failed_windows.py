"""Spans the twin worker processed without an analytics part: their replay or their analytics
failed (an error of the twin or of the analytics for those samples, logged and counted in
``cranetwin_worker_errors``).

The worker moves its progress mark past such a span (one bad stretch of data must not stop a
machine), so the span is processed but has no part. A later change of its input (a known
payload stored or deleted for it, :mod:`cranetwin.storage.redo`; late samples) must retry it
as it redoes the spans that have a part: the payload may be what the replay lacked, and a
retried span must not count its windows or its operating time a second time. So the failure
is recorded, in the transaction that moves the progress mark past it, as one row of
``analytics_windows`` at level :data:`FAILED_LEVEL` per span: ``t0_ns``/``t1_ns`` the span
[start, end), ``n`` the windows and ``operating_s``/``idle_s`` the operating and idle time the
progress counted for it (0 s when the replay failed: no time was counted). A redo of the span
replaces those counts, as it does a part's
(:meth:`cranetwin.service.worker.TwinWorker.process_window`), and deletes the row in the
transaction that stores the span's part; a redo that fails again records it again (with what
is counted then). A span with fewer than 8 samples is not replayed and not recorded: no
payload can change that, and late samples redo it anyway.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import Engine, select
from sqlalchemy.orm import Session

from cranetwin.storage import analytics_windows as aw

FAILED_LEVEL = -6
"""``level_s`` of a failed span (``-1`` duty to date, ``-2`` commit-order mark, ``-3`` lift
seconds, ``-4`` redo request, ``-5`` known-payload version, ``0`` block mark)."""


def failed_row(machine_id: str, w0: float, w1: float, windows: int, operating_s: float,
               idle_s: float) -> dict[str, Any]:
    """The row recording that span [w0, w1) [s] has no part, with what the progress counted
    for it: ``windows`` windows (0 when none), operating and idle time [s]
    (:func:`cranetwin.storage.analytics_windows.put_rows` stores or replaces it)."""
    return aw.window_row(machine_id, FAILED_LEVEL, w0, w1, windows, b"", operating_s, idle_s)


def failed_spans(engine: Engine, machine_id: str, t0_s: float,
                 t1_s: float) -> list[tuple[float, float]]:
    """The failed spans inside [t0_s, t1_s): (start s, end s), oldest first."""
    return [(a, b) for a, b, _, _ in aw.windows(engine, machine_id, FAILED_LEVEL, t0_s, t1_s)]


def counted(engine: Engine, machine_id: str, w0: float) -> tuple[int, float, float] | None:
    """What the progress counted for the failed span starting at ``w0`` [s]: (windows,
    operating s, idle s); None when no failed span starts there."""
    w = aw.AnalyticsWindowRow
    with Session(engine) as s:
        r = s.execute(select(w.n, w.operating_s, w.idle_s).where(
            w.machine_id == machine_id, w.level_s == FAILED_LEVEL,
            w.t0_ns == round(w0 * aw.SEC))).first()
    return None if r is None else (int(r[0]), float(r[1]), float(r[2]))


def clear(session: Session, machine_id: str, w0: float) -> None:
    """Delete the failed span starting at ``w0`` [s] (if any), in the caller's transaction
    (the one storing its part)."""
    aw.delete_window(session, machine_id, FAILED_LEVEL, w0)


__all__ = ["FAILED_LEVEL", "clear", "counted", "failed_row", "failed_spans"]
