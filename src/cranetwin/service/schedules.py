"""Service schedules: maintenance items per machine, due by operating hours, lifts, damage
fraction or calendar days — what is due when (no HTTP here).

A planner sets an item (:func:`set_schedule`) with an interval on one basis; the item is due at
``last done + interval``. The counters come from what the twin worker already stores
(:func:`usage_of`), never from a new replay:

* ``operating_hours`` — the worker's operating time (``twin_progress.operating_s``: time with
  samples, the AEMP ``CumulativeOperatingHours``) [h];
* ``lifts`` — work cycles of the machine's duty to date (:class:`~cranetwin.service.history.
  DutyToDate`: the reports' work-cycle detection folded over the stored parts) [lifts];
* ``damage_fraction`` — Palmgren–Miner damage D of a fatigue detail of the machine file
  (``[[fatigue]]``), from the stored parts of the whole processed history merged
  (:func:`~cranetwin.service.history.range_state`); the item names its ``detail``, or, without
  one, the most damaged detail at the time of the check (named in every status) [1];
* ``calendar_days`` — days since the epoch [d].

The estimated date of "due at" divides what remains by the recent rate: the counters' growth
over the last :data:`RECENT_DAYS` days of processed data (before the worker's progress mark) per
calendar day. An item is ``due`` when what remains is at most ``lead_fraction`` (10 %) of its
interval, ``overdue`` when it is below zero, else ``ok`` (``unknown``: no counter yet). The twin
worker calls :func:`check_due` after each pass over a machine: every item found due or overdue
raises one ``service_due`` event (kept with the other events, acknowledged and cleared through
the alarms), raised again only after the item is marked done (:func:`mark_done`, which clears the
event's alarm).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from cranetwin.service.errors import InvalidRequestError, NotFoundError
from cranetwin.service.timerange import iso
from cranetwin.storage import schedules as st

BASES = st.BASES
UNITS = {"operating_hours": "h", "lifts": "lifts", "damage_fraction": "", "calendar_days": "d"}
RECENT_DAYS = 7.0
LEAD_FRACTION = 0.1
DAY_S = 86400.0


@dataclass(frozen=True)
class Usage:
    """A machine's counters to date and their recent rates.

    Attributes:
        until_s: Time the counters hold for (the twin worker's progress mark) [s], or None.
        now_s: Time of the check [s since the epoch].
        values: basis → counter (``damage_fraction:<detail>`` per fatigue detail).
        rates_per_day: The same keys → growth per calendar day over the recent days.
    """

    until_s: float | None
    now_s: float
    values: dict[str, float] = field(default_factory=dict)
    rates_per_day: dict[str, float] = field(default_factory=dict)

    def key(self, basis: str, detail: str | None) -> str | None:
        """The counter of ``basis`` (for damage: of ``detail``, or the most damaged detail)."""
        if basis != "damage_fraction":
            return basis if basis in self.values else None
        if detail is not None:
            k = f"damage_fraction:{detail}"
            return k if k in self.values else None
        dmg = {k: v for k, v in self.values.items() if k.startswith("damage_fraction:")}
        return max(dmg, key=lambda k: dmg[k]) if dmg else None


@dataclass(frozen=True)
class DueStatus:
    """What is due when for one item.

    Attributes:
        schedule: The stored item.
        detail: The fatigue detail used (damage items), else None.
        unit: Unit of the values (h, lifts, "" for damage, d).
        current: The counter now (None: unknown).
        due_at: The counter at which the item is due.
        remaining: ``due_at − current`` (negative: overdue).
        due_at_s: Estimated time the item is due [s since the epoch] (None: no recent rate).
        rate_per_day: Recent growth of the counter per calendar day.
        status: ``ok``, ``due``, ``overdue`` or ``unknown``.
    """

    schedule: st.Schedule
    detail: str | None
    unit: str
    current: float | None
    due_at: float
    remaining: float | None
    due_at_s: float | None
    rate_per_day: float | None
    status: str


def due_status(s: st.Schedule, usage: Usage, lead_fraction: float = LEAD_FRACTION) -> DueStatus:
    """Due state of item ``s`` with the counters ``usage`` (pure)."""
    k = usage.key(s.basis, s.detail)
    detail = k.split(":", 1)[1] if k is not None and s.basis == "damage_fraction" else s.detail
    due_at = s.last_done_value + s.interval
    if k is None:
        return DueStatus(s, detail, UNITS[s.basis], None, due_at, None, None, None, "unknown")
    cur = usage.values[k]
    rate = usage.rates_per_day.get(k)
    remaining = due_at - cur
    base = usage.now_s if s.basis == "calendar_days" else (usage.until_s or usage.now_s)
    when: float | None = None
    if s.basis == "calendar_days":
        when = due_at * DAY_S
    elif remaining <= 0:
        when = None
    elif rate is not None and rate > 0:
        when = base + remaining / rate * DAY_S
    status = ("overdue" if remaining < 0 else "due" if remaining <= lead_fraction * s.interval
              else "ok")
    return DueStatus(s, detail, UNITS[s.basis], cur, due_at, remaining, when, rate, status)


def _date(t_s: float | None) -> str | None:
    """:func:`iso`, None for an instant no calendar date holds (beyond the year 9999: a due
    date extrapolated from a slow rate, or a very long interval)."""
    try:
        return iso(t_s)
    except (ValueError, OverflowError, OSError):
        return None


def status_json(d: DueStatus) -> dict[str, Any]:
    """A due status in the API's shape (times as ISO 8601 UTC; a due date past the year 9999
    is null)."""
    s = d.schedule

    def num(x: float | None) -> float | None:
        return None if x is None or not math.isfinite(x) else float(x)
    return {
        "item": s.item, "basis": s.basis, "interval": s.interval, "unit": d.unit,
        "detail": d.detail,
        "last_done": {"value": s.last_done_value, "at": iso(s.last_done_s), "by": s.last_done_by},
        "created": {"at": iso(s.created_s), "by": s.created_by},
        "current": num(d.current), "due_at": {"value": d.due_at, "at": _date(d.due_at_s)},
        "remaining": num(d.remaining), "rate_per_day": num(d.rate_per_day), "status": d.status,
        "event_id": s.due_event_id,
    }


# -- counters from stored analytics --------------------------------------------------------------

def usage_of(backend: Any, machine_id: str, bases: set[str] | None = None,
             now_s: float | None = None) -> Usage:
    """The counters of ``machine_id`` for ``bases`` (default: all) from stored state."""
    from cranetwin.service.history import range_state, stored_duty

    now = time.time() if now_s is None else now_s
    want = set(BASES) if bases is None else bases
    values: dict[str, float] = {"calendar_days": now / DAY_S}
    rates: dict[str, float] = {"calendar_days": 1.0}
    prog = backend.progress(machine_id)
    dr = backend.data_range(machine_id)
    if prog is None or dr is None:
        return Usage(None, now, values, rates)
    until = float(prog.watermark_s)
    first = float(math.floor(dr[0] / 60.0) * 60.0)
    recent0 = max(first, until - RECENT_DAYS * DAY_S)
    span_d = max((until - recent0) / DAY_S, 1e-9)
    engine = backend.store.engine_for(machine_id)
    if "operating_hours" in want:
        values["operating_hours"] = prog.operating_s / 3600.0
        with backend.session(machine_id) as s:
            rates["operating_hours"] = st.operating_seconds(s, machine_id, recent0,
                                                            until) / 3600.0 / span_d
    if not want & {"lifts", "damage_fraction"} or until <= first:
        return Usage(until, now, values, rates)
    rec = backend.machine(machine_id)
    machine = backend.model_of(rec)
    if "lifts" in want:
        duty = stored_duty(engine, machine_id)
        if duty is not None:
            values["lifts"] = float(duty[0])
    recent = range_state(engine, machine, machine_id, recent0, until, lambda a, b: None, until)
    rep_recent = recent.report(recent0, until) if recent.n_samples else None
    if rep_recent is not None:
        rates["lifts"] = len(rep_recent.cycles) / span_d
    if "damage_fraction" in want and machine.fatigue:
        whole = (recent if recent0 == first else
                 range_state(engine, machine, machine_id, first, until, lambda a, b: None, until))
        if whole.n_samples:
            for life in whole.report(first, until).life:
                values[f"damage_fraction:{life.name}"] = float(life.damage)
            if rep_recent is not None:
                for life in rep_recent.life:
                    rates[f"damage_fraction:{life.name}"] = float(life.damage) / span_d
    return Usage(until, now, values, rates)


# -- planner's functions -------------------------------------------------------------------------

# the longest interval a basis may have: a fraction of the design damage, a century of days
MAX_INTERVAL = {"damage_fraction": 1.0, "calendar_days": 36525.0}


@dataclass(frozen=True)
class ScheduleInput:
    """What a planner sets for an item.

    Attributes:
        basis: One of :data:`BASES`.
        interval: Interval in the basis' unit (> 0).
        detail: Fatigue detail of a damage item (None: the most damaged).
        last_done_value: Counter when last done (None: the counter now — counted from now;
            ignored for calendar items, whose counter is the date ``last_done_s``).
        last_done_s: When last done [s since the epoch] (None: now).
    """

    basis: str
    interval: float
    detail: str | None = None
    last_done_value: float | None = None
    last_done_s: float | None = None


def _check(backend: Any, machine_id: str, inp: ScheduleInput) -> None:
    if inp.basis not in BASES:
        raise InvalidRequestError("Unknown basis", f"basis {inp.basis!r}: expected one of "
                                  f"{', '.join(BASES)}")
    if not (math.isfinite(inp.interval) and inp.interval > 0):
        raise InvalidRequestError("Bad interval", f"interval {inp.interval}: expected > 0")
    most = MAX_INTERVAL.get(inp.basis)
    if most is not None and inp.interval > most:
        raise InvalidRequestError("Bad interval", f"interval {inp.interval:g} of a "
                                  f"{inp.basis} item: expected at most {most:g}")
    if inp.detail is not None:
        if inp.basis != "damage_fraction":
            raise InvalidRequestError("Detail without damage basis",
                                      "detail is only for basis damage_fraction")
        names = [d.name for d in backend.model_of(backend.machine(machine_id)).fatigue]
        if inp.detail not in names:
            raise InvalidRequestError("Unknown fatigue detail", f"detail {inp.detail!r}: "
                                      f"expected one of {', '.join(names) or '(none)'}")


def _counter_now(backend: Any, machine_id: str, basis: str, detail: str | None,
                 t_s: float) -> float:
    """The basis' counter now (0 before the worker processed anything)."""
    if basis == "calendar_days":
        return t_s / DAY_S
    usage = usage_of(backend, machine_id, {basis}, t_s)
    k = usage.key(basis, detail)
    return usage.values[k] if k is not None else 0.0


