"""Exports of the load-history analytics: PDF, self-contained HTML and CSV.

:func:`build_report` folds a :class:`~cranetwin.reports.sources.Source` into an
:class:`~cranetwin.analytics.AnalyticsState`; :func:`~cranetwin.reports.writers.write` lays the
result out. See docs/ANALYTICS.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cranetwin.analytics import AnalyticsConfig, AnalyticsReport, AnalyticsState
from cranetwin.errors import ReportError
from cranetwin.reports.sources import (
    DemoSource,
    RecordingSource,
    Source,
    StoreSource,
    history_from_recording,
    history_from_twin,
)
from cranetwin.reports.writers import FORMATS, SECTIONS, check_format, csv_tables, render, write


def build_report(source: Source, config: AnalyticsConfig | None = None,
                 progress: Callable[[int], None] | None = None, t0_s: float | None = None,
                 t1_s: float | None = None) -> AnalyticsReport:
    """Analyse every chunk of ``source`` (only instants with t0_s ≤ t < t1_s if given);
    ``progress(units)`` is called after each chunk.

    Rates (remaining life, next service, class of utilisation) follow
    :class:`cranetwin.analytics.RateBasis`: the machine's whole recorded history gives the
    operating hours per day when the source knows it (``history_usage()``, storage), else the
    requested range [t0_s, t1_s) does (the data span when no range is given).

    Raises:
        ReportError: No data in the window.
    """
    lo = -np.inf if t0_s is None else t0_s
    hi = np.inf if t1_s is None else t1_s
    merged = getattr(source, "range_state", None)
    if callable(merged):  # storage: merged from stored parts, only the edges replayed
        merged_state: AnalyticsState = merged(config)
        if progress is not None:
            progress(source.total())
        if merged_state.n_samples == 0:
            raise ReportError(f"no data from {source.label} in the window {lo} s to {hi} s "
                              "(epoch seconds); check --from/--to")
        usage_fn = getattr(source, "history_usage", None)
        usage = usage_fn() if callable(usage_fn) else None
        r0 = t0_s if t0_s is not None else getattr(source, "t0_s", None)
        r1 = t1_s if t1_s is not None else getattr(source, "t1_s", None)
        return merged_state.report(r0, r1, *(usage if usage is not None else (None, None)))
    state = AnalyticsState(source.machine, config)
    for h, units in source.chunks():
        if h is not None and h.n:
            a, b = np.searchsorted(h.t_s, [lo, hi], side="left")
            if b > a:
                state.update(h.slice(int(a), int(b)))
        if progress is not None and units:
            progress(units)
    if state.n_samples == 0:
        raise ReportError(f"no data from {source.label} in the window {lo} s to {hi} s "
                          "(epoch seconds); check --from/--to")
    usage_fn = getattr(source, "history_usage", None)
    usage = usage_fn() if callable(usage_fn) else None
    return state.report(t0_s, t1_s, *(usage if usage is not None else (None, None)))


__all__ = ["FORMATS", "SECTIONS", "DemoSource", "RecordingSource", "Source", "StoreSource",
           "build_report", "check_format", "csv_tables", "history_from_recording",
           "history_from_twin", "render", "write"]
