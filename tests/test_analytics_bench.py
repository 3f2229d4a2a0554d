"""``cranetwin bench analytics`` on a tiny input: its JSON is well formed and complete, its
baselines are measured in the same run and count what the analytics count, its ratios follow
from the times it reports, and its results match the synthetic crane's truth. Timings are never
asserted: speed targets are met in the benchmark itself, not in unit tests."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.analytics import RainflowCounter
from cranetwin.bench.analytics import _py_rainflow
from cranetwin.cli import app
from cranetwin.model import load_machine
from cranetwin.testing.histories import CYCLE_S, SyntheticCrane

pytestmark = pytest.mark.timeout(300)

DAYS, RATE_HZ, BASELINE_H = 1, 2.0, 0.05

# every figure the benchmark reports, with its type
KEYS: dict[str, type | tuple[type, ...]] = {
    "hours": float, "days": int, "rate_hz": float, "samples_per_channel": int,
    "load_channels": int, "wall_seconds": float, "cpu_seconds": float,
    "samples_per_second": int, "cpu_samples_per_second": int,
    "report_pdf_seconds": (float, type(None)), "report_pdf_cpu_seconds": (float, type(None)),
    "report_total_seconds": float, "report_total_cpu_seconds": float,
    "generate_seconds_not_counted": float, "peak_rss_mib": float,
    "baseline_hours_measured": float,
    "baseline_pure_python_rainflow_scaled_cpu_seconds": float,
    "baseline_fatpack_rainflow_scaled_cpu_seconds": float,
    "ours_rainflow_only_scaled_cpu_seconds": float,
    "rainflow_speedup_vs_pure_python": float, "rainflow_speedup_vs_fatpack": float,
    "speedup": float, "work_cycles": int, "events": int, "kp": (float, type(None)),
    "max_damage": float,
}


def _no_nan(token: str) -> Any:
    raise AssertionError(f"{token} in the JSON output (not valid JSON)")


@pytest.fixture(scope="module")
def figures() -> dict[str, Any]:
    r = CliRunner().invoke(app, ["bench", "analytics", "--json", "--days", str(DAYS),
                                 "--rate-hz", str(RATE_HZ), "--baseline-hours", str(BASELINE_H),
                                 "--no-pdf"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output, parse_constant=_no_nan)
    assert isinstance(out, dict)
    return out


def _ratio_consistent(ratio: float, ratio_decimals: int, num: float, num_decimals: int,
                      den: float, den_decimals: int) -> bool:
    """``ratio`` (rounded) is num / den for some unrounded num and den that round to the
    reported ``num`` and ``den``: interval arithmetic over the rounding of each figure."""
    hn, hd, hr = (0.5 * 10.0 ** -d for d in (num_decimals, den_decimals, ratio_decimals))
    lo = max(num - hn, 0.0) / (den + hd)
    hi = (num + hn) / (den - hd) if den > hd else math.inf
    return lo - hr <= ratio <= hi + hr


def test_bench_json_has_every_figure_with_its_type(figures: dict[str, Any]) -> None:
    assert set(figures) == set(KEYS)
    for key, kind in KEYS.items():
        value = figures[key]
        assert isinstance(value, kind) and not isinstance(value, bool), (key, value)
    assert figures["report_pdf_seconds"] is None  # --no-pdf: not measured, not NaN


def test_bench_input_is_what_was_asked(figures: dict[str, Any]) -> None:
    assert figures["days"] == DAYS and figures["rate_hz"] == RATE_HZ
    assert figures["hours"] == 8.0 * DAYS
    assert figures["samples_per_channel"] == int(8 * 3600 * RATE_HZ) * DAYS
    assert figures["load_channels"] == 7


def test_bench_rates_follow_from_the_reported_times(figures: dict[str, Any]) -> None:
    n = figures["samples_per_channel"]
    assert figures["wall_seconds"] > 0 and figures["cpu_seconds"] > 0
    # the times are reported to the millisecond, the rates from the unrounded times: they agree
    # within what that rounding allows (0.5 ms of the time), plus the rates' own rounding
    for rate, secs in (("samples_per_second", "wall_seconds"),
                       ("cpu_samples_per_second", "cpu_seconds")):
        t = figures[secs]
        assert n / (t + 0.0005) - 1 <= figures[rate] <= n / max(t - 0.0005, 1e-9) + 1, rate
    assert figures["report_total_seconds"] == figures["wall_seconds"]
    assert figures["report_total_cpu_seconds"] == figures["cpu_seconds"]


def test_bench_baselines_are_measured_in_the_run_and_ratios_are_consistent(
        figures: dict[str, Any]) -> None:
    assert figures["baseline_hours_measured"] == BASELINE_H
    py = figures["baseline_pure_python_rainflow_scaled_cpu_seconds"]
    fp = figures["baseline_fatpack_rainflow_scaled_cpu_seconds"]
    ours = figures["ours_rainflow_only_scaled_cpu_seconds"]
    assert py > 0 and fp > 0 and ours > 0
    # ratios come from unrounded times; scaled seconds are reported to 0.01 s, cpu to 0.001 s
    assert _ratio_consistent(figures["rainflow_speedup_vs_pure_python"], 1, py, 2, ours, 2)
    assert _ratio_consistent(figures["rainflow_speedup_vs_fatpack"], 1, fp, 2, ours, 2)
    assert _ratio_consistent(figures["speedup"], 2, py, 2, figures["cpu_seconds"], 3)


def test_bench_results_match_the_synthetic_truth(figures: dict[str, Any]) -> None:
    crane = SyntheticCrane(load_machine("patu655"), seed=0, days=DAYS)
    shift_s = crane.shift_bounds(0)[1] - crane.shift_bounds(0)[0]
    complete = [k for k in range(crane.cycles_per_shift) if (k + 1) * CYCLE_S <= shift_s]
    work = sum(1 for k in complete if not crane._idle[k]) * DAYS
    assert figures["work_cycles"] == work
    assert figures["kp"] is not None and 0.0 < figures["kp"] <= 1.0
    assert 0.0 < figures["max_damage"] < 1.0


def test_pure_python_baseline_counts_the_same_closed_cycles() -> None:
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.normal(size=20_000))
    c = RainflowCounter(0.5)
    c.update(y)
    assert _py_rainflow(y.tolist(), 0.5) == c._closed.total > 1000


def test_pure_python_baseline_counts_a_known_sequence() -> None:
    # reversals 0, 3, 1, 2, 0, 3 with width 1: the inner range 1→2 closes one cycle
    assert _py_rainflow([0.0, 3.0, 1.0, 2.0, 0.0, 3.0], 1.0) == 1
    assert _py_rainflow([0.0, 3.0, 1.0, 2.0, 0.0], 1.0) == 0  # 1→2 not yet closed
    assert _py_rainflow([0.0, 1.0, 2.0, 3.0], 1.0) == 0


STORED_KEYS = {"days", "shift_h", "rate_hz", "stored_hours", "samples", "write_seconds",
               "worker_windows", "worker_seconds", "worker_seconds_per_window",
               "report_2d_seconds", "report_2d_cpu_seconds", "direct_range_hours",
               "merged_range_seconds", "direct_range_seconds", "speedup_vs_direct",
               "equal_to_direct", "work_cycles", "events", "kp", "max_damage",
               "remaining_years_worst", "peak_rss_mib",
               "export_samples", "export_samples_per_second",
               "export_inprocess_samples_per_second", "export_inprocess_cpu_samples_per_second",
               "export_inprocess_csv_samples_per_second", "export_read_samples_per_second",
               "baseline_export_per_block_read_samples_per_second",
               "baseline_json_pages_samples_per_second",
               *(f"export_http_{f}_{k}" for f in ("parquet", "csv")
                 for k in ("rows", "seconds", "samples_per_second",
                           "server_cpu_samples_per_second", "client_cpu_seconds", "walls")),
               "export_cli_rows", "export_cli_seconds", "export_cli_samples_per_second",
               "export_cli_cpu_seconds", "export_cli_export_seconds",
               "export_cli_export_samples_per_second"}


def test_stored_benchmark_merges_what_the_worker_stored() -> None:
    r = CliRunner().invoke(app, ["bench", "analytics", "--stored", "--json", "--days", "2",
                                 "--shift-h", "0.05", "--direct-hours", "0.02",
                                 "--export-runs", "1"])
    assert r.exit_code == 0, r.output
    j = json.loads(r.output.strip().splitlines()[-1], parse_constant=_no_nan)
    assert set(j) == STORED_KEYS
    assert j["equal_to_direct"] is True  # the merged report of the range equals replaying it
    assert j["samples"] == 2 * (180 + 5) * 100  # both shifts, every sample, through the worker
    # the export streamed every stored sample (all channels), and each rate is a real rate
    assert j["export_samples"] > 0 and j["export_samples"] % j["samples"] == 0
    for key in ("export_samples_per_second", "export_inprocess_samples_per_second",
                "export_inprocess_cpu_samples_per_second",
                "export_inprocess_csv_samples_per_second", "export_read_samples_per_second",
                "baseline_export_per_block_read_samples_per_second",
                "baseline_json_pages_samples_per_second", "export_cli_samples_per_second",
                "export_cli_export_samples_per_second",
                *(f"export_http_{f}_{k}" for f in ("parquet", "csv")
                  for k in ("samples_per_second", "server_cpu_samples_per_second"))):
        assert j[key] > 0, key
    # every stored sample came through HTTP (both formats) and the CLI, counted from the files
    for key in ("export_http_parquet_rows", "export_http_csv_rows", "export_cli_rows"):
        assert j[key] == j["export_samples"], key
    assert j["export_samples_per_second"] == j["export_http_parquet_samples_per_second"]
    assert j["worker_windows"] == 2 * 4
    assert j["speedup_vs_direct"] == pytest.approx(
        j["direct_range_seconds"] / j["merged_range_seconds"], rel=0.06, abs=0.06)
    assert j["work_cycles"] > 0 and j["kp"] is not None
