"""Shock loads: the rate of change of a cylinder's load force above a per-machine threshold,
found the same way by the twin worker as data arrive (live) and by the report merged from stored
data, on a simulated load drop followed by a lift driven into its end stop.

The end stop is the case the pressures cannot show: the stop, not the oil, takes the rod's
impact (true force rate 9.4 MN/s, the pressures' force only 1.6 MN/s), so at a stroke end the
detector takes the cylinder's load by inverse dynamics."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from cranetwin.analytics import EventConfig, analyse
from cranetwin.analytics.events import relief_force_n, shock_limits_n_per_s
from cranetwin.model import load_machine, machine_from_dict
from cranetwin.reports.sources import history_from_recording, history_from_twin
from cranetwin.service.analytics import analytics_report
from cranetwin.service.backend import Backend
from cranetwin.service.replayer import Replayer
from cranetwin.service.timerange import TimeRange
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.sim import Recording, simulate
from cranetwin.sim.scenario import scenario_from_dict

MACHINE = load_machine("patu655")
MID = "crane-shock"
T0 = 1795420800.0
SCENARIO = {"name": "drop-then-end-stop", "duration_s": 7.0,
            "initial": {"q": [0.0, 0.6, -1.6, 0.3], "payload_kg": 900.0},
            "actuators": {"lift": {"voltage": [[0, 0], [0.2, 6], [2.4, 6], [2.6, 10],
                                               [7, 10]]}},
            "payload": [{"t_s": 1.5, "mass_kg": 0.0}]}


@pytest.fixture(scope="module")
def rec() -> Recording:
    return simulate(MACHINE, scenario_from_dict(SCENARIO), machine_id=MID)


def _shocks(events: list[Any]) -> list[Any]:
    return [e for e in events if e.kind == "shock_load"]


@pytest.mark.timeout(600)
def test_truth_and_twin_flag_the_drop_and_the_end_stop(rec: Recording) -> None:
    lim = shock_limits_n_per_s(MACHINE)
    assert lim[0] == pytest.approx(15.0 * relief_force_n(MACHINE)[0])  # 2.12 MN/s, lift
    truth = _shocks(analyse(MACHINE, history_from_recording(MACHINE, rec)).events)
    twin = _shocks(analyse(MACHINE, history_from_twin(MACHINE, rec_replay(rec))).events)
    for found in (truth, twin):
        lift = [e for e in found if e.component == "lift"]
        assert [e.severity for e in lift] == ["warning", "critical"], found
        drop, stop = lift
        assert 1.5 <= drop.t_start < 1.7  # the load released at 1.5 s
        assert stop.value > 2 * stop.limit  # critical: at least twice the threshold
    # the twin's impact is the truth's within the 50-ms look-back and a fifth of its rate
    assert twin[1].t_start == pytest.approx(truth[1].t_start, abs=0.1)
    assert twin[1].value == pytest.approx(truth[1].value, rel=0.2)


def rec_replay(rec: Recording) -> Any:
    from cranetwin.twin import replay

    return replay(rec, MACHINE, grid_hz=100.0)


@pytest.mark.timeout(120)
def test_threshold_is_a_machine_setting(rec: Recording) -> None:
    data = MACHINE.model_dump(mode="json")
    data["cylinders"][0]["shock_rate_n_per_s"] = 20e6
    stiff = machine_from_dict(data, "test")
    assert shock_limits_n_per_s(stiff)[0] == 20e6
    assert shock_limits_n_per_s(stiff)[1] == shock_limits_n_per_s(MACHINE)[1]
    h = history_from_recording(stiff, rec)
    assert not [e for e in _shocks(analyse(stiff, h).events) if e.component == "lift"]
    # the analytics' own default still applies to cylinders without a setting
    loose = shock_limits_n_per_s(MACHINE, EventConfig(shock_rate_per_s=30.0).shock_rate_per_s)
    assert loose[1] == pytest.approx(2 * shock_limits_n_per_s(MACHINE)[1])


@pytest.mark.timeout(600)
def test_live_and_stored_report_agree(db_url: str, rec: Recording) -> None:
    """The worker's stored events (live) and the report merged from stored parts (batch) give
    the same shock events with the same times and values, with a window edge 20 ms before
    the impact (its force rate looks back across the edge)."""
    direct = _shocks(analyse(MACHINE, history_from_twin(MACHINE, rec_replay(rec))).events)
    t_hit = direct[-1].t_start
    offset_ns = int(round((T0 + 60.0 - (t_hit - 0.02)) * 100)) * 10_000_000
    blocks = [dataclasses.replace(b, t0_ns=b.t0_ns + offset_ns) for b in rec.blocks(10)]
    b = Backend.open(db_url)
    try:
        b.store.add_machine(MID, wire_id=7, secret=b"s" * 32)
        b.store.write_blocks(blocks)
        tick = [0.0]
        worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                            replayer=Replayer(), quiet_s=1.0, clock=lambda: tick[0])
        done = 0
        for _ in range(3):  # the last window waits until the machine is quiet
            done += worker.catch_up(b.machine(MID))
            tick[0] += 2.0
        assert done == 2
        live = b.store.events(MID, T0, T0 + 120, kinds=["shock_load"])
        rep = analytics_report(b, Replayer(), MACHINE, MID, TimeRange(T0, T0 + 120))
        assert rep is not None
        batch = _shocks(rep.events)
        assert len(batch) >= 2 and len(live) == len(batch)
        for e, s in zip(batch, live, strict=True):
            assert s.t_s == pytest.approx(e.t_start, abs=1e-6)
            assert (s.severity, s.evidence["component"], s.evidence["value"],
                    s.evidence["limit"]) == (e.severity, e.component, e.value, e.limit)
        hit = [e for e in batch if e.component == "lift" and e.severity == "critical"]
        assert len(hit) == 1 and hit[0].t_start >= T0 + 60.0  # in the second window
        assert hit[0].t_start - offset_ns / 1e9 == pytest.approx(t_hit, abs=0.03)
        assert np.isfinite(hit[0].value) and hit[0].value > 2 * hit[0].limit
    finally:
        b.close()
