"""The report's content as plain tables (header + rows of strings or numbers).

One place decides what a report says; the PDF, HTML and CSV writers only lay it out.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cranetwin.analytics import AnalyticsReport, range_histogram
from cranetwin.model import Machine

Row = list[str | float | int]


@dataclass(frozen=True)
class Table:
    """A titled table."""

    title: str
    header: list[str]
    rows: list[Row]


def when(t_s: float) -> str:
    """UTC date and time of an epoch time, e.g. ``2023-11-14 06:00:00``."""
    if not np.isfinite(t_s):
        return "never"
    try:
        return dt.datetime.fromtimestamp(t_s, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")
    except (OverflowError, OSError, ValueError):
        return "beyond 9999"


def _range_end(rep: AnalyticsReport) -> float:
    """End of the requested range (dates of the projections count from it)."""
    return rep.basis.range_t1_s if rep.basis is not None else rep.t_end


def _date_after(rep: AnalyticsReport, days: float) -> str:
    if not np.isfinite(days):
        return "never at this rate"
    return when(_range_end(rep) + days * 86400.0)[:10]


def fmt(x: float, digits: int = 3) -> str:
    """A number with ``digits`` significant digits."""
    if isinstance(x, float) and not np.isfinite(x):
        return "inf" if x > 0 else "n/a"
    return f"{x:.{digits}g}"


def summary(rep: AnalyticsReport, machine: Machine, source: str) -> Table:
    """Headline figures."""
    c = rep.classification
    worst = max(rep.life, key=lambda e: e.damage, default=None)
    rows: list[Row] = [
        ["Machine", machine.name],
        ["Data source", source],
        ["Requested range (UTC)",
         f"{when(rep.basis.range_t0_s)} to {when(rep.basis.range_t1_s)} (end exclusive)"
         if rep.basis is not None else "whole source"],
        ["Data (UTC)", f"{when(rep.t_start)} to {when(rep.t_end)}"],
        ["Samples analysed", f"{rep.n_samples:,}"],
        ["Recorded / working / idle time [h]",
         f"{rep.recorded_s / 3600:.1f} / {rep.working_s / 3600:.1f} / {rep.idle_s / 3600:.1f}"],
        ["Work cycles", len(rep.cycles)],
        ["Events (critical)", f"{len(rep.events)} "
                              f"({sum(e.severity == 'critical' for e in rep.events)})"],
    ]
    if c is not None:
        rows.append(["Projected group (design)", f"{c.label} ({c.design_group or '-'})"])
    if worst is not None:
        rows.append(["Most damaged detail", f"{worst.name}: D = {worst.damage:.3g}"])
        soon = min(rep.life, key=lambda e: e.next_service_days)
        rows.append(["Next service (earliest damage step)",
                     f"{_date_after(rep, soon.next_service_days)} ({soon.name}, "
                     f"D = {soon.next_service_damage:.2g})"])
    if rep.basis is not None:
        rows.append(["Rate basis (remaining life, next service, U class)",
                     rep.basis.description])
    priors = [a for a in rep.assumptions if a.startswith("Prior")]
    rows.append(["Prior damage / prior equivalent cycles",
                 "taken as zero (no earlier record)" if all("taken as zero" in a for a in priors)
                 else "carried in from earlier records (see Assumptions)"])
    return Table("Summary", ["item", "value"], rows)


def assumptions(rep: AnalyticsReport) -> Table:
    """Every assumption the figures rest on (fatigue details, prior damage, design class,
    rate basis)."""
    return Table("Assumptions", ["#", "assumption"],
                 [[i + 1, a] for i, a in enumerate(rep.assumptions)])


def usage(rep: AnalyticsReport) -> Table:
    """Per-day usage."""
    rows: list[Row] = []
    for day, u in sorted(rep.days.items()):
        rows.append([when(day * 86400.0)[:10], round(u.recorded_s / 3600, 2),
                     round(u.working_s / 3600, 2),
                     round(u.working_s / u.recorded_s, 3) if u.recorded_s else 0.0,
                     u.cycles, round(u.payload_kg / 1000, 2)])
    return Table("Usage per day", ["date", "recorded h", "working h", "utilisation",
                                   "work cycles", "payload t"], rows)


def spectra(rep: AnalyticsReport, bins: int = 10) -> Table:
    """Load spectra: rainflow cycles per range class (``bins`` equal classes up to the max)."""
    rows: list[Row] = []
    for s in rep.spectra:
        tab = s.cycles
        if tab.count.size == 0:
            continue
        top = float(tab.ranges.max()) or 1.0
        edges = np.linspace(0.0, top * (1 + 1e-9), bins + 1)
        h = range_histogram(tab, edges)
        for lo, hi, n in zip(edges[:-1], edges[1:], h, strict=True):
            rows.append([s.channel, s.unit, round(float(lo), 1), round(float(hi), 1),
                         round(float(n), 1)])
    return Table("Load spectra (rainflow, ASTM E1049)",
                 ["channel", "unit", "range from", "range to", "cycles"], rows)


def cycle_rows(rep: AnalyticsReport) -> Table:
    """Every rainflow from-to class with its count (the full cycle table)."""
    rows: list[Row] = []
    for s in rep.spectra:
        t = s.cycles
        for lo, hi, r, m, n in zip(t.lower.tolist(), t.upper.tolist(), t.ranges.tolist(),
                                   t.means.tolist(), t.count.tolist(), strict=True):
            rows.append([s.channel, s.unit, lo, hi, r, m, n])
    return Table("Rainflow cycles", ["channel", "unit", "lower_level", "upper_level", "range",
                                     "mean", "count"], rows)


def damage(rep: AnalyticsReport, machine: Machine) -> Table:
    """Miner damage, remaining life and next service per detail."""
    details = {d.name: d for d in machine.fatigue}
    rows: list[Row] = []
    for e in rep.life:
        d = details[e.name]
        rows.append([e.name, d.load, d.detail_category_mpa, d.slope_m, fmt(e.equivalent_range_mpa),
                     fmt(e.damage), fmt(e.damage_rate_per_day * 365.25),
                     fmt(e.remaining_days / 365.25), _date_after(rep, e.next_service_days)])
    return Table("Fatigue damage (Palmgren-Miner, EN 13001-3-1 S-N)",
                 ["detail", "load", "Δσc MPa", "m", "Δσeq(2e6) MPa", "damage D", "D per year",
                  "remaining years", "next service (D step)"], rows)


def duty(rep: AnalyticsReport) -> Table:
    """ISO 4301-1 classification and ISO 12482 duty record with formula and inputs."""
    rows: list[Row] = []
    c, d = rep.classification, rep.duty
    if c is not None:
        rows += [["Working cycles C (observed)", c.cycles],
                 ["kp = Σ (C_i/C_T)·(P_i/P_max)³", fmt(c.kp)],
                 ["Spectrum class", f"Q{c.q_class} / L{c.q_class}"],
                 ["Cycles projected to design life", f"{c.projected_cycles:,.0f}"],
                 ["Class of utilisation", f"U{c.u_class}"],
                 ["Group (ISO 4301-1 Table 3)", f"A{c.group} (design {c.design_group or '-'})"]]
    if d is not None:
        rows += [["ISO 12482 recording method", "a (automatic recorder, cannot be switched off)"],
                 ["Formula", d.formula],
                 ["S = Σ C_i·(P_i/P_max)³ (full-load equivalent cycles)",
                  fmt(d.equivalent_cycles, 5)],
                 ["Design C_T", f"{d.design_cycles:,.0f}"],
                 ["Design kp", fmt(d.design_kp)],
                 ["C_T·kp", f"{d.design_equivalent:,.0f}"],
                 ["Used design working period S/(C_T·kp)", f"{100 * d.used_fraction:.4g} %"]]
        rate = (rep.basis.per_day(d.equivalent_cycles - d.prior_equivalent)
                if rep.basis is not None
                else d.equivalent_cycles / max(rep.observed_days, 1e-9))
        if rate > 0:
            rows.append(["Design working period reached (at this rate)",
                         _date_after(rep, (d.design_equivalent - d.equivalent_cycles) / rate)])
    return Table("Duty class and used design working period", ["quantity", "value"], rows)


def events(rep: AnalyticsReport, limit: int | None = None) -> Table:
    """Events with their evidence."""
    rows: list[Row] = []
    for e in rep.events[:limit]:
        ev = "; ".join(f"{k}={when(v) if k.startswith('t_') else fmt(v, 4)}"
                       for k, v in e.evidence.items())
        rows.append([when(e.t_start), e.kind, e.severity, e.component, fmt(e.value, 4),
                     fmt(e.limit, 4), e.unit, ev])
    return Table("Events", ["time (UTC)", "kind", "severity", "component", "value", "limit",
                            "unit", "evidence"], rows)


def work_cycles(rep: AnalyticsReport) -> Table:
    """Every detected work cycle."""
    rows: list[Row] = [[when(c.t_grab), round(c.t_release - c.t_grab, 2), round(c.payload_kg, 1),
                        round(c.load_ratio, 4) if np.isfinite(c.load_ratio) else "unknown",
                        int(c.lift), int(c.swing), round(c.reach_max_m, 3)]
                       for c in rep.cycles]
    return Table("Work cycles", ["grab (UTC)", "loaded s", "payload kg", "load ratio", "lift",
                                 "swing", "max reach m"], rows)


def productivity(rep: AnalyticsReport) -> Table:
    """Productivity figures."""
    n = len(rep.cycles)
    complete = sum(c.complete for c in rep.cycles)
    moved = sum(c.payload_kg for c in rep.cycles)
    return Table("Productivity", ["quantity", "value"], [
        ["Work cycles (complete: grab, lift, swing, release)", f"{n} ({complete})"],
        ["Payload moved [t]", f"{moved / 1000:.1f}"],
        ["Payload per working hour [t/h]", f"{rep.payload_per_working_hour_kg / 1000:.2f}"],
        ["Mean cycle time [s]", fmt(rep.mean_cycle_time_s)],
        ["Mean payload per cycle [kg]", fmt(moved / n if n else float("nan"))],
        ["Utilisation (working / recorded)", f"{100 * rep.utilisation:.1f} %"],
    ])


def schedule(items: Sequence[Any]) -> Table:
    """The service schedule: each maintenance item, its interval, when last done, the counter
    now and when it is due (value, estimated date) — the
    :class:`cranetwin.service.schedules.DueStatus` of each item."""
    rows: list[Row] = []
    for d in items:
        s = d.schedule
        unit = d.unit or "damage"
        due_date = when(d.due_at_s) if d.due_at_s is not None else "–"
        rows.append([s.item, f"{s.basis} ({unit})" + (f", {d.detail}" if d.detail else ""),
                     fmt(s.interval, 4), f"{fmt(s.last_done_value, 4)} ({when(s.last_done_s)})",
                     "–" if d.current is None else fmt(d.current, 4), fmt(d.due_at, 4),
                     due_date, "–" if d.remaining is None else fmt(d.remaining, 4), d.status])
    return Table("Service schedule", ["item", "basis", "interval", "last done (UTC)", "now",
                                      "due at", "due (UTC, estimated)", "remaining", "status"],
                 rows)
