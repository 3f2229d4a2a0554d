"""The chaos schedule of ``cranetwin bench chaos`` in CI, shortened except for the database
outage (60 s): real daemon and sender processes, 20 % and 30 % loss with duplication and
reordering, a poisoning machine beside a bystander, kill -9 of the daemon and of a sender, the
database unavailable. Every journaled sample is stored exactly once and nothing acked is missing;
the timing figures (retransmission ratio, bystander latency) are the benchmark's, not asserted
here."""

from __future__ import annotations

import pytest

from conftest import pg_unreachable_reason
from cranetwin.bench.chaos import Schedule, run_chaos


@pytest.mark.slow
@pytest.mark.timeout(420)
@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgresql",
                                                         marks=pytest.mark.postgres)])
def test_chaos_schedule_loses_doubles_and_falsely_acks_nothing(kind: str) -> None:
    if kind == "postgresql" and (reason := pg_unreachable_reason()):
        pytest.skip(reason)
    out = run_chaos(kind, Schedule(machines=2, ratio_s=5.0, probe_s=3.0, chaos_s=20.0,
                                   outage_s=60.0, drain_s=150.0))
    assert out["drained"], out
    assert out["sent"] > 2 * (5 + 20) * 100  # the chaos machines plus the bystander
    assert (out["lost"], out["doubled"], out["acked_not_stored"]) == (0, 0, 0), out
    assert out["stored"] == out["sent"] and out["machines_mismatched"] == 0, out
    assert out["poison_datagrams_sent"] > 0 and out["poison_samples_stored"] == 0, out
    # the faults really happened
    assert out["proxy_30"]["dropped"] > 0 and out["proxy_30"]["duplicated"] > 0
    assert out["proxy_30"]["delayed"] > 0 and out["proxy_20"]["dropped"] > 0
    assert out["retransmitted"] > 0 and out["daemon_kills"] == 1
    refused = out["daemon_dropped_phases_1_2"]
    assert sum(refused.get(r, 0) for r in ("bad_time", "out_of_range", "oversize",
                                           "bad_seq")) > 0, refused