def set_schedule(backend: Any, machine_id: str, item: str, inp: ScheduleInput, by: str,
                 now_s: float | None = None) -> dict[str, Any]:
    """Create or replace item ``item`` of the machine; returns its status.

    Raises:
        NotFoundError: Unknown machine.
        InvalidRequestError: Bad basis, interval or detail.
    """
    backend.machine(machine_id)  # NotFoundError for an unknown machine
    _check(backend, machine_id, inp)
    now = time.time() if now_s is None else now_s
    done_s = now if inp.last_done_s is None else inp.last_done_s
    value = inp.last_done_value
    if inp.basis == "calendar_days":  # the counter of a calendar item is the date
        value = done_s / DAY_S
    elif value is None:
        value = _counter_now(backend, machine_id, inp.basis, inp.detail, now)
    sch = st.Schedule(0, machine_id, item, inp.basis, float(inp.interval), inp.detail,
                      float(value), float(done_s), None, now, by)
    with backend.session(machine_id) as s, s.begin():
        st.put_schedule(s, sch)
    return _one(backend, machine_id, item, now)


def mark_done(backend: Any, machine_id: str, item: str, by: str, value: float | None = None,
              at_s: float | None = None, now_s: float | None = None) -> dict[str, Any]:
    """Record item ``item`` done (at counter ``value`` and time ``at_s``; None: now), and clear
    the alarm of its ``service_due`` event; returns its status.

    Raises:
        NotFoundError: Unknown machine or item.
    """
    from cranetwin.storage import alarms

    now = time.time() if now_s is None else now_s
    with backend.session(machine_id) as s:
        cur = st.get_schedule(s, machine_id, item)
    if cur is None:
        raise NotFoundError("Unknown service item", f"machine {machine_id} has no item {item!r}")
    t = now if at_s is None else at_s
    v = value
    if cur.basis == "calendar_days":
        v = t / DAY_S
    elif v is None:
        v = _counter_now(backend, machine_id, cur.basis, cur.detail, now)
    with backend.session(machine_id) as s, s.begin():
        st.mark_done(s, machine_id, item, float(v), float(t), by)
        if cur.due_event_id is not None:
            alarms.set_alarm_state(s, cur.due_event_id, "clear", by, now)
    return _one(backend, machine_id, item, now)


