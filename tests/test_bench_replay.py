"""``cranetwin bench replay``: the figures it prints, on a short recording (timings are not
asserted: they belong to the benchmark, not to a unit test)."""

from __future__ import annotations

import pytest

from cranetwin.bench import replay as bench_replay


def test_replay_bench_reports_every_run_and_the_median() -> None:
    out = bench_replay.run(recording_seconds=20.0, grid_hz=1000.0, baseline_seconds_of_data=0.2,
                           repeat=3)
    for key in ("recording_seconds", "grid_hz", "wall_seconds", "real_time_factor",
                "peak_rss_mib", "cpu_seconds", "consumer_seconds", "baseline_seconds",
                "speedup"):
        assert key in out, key
    runs = out["wall_seconds_runs"]
    assert len(runs) == 3 and runs == sorted(runs)
    assert out["wall_seconds"] == runs[1]
    assert out["grid_points"] == 20 * 1000 + 1
    # wall_seconds is rounded to 1 ms: a few per cent of a 20 s replay's time
    assert out["real_time_factor"] == pytest.approx(20.0 / out["wall_seconds"], rel=0.1)
    # replayed hours per CPU-hour, of the median run, for both builds (same number of runs)
    assert len(out["cpu_seconds_runs"]) == len(out["generic_cpu_seconds_runs"]) == 3
    assert out["cpu_seconds"] == sorted(out["cpu_seconds_runs"])[1]
    assert out["generic_cpu_seconds"] == sorted(out["generic_cpu_seconds_runs"])[1]
    assert out["machine_hours_per_core_hour"] == pytest.approx(20.0 / out["cpu_seconds"],
                                                               rel=0.05)
    assert out["baseline_machine_hours_per_core_hour"] == pytest.approx(
        20.0 / out["generic_cpu_seconds"], rel=0.05)


def test_replay_bench_rejects_no_runs() -> None:
    with pytest.raises(ValueError, match="repeat"):
        bench_replay.run(recording_seconds=5.0, repeat=0)
