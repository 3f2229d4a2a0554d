"""cranetwin bench bus: both paths run through the real commands (``cranetwin ingest``,
``cranetwin ingest --bus``, ``cranetwin store-writer``, a private ``nats-server``) and the
figures are consistent; timings are not checked."""

from __future__ import annotations

import shutil

import pytest

from test_bus import nats_unreachable_reason

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


def test_bench_bus_stores_everything_on_both_paths_and_reports_the_documented_keys() -> None:
    if shutil.which("nats-server") is None:
        pytest.skip("nats-server is not installed")
    reason = nats_unreachable_reason()  # nats-py missing or no JetStream on this host
    if reason and "nats-py" in reason:
        pytest.skip(reason)
    from cranetwin.bench.bus import run_bench

    out = run_bench(None, None, machines=4, samples=300, processes=1, speed=0.0,
                    batch_samples=50)
    assert out["samples_sent"] == 1200
    for path in ("direct", "bus"):
        got = out[path]
        assert got["all_acked"] and got["stored"] == 1200, (path, got)
        assert got["lost"] == got["duplicated"] == got["machines_mismatched"] == 0
    assert out["bus"]["store_writer"]["stored_samples"] == 1200
    assert out["bus"]["store_writer"]["refused"] == {}
    assert out["bus"]["nats_server_cpu_seconds"] is not None
    b_cpu = out["bus"]["daemon_cpu_seconds"] + out["bus"]["store_writer_cpu_seconds"]
    assert out["bus_samples_per_cpu_second"] == round(1200 / b_cpu)
    assert out["per_core_ratio_vs_direct"] == pytest.approx(
        out["bus_samples_per_cpu_second"] / out["direct_samples_per_cpu_second"], rel=0.01)
    assert out["lost"] == out["duplicated"] == 0