def delete_schedule(backend: Any, machine_id: str, item: str) -> None:
    """Delete item ``item``.

    Raises:
        NotFoundError: Unknown machine or item.
    """
    backend.machine(machine_id)
    with backend.session(machine_id) as s, s.begin():
        if not st.delete_schedule(s, machine_id, item):
            raise NotFoundError("Unknown service item",
                                f"machine {machine_id} has no item {item!r}")


def statuses(backend: Any, machine_id: str, now_s: float | None = None) -> list[DueStatus]:
    """Due status of every item of the machine, by item name."""
    with backend.session(machine_id) as s:
        items = st.list_schedules(s, machine_id)
    if not items:
        return []
    usage = usage_of(backend, machine_id, {i.basis for i in items}, now_s)
    return [due_status(i, usage) for i in items]


def list_schedule(backend: Any, machine_id: str, now_s: float | None = None) -> dict[str, Any]:
    """``{machine_id, until, items: [status, ...]}`` (see :func:`status_json`).

    Raises:
        NotFoundError: Unknown machine.
    """
    backend.machine(machine_id)
    items = statuses(backend, machine_id, now_s)
    prog = backend.progress(machine_id)
    return {"machine_id": machine_id,
            "counters_until": iso(prog.watermark_s) if prog is not None else None,
            "items": [status_json(d) for d in items]}


