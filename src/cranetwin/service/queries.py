"""Queries over stored data that replay nothing: raw samples page by page, and the moment a
condition held (coarse to fine over the stored summaries, then the exact sample).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from cranetwin.model import Machine
from cranetwin.service.backend import Backend
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
