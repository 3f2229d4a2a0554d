"""Exports of the load-history analytics: PDF, self-contained HTML and CSV.

:func:`build_report` folds a :class:`~cranetwin.reports.sources.Source` into an
:class:`~cranetwin.analytics.AnalyticsState`; :func:`~cranetwin.reports.writers.write` lays the
result out. See docs/ANALYTICS.md.
"""

from __future__ import annotations

from collections.abc import Callable

from cranetwin.analytics import AnalyticsConfig, AnalyticsReport, AnalyticsState
from cranetwin.reports.sources import (
    DemoSource,
    RecordingSource,
    Source,
    StoreSource,
    history_from_recording,
    history_from_twin,
)
from cranetwin.reports.writers import FORMATS, SECTIONS, csv_tables, write


def build_report(source: Source, config: AnalyticsConfig | None = None,
                 progress: Callable[[int], None] | None = None) -> AnalyticsReport:
    """Analyse every chunk of ``source``; ``progress(units)`` is called after each chunk."""
    state = AnalyticsState(source.machine, config)
    for h, units in source.chunks():
        if h is not None and h.n:
            state.update(h)
        if progress is not None and units:
            progress(units)
    return state.report()


__all__ = ["FORMATS", "SECTIONS", "DemoSource", "RecordingSource", "Source", "StoreSource",
           "build_report", "csv_tables", "history_from_recording", "history_from_twin", "write"]
