"""``cranetwin bench worker``: the figures it prints, on a few machines (timings are not
asserted: they belong to the benchmark, not to a unit test)."""

from __future__ import annotations

import pytest

from conftest import PG_URL, pg_unreachable_reason
from cranetwin.bench import worker as bench_worker


@pytest.mark.postgres
@pytest.mark.timeout(240)
def test_worker_bench_reports_each_step_and_the_line() -> None:
    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    out = bench_worker.run(machines=3, history_s=30.0, steps_s=(8.0, 20.0), passes=2,
                           threads=1, pg=PG_URL)
    assert [r["step_s"] for r in out["runs"]] == [8.0, 20.0]
    for r in out["runs"]:
        assert len(r["cpu_ms_per_machine_pass_runs"]) == 2
        assert r["cpu_ms_per_machine_pass"] > 0
        assert r["unreplayed"] == 0
        assert r["statements_per_machine_pass"] > 0
        per_minute = sum(r["cpu_ms_per_machine_pass_runs"]) * 60.0 / (2 * r["step_s"])
        assert r["cpu_ms_per_machine_minute"] == pytest.approx(per_minute, rel=0.02, abs=0.05)
    # 8 s per pass: two 4-s windows; 20 s: five (a span may stop at a whole minute)
    assert out["runs"][0]["windows_per_machine_pass"] == 2.0
    assert out["runs"][1]["windows_per_machine_pass"] == 5.0
    assert out["lag_at_end_s"] <= 4.0 + 1.0 + 1e-6  # a window and the settle time at most
    assert "fixed_ms_per_machine_pass" in out and "ms_per_machine_second" in out
