"""Load-history analytics: rainflow spectra, Miner damage, duty class, events, productivity.

Pure functions and small state objects over numpy arrays. This package imports only numpy,
``cranetwin.model`` and ``cranetwin.errors`` (never fastapi, sqlalchemy or sockets; a test checks
it). Input: :class:`LoadHistory`. Batch: :func:`analyse`; incremental: :class:`AnalyticsState`.
Formulas and standards: docs/ANALYTICS.md.
"""

from __future__ import annotations

from cranetwin.analytics.classification import (
    Classification,
    DutyRecord,
    classify,
    duty_record,
    group,
    spectrum_class,
    spectrum_factor,
    utilisation_class,
)
from cranetwin.analytics.events import KINDS, Event, EventConfig, EventDetector
from cranetwin.analytics.fatigue import (
    LifeEstimate,
    cycles_to_failure,
    equivalent_stress_range_mpa,
    life_estimate,
    miner_damage,
)
from cranetwin.analytics.history import LoadHistory
from cranetwin.analytics.productivity import (
    DayUsage,
    ProductivityConfig,
    ProductivityTracker,
    WorkCycle,
)
from cranetwin.analytics.rainflow import (
    CycleTable,
    RainflowCounter,
    four_point,
    rainflow,
    range_histogram,
    turning_points,
)
from cranetwin.analytics.state import (
    AnalyticsConfig,
    AnalyticsPart,
    AnalyticsReport,
    AnalyticsState,
    RateBasis,
    Spectrum,
    analyse,
    assumptions,
    default_class_widths,
    load_channels,
    rate_basis,
)

__all__ = [
    "KINDS",
    "AnalyticsConfig",
    "AnalyticsPart",
    "AnalyticsReport",
    "AnalyticsState",
    "Classification",
    "CycleTable",
    "DayUsage",
    "DutyRecord",
    "Event",
    "EventConfig",
    "EventDetector",
    "LifeEstimate",
    "LoadHistory",
    "ProductivityConfig",
    "ProductivityTracker",
    "RainflowCounter",
    "RateBasis",
    "Spectrum",
    "WorkCycle",
    "analyse",
    "assumptions",
    "classify",
    "cycles_to_failure",
    "default_class_widths",
    "duty_record",
    "equivalent_stress_range_mpa",
    "four_point",
    "group",
    "life_estimate",
    "load_channels",
    "miner_damage",
    "rainflow",
    "range_histogram",
    "rate_basis",
    "spectrum_class",
    "spectrum_factor",
    "turning_points",
    "utilisation_class",
]
