"""The analytics benchmark runs on a tiny input and its pure-Python baseline counts the same
cycles as the analytics (timings are never asserted)."""

from __future__ import annotations

import numpy as np

from cranetwin.analytics import RainflowCounter
from cranetwin.bench.analytics import _py_rainflow, run


def test_pure_python_baseline_counts_the_same_closed_cycles() -> None:
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.normal(size=20_000))
    c = RainflowCounter(0.5)
    c.update(y)
    assert _py_rainflow(y.tolist(), 0.5) == c._closed.total


def test_bench_reports_its_figures() -> None:
    res = run(days=1, rate_hz=2.0, baseline_hours=0.05, pdf=False)
    assert res["hours"] == 8.0
    assert res["samples_per_channel"] == 8 * 3600 * 2
    for key in ("wall_seconds", "samples_per_second", "speedup", "cpu_seconds",
                "baseline_pure_python_rainflow_scaled_cpu_seconds"):
        assert res[key] > 0
    assert res["work_cycles"] == 600
