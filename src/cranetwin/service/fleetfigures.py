"""Fleet-wide figures for the fleet page: working hours, lifts and tonnes lifted per machine
(the twin worker's cumulative counters) and in total, and today's alarms (events since UTC
midnight, warning or critical)."""

from __future__ import annotations

import time
from typing import Any


def fleet_figures(backend: Any, now_s: float | None = None) -> dict[str, Any]:
    """``{"machines": {id: {operating_h, lifts, tonnes}}, "total": {operating_h, lifts,
    tonnes, alarms_today, critical_today}, "day_start": epoch s}`` (``backend``:
    ``service.backend.Backend``)."""
    from cranetwin.storage.alarmshards import list_all

    now = time.time() if now_s is None else now_s
    day_start = now - now % 86400.0
    per: dict[str, dict[str, float]] = {}
    for rec in backend.list_machines():
        p = backend.progress(rec.machine_id)
        per[rec.machine_id] = {
            "operating_h": (p.operating_s / 3600.0) if p else 0.0,
            "lifts": float(p.load_count) if p else 0.0,
            "tonnes": (p.payload_total_kg / 1000.0) if p else 0.0,
        }
    engines = backend.store.engines  # every shard
    today = list_all(engines, severities=["warning", "critical"], t0_s=day_start, state="all",
                     limit=1)[0]
    critical = list_all(engines, severities=["critical"], t0_s=day_start, state="all",
                        limit=1)[0]
    total = {k: sum(m[k] for m in per.values()) for k in ("operating_h", "lifts", "tonnes")}
    return {"machines": per, "total": {**total, "alarms_today": today,
                                       "critical_today": critical}, "day_start": day_start}
