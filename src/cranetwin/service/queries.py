"""Queries over stored data that replay nothing: raw samples page by page, the moment a
condition held (coarse to fine over the stored summaries, then the exact sample), events and
machines filtered and page by page.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from cranetwin.model import Machine
from cranetwin.service.backend import Backend, MachineRecord
from cranetwin.service.errors import InvalidRequestError
from cranetwin.service.timerange import TimeRange, parse_time
from cranetwin.service.worker import derived_channels


@dataclass(frozen=True)
class SamplesPage:
    """One page of raw samples: ``values`` (len(t), len(channels)) in channel units, None =
    missing; ``next_cursor`` continues the paging (None: done)."""

    channels: list[str]
    t: list[float]
    values: list[list[float | None]]
    next_cursor: str | None


@dataclass(frozen=True)
class Moment:
    """When a condition held (``t`` [s]) and the value there; both None when it never held."""

    t: float | None
    value: float | None


def check_channels(machine: Machine, names: list[str]) -> None:
    """Refuse channel names that are neither raw channels of ``machine`` nor derived ones.

    Raises:
        InvalidRequestError: Unknown names (the message lists the known ones).
    """
    raw = [c.name for c in machine.channels]
    derived = derived_channels(machine)
    bad = [n for n in names if n not in raw and n not in derived]
    if bad:
        raise InvalidRequestError(
            "Unknown channel", f"{', '.join(repr(b) for b in bad)}: expected raw channels "
            f"({', '.join(raw)}) or derived ones ({', '.join(derived)})")


def samples_page(backend: Backend, machine_id: str, rng: TimeRange, limit: int,
                 cursor: str | None, nominal_rate_hz: float) -> SamplesPage:
    """One page of raw samples in [from, to) (≤ ``limit``; next page from ``next_cursor``).

    Gaps of any length are skipped with one index probe (the start of the next stored
    block), so paging never stops early: ``next_cursor`` is null only when no sample is
    left in [cursor, to).

    Args:
        backend: Store adapter.
        machine_id: The machine.
        rng: [from, to).
        limit: Most samples in the page.
        cursor: ``next_cursor`` of the previous page, or None for the first.
        nominal_rate_hz: Expected sample rate [Hz] (sizes the first read).

    Raises:
        InvalidRequestError: The cursor is not a time inside [from, to).
    """
    start = rng.t0_s
    if cursor is not None:
        c = parse_time(cursor, "cursor")
        if not rng.t0_s <= c <= rng.t1_s:
            raise InvalidRequestError("Invalid cursor",
                                      f"cursor {cursor!r} is outside [from, to)")
        start = c
    mid = machine_id
    first = backend.next_sample_time(mid, start)  # a leading gap: skipped at once
    if first is None or first >= rng.t1_s:
        return SamplesPage(channels=[], t=[], values=[], next_cursor=None)
    start = max(start, first)
    span = limit / nominal_rate_hz * 1.1 + 1.0
    t = np.zeros(0)
    vals = np.zeros((0, 0))
    channels: tuple[str, ...] = ()
    while True:
        end = min(rng.t1_s, start + span)
        s = backend.read_samples(mid, start, end)
        t, vals, channels = s.t_s, s.values, s.channels
        keep = t < rng.t1_s
        t, vals = t[keep], vals[keep]
        if t.shape[0] > limit or end >= rng.t1_s or span > 400 * 86400.0:
            break
        span *= 4.0
    nxt = None
    if t.shape[0] > limit:
        nxt = repr(float(t[limit]))
        t, vals = t[:limit], vals[:limit]
    elif end < rng.t1_s:  # a page short of ``limit`` before a long gap: continue after it
        more = backend.next_sample_time(mid, end)
        if more is not None and more < rng.t1_s:
            nxt = repr(float(max(more, end)))
    v = np.where(np.isfinite(vals), vals, np.nan)
    return SamplesPage(channels=list(channels), t=t.tolist(),
                       values=[[None if not math.isfinite(x) else x for x in row]
                               for row in v.tolist()],
                       next_cursor=nxt)


def find_moment(backend: Backend, machine: Machine, machine_id: str, rng: TimeRange,
                channel: str, op: Literal["gt", "lt"], value: float,
                which: Literal["first", "last"]) -> Moment:
    """First/last time ``channel`` op ``value`` held in [from, to).

    Coarse-to-fine over the summaries: a bucket whose max (min) does not pass cannot hold a
    passing value, so the search narrows to the first (last) passing bucket, then to the
    finest summaries inside it, then (raw channels) to the exact sample.
    """
    t0, t1 = rng.t0_s, rng.t1_s
    finest = backend.finest_interval_s()
    hit: tuple[float, float, float] | None = None
    for _ in range(6):
        t, lo, hi, _mean = backend.summaries(machine_id, [channel], t0, t1,
                                                  2000)[channel]
        if t.shape[0] == 0:
            return Moment(t=None, value=None)
        ext = hi if op == "gt" else lo
        ok = np.isfinite(ext) & ((ext > value) if op == "gt" else (ext < value))
        if not ok.any():
            if hit is None:
                return Moment(t=None, value=None)
            break
        i = int(np.argmax(ok)) if which == "first" else int(len(ok) - 1 - np.argmax(ok[::-1]))
        width = float(np.median(np.diff(t))) if t.shape[0] > 1 else finest
        hit = (float(t[i]), float(ext[i]), width)
        t0, t1 = max(rng.t0_s, float(t[i])), min(rng.t1_s, float(t[i]) + width)
        if width <= finest * 1.0001:
            break
    assert hit is not None
    if channel in {c.name for c in machine.channels}:
        s = backend.read_samples(machine_id, t0, t1 + 1e-9)
        if s.t_s.shape[0] and channel in s.channels:
            col = s.column(channel)
            inside = (s.t_s >= rng.t0_s) & (s.t_s < rng.t1_s)
            ok = inside & np.isfinite(col) & ((col > value) if op == "gt" else (col < value))
            if ok.any():
                idx = np.flatnonzero(ok)
                j = int(idx[0] if which == "first" else idx[-1])
                return Moment(t=float(s.t_s[j]), value=float(col[j]))
    return Moment(t=max(hit[0], rng.t0_s), value=hit[1])


# -- events page by page -----------------------------------------------------------------------
@dataclass(frozen=True)
class EventsPage:
    """Events of a range, one page: contract dicts ``{t, kind, severity, message, evidence}``,
    oldest first; ``next_cursor`` continues (None: no more)."""

    events: list[dict[str, Any]]
    next_cursor: str | None


_EVENT_CURSOR = re.compile(r"^(-?\d{1,19}):(\d{1,19})$")


def events_page(backend: Backend, machine_id: str, rng: TimeRange, *,
                kinds: list[str] | None = None, severities: list[str] | None = None,
                limit: int = 1000, cursor: str | None = None) -> EventsPage:
    """One page of the stored events in [from, to), filtered by kind and severity.

    Args:
        cursor: ``next_cursor`` of the previous page (opaque), or None for the first.

    Raises:
        InvalidRequestError: A malformed cursor or an unknown severity.
    """
    from cranetwin.service.backend import _message
    from cranetwin.storage.eventpages import events_page as read_page
    from cranetwin.storage.events import SEVERITIES

    after = None
    if cursor is not None:
        m = _EVENT_CURSOR.match(cursor)
        if m is None:
            raise InvalidRequestError("Invalid cursor", f"cursor {cursor!r}: pass the "
                                      "next_cursor of the previous page")
        after = (int(m.group(1)), int(m.group(2)))
    if severities is not None:
        bad = [s for s in severities if s not in SEVERITIES]
        if bad:
            raise InvalidRequestError("Unknown severity", f"{', '.join(map(repr, bad))}: "
                                      f"expected {', '.join(SEVERITIES)}")
    with backend.session(machine_id) as s:
        rows = read_page(s, machine_id, rng.t0_s, rng.t1_s, kinds=kinds, severities=severities,
                         after=after, limit=limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    out = []
    for _t, _i, e in rows:
        ev = dict(e.evidence or {})
        out.append({"t": float(e.t_s), "kind": e.kind, "severity": e.severity,
                    "message": str(ev.get("message") or _message(e.kind, ev)), "evidence": ev})
    nxt = f"{rows[-1][0]}:{rows[-1][1]}" if more and rows else None
    return EventsPage(out, nxt)


def event_pages(backend: Backend, machine_id: str, rng: TimeRange,
                page_size: int = 5000) -> Iterator[list[dict[str, Any]]]:
    """Every event of [from, to), page by page (for exports: bounded memory)."""
    cursor: str | None = None
    while True:
        page = events_page(backend, machine_id, rng, limit=page_size, cursor=cursor)
        yield page.events
        if page.next_cursor is None:
            return
        cursor = page.next_cursor


# -- machines, filtered and paged ------------------------------------------------------------------
@dataclass(frozen=True)
class MachineFilter:
    """Which machines a listing keeps.

    Attributes:
        status: Keep machines of these statuses (None: all).
        model: Keep machines of these machine description names (None: all).
        bbox: (min lon, min lat, max lon, max lat) [deg]: keep machines whose location is
            inside (edges included); machines without a location are dropped. None: all.
    """

    status: tuple[str, ...] | None = None
    model: tuple[str, ...] | None = None
    bbox: tuple[float, float, float, float] | None = None

    def keeps_record(self, rec: MachineRecord) -> bool:
        """Whether ``rec`` passes the filters that need no status."""
        if self.model is not None and rec.model not in self.model:
            return False
        if self.bbox is not None:
            if rec.location is None:
                return False
            lat, lon = rec.location[0], rec.location[1]
            lon0, lat0, lon1, lat1 = self.bbox
            if not (lat0 <= lat <= lat1 and lon0 <= lon <= lon1):
                return False
        return True


def parse_bbox(text: str | None) -> tuple[float, float, float, float] | None:
    """``"min_lon,min_lat,max_lon,max_lat"`` [deg] (the OGC/GeoJSON order) as a tuple.

    Raises:
        InvalidRequestError: Not four finite numbers in range, or min above max.
    """
    if text is None:
        return None
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != 4 or not all(math.isfinite(x) for x in v) or not (
            -180 <= v[0] <= v[2] <= 180 and -90 <= v[1] <= v[3] <= 90):
        raise InvalidRequestError("Invalid bbox", f"bbox={text!r}: expected min_lon,min_lat,"
                                  "max_lon,max_lat in degrees (min ≤ max)")
    return (v[0], v[1], v[2], v[3])


@dataclass(frozen=True)
class MachinesPage:
    """A page of machine statuses by id; ``next_cursor`` continues (None: no more);
    ``total`` counts every machine the filters keep, or None when counting would need the
    status of every machine (a status filter)."""

    items: list[Any]
    next_cursor: str | None
    total: int | None


def machines_page(records: list[MachineRecord], status_of: Callable[[MachineRecord], Any],
                  flt: MachineFilter, limit: int | None = None, offset: int = 0,
                  cursor: str | None = None) -> MachinesPage:
    """Machines (sorted by id) after the filters, from ``cursor`` (the last id of the previous
    page) or ``offset``, at most ``limit`` (None: all). ``status_of`` (the fleet's
    :meth:`~cranetwin.service.fleet.FleetService.machine_status`) runs only for machines
    that may be returned, so a small page of a large fleet is cheap."""
    recs = sorted((r for r in records if flt.keeps_record(r)), key=lambda r: r.machine_id)
    if cursor is not None:
        recs = [r for r in recs if r.machine_id > cursor]
    total = len(recs) if flt.status is None and cursor is None else None
    items: list[Any] = []
    skipped = 0
    more = False
    last: str | None = None
    for r in recs:
        if flt.status is None and skipped < offset:
            skipped += 1
            continue
        if flt.status is None and limit is not None and len(items) >= limit:
            more = True
            break
        st = status_of(r)
        if flt.status is not None and st.status not in flt.status:
            continue
        if skipped < offset:
            skipped += 1
            continue
        if limit is not None and len(items) >= limit:
            more = True
            break
        items.append(st)
        last = r.machine_id
    return MachinesPage(items, last if more else None, total)