def _one(backend: Any, machine_id: str, item: str, now_s: float) -> dict[str, Any]:
    found = [d for d in statuses(backend, machine_id, now_s) if d.schedule.item == item]
    return status_json(found[0])


# -- the worker's check --------------------------------------------------------------------------

def check_due(backend: Any, machine_id: str, now_s: float | None = None) -> int:
    """Raise a ``service_due`` event for every item of the machine that is due or overdue and
    has none yet this interval; returns how many were raised.

    The event is stamped when it was found (the counters' time for hours, lifts and damage, the
    due date for calendar items), plus the item's id in microseconds, so that items found in one
    check are distinct events; severity ``warning`` when due, ``critical`` when overdue.
    """
    now = time.time() if now_s is None else now_s
    prog = backend.progress(machine_id)
    counted = prog.watermark_s if prog is not None else now
    raised = 0
    for d in statuses(backend, machine_id, now):
        s = d.schedule
        if d.status not in ("due", "overdue") or s.due_raised_s is not None:
            continue
        found = d.due_at_s if s.basis == "calendar_days" and d.due_at_s is not None else counted
        t = min(float(found), now) + s.schedule_id * 1e-6
        what = "overdue" if d.status == "overdue" else "due"
        msg = (f"service {what}: {s.item} (every {s.interval:g} {d.unit or 'damage'} of "
               f"{s.basis.replace('_', ' ')}; due at {d.due_at:.4g}, now {d.current:.4g})")
        evidence = {"message": msg, "item": s.item, "basis": s.basis, "interval": s.interval,
                    "due_at": d.due_at, "current": d.current, "status": d.status,
                    "detail": d.detail, "schedule_id": s.schedule_id, "component": s.item}
        with backend.session(machine_id) as ses, ses.begin():
            if st.raise_due(ses, s.schedule_id, t, "critical" if d.status == "overdue"
                            else "warning", evidence, now) is not None:
                raised += 1
    return raised
