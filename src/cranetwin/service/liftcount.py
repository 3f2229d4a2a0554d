"""The twin worker's lift counters (AEMP ``CumulativeLoadCount``, payload totals, overloads,
largest lift) as a function of what is stored per minute, so late data corrects them.

With every processed minute the worker stores the seconds its lift detection sees
(:func:`cranetwin.service.derived.lift_seconds`: 1-s mean payload and the rated load at the
reach) as an ``analytics_windows`` row of level :data:`LIFT_LEVEL`, replaced when the minute is
redone. After redoing minutes for late data the counters are folded again over the stored
seconds of the whole processed history (:func:`recount`): a lift detected across minutes
(:func:`cranetwin.service.derived.fold_lifts`) that the late samples split, joined or changed is
counted as a fresh processing of the history counts it, once. The cost is one read of the
machine's stored seconds (16 bytes per processed second) per pass that redid minutes.
"""

from __future__ import annotations

from dataclasses import replace as dc_replace
from typing import TYPE_CHECKING, Any

import numpy as np

from cranetwin.model import Machine
from cranetwin.service.derived import F64, fold_lifts, rated_max_kg
from cranetwin.storage import analytics_windows as aw

if TYPE_CHECKING:
    from cranetwin.service.backend import Progress

LIFT_LEVEL = -3
"""``level_s`` of a minute's lift seconds (``-1`` duty to date, ``-2`` commit-order mark)."""
MINUTE_S = 60


def seconds_row(machine_id: str, w0: float, w1: float, means: F64,
                rated_at: F64) -> dict[str, Any]:
    """The row of the lift seconds of minute [w0, w1) (:func:`cranetwin.storage.
    analytics_windows.put_rows` stores or replaces it)."""
    data = np.concatenate([means, rated_at]).astype("<f8").tobytes()
    return aw.window_row(machine_id, LIFT_LEVEL, w0, w1, int(means.size), data)


def store_seconds(engine: Any, machine_id: str, w0: float, w1: float, means: F64,
                  rated_at: F64) -> None:
    """Store (replace) the lift seconds of minute [w0, w1)."""
    from sqlalchemy.orm import Session

    with Session(engine) as s, s.begin():
        aw.put_rows(s, [seconds_row(machine_id, w0, w1, means, rated_at)])


def recount(engine: Any, machine: Machine, prog: Progress,
            threshold_kg: float) -> Progress | None:
    """``prog`` with its lift counters folded again over the stored seconds of every minute
    before its watermark; None when some processed minute has no stored seconds (processed
    before they were stored: the counters are then left as they are)."""
    from cranetwin.service.backend import Progress

    mid, until = prog.machine_id, prog.watermark_s
    rows = aw.windows(engine, mid, LIFT_LEVEL, -1e9, until)
    have = {r[0] for r in rows}
    if any(a not in have for a in aw.window_starts(engine, mid, MINUTE_S, -1e9, until)):
        return None
    fresh = Progress.empty(mid)
    rated_max = rated_max_kg(machine)
    for _a, _b, n, data in rows:
        v = np.frombuffer(data, dtype="<f8")
        fresh = fold_lifts(fresh, v[:n], v[n:2 * n], threshold_kg, rated_max)
    return dc_replace(prog, load_count=fresh.load_count,
                      payload_total_kg=fresh.payload_total_kg,
                      load_cube_sum=fresh.load_cube_sum, overloads=fresh.overloads,
                      max_payload_kg=fresh.max_payload_kg, in_lift=fresh.in_lift,
                      lift_peak_kg=fresh.lift_peak_kg, lift_peak_ratio=fresh.lift_peak_ratio)
