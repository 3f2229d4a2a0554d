"""A silence in the samples is a real discontinuity: the replay's spline across a dropout is no
measurement. The twin worker and the report edges (``service.history.window_rows``), the CLI's
report, the load history and the 3D view's /twin leave the bridged instants out, so a demo
crane whose stream pauses for 20 s in the middle of a minute raises no false event and API and
CLI report the same range alike (the spline's swings were 7 events: a critical overload,
over-pressures, end-stop impacts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

PERIOD_S = 0.01
T0 = 1_780_000_020.0  # a whole minute [s]
GAP = (T0 + 70.0, T0 + 90.0)  # no samples in between [s]
MID = "crane-g"


def _demo_samples(tmp_path: Path, seconds: float) -> tuple[object, object]:
    """(machine, SampleArrays) of a demo crane's stream (the heaviest demo logs), t from 0."""
    from cranetwin.demo import DemoConfig, demo_scenario
    from cranetwin.ingest.sender import simulator_stream
    from cranetwin.model import load_machine
    from cranetwin.protocol import Layout, MachineKey
    from cranetwin.samples import SampleArrays

    machine = load_machine("patu655")
    key = MachineKey(1, MID, b"k" * 16, Layout.from_channels(machine.channels))
    sc = tmp_path / "scenario.json"
    sc.write_text(demo_scenario(max(DemoConfig().payloads_kg), 2, 3600.0).model_dump_json())
    stream, period = simulator_stream(key, machine, str(sc), seed=2)
    assert period == PERIOD_S
    n = int(round(seconds / PERIOD_S))
    v = np.concatenate([stream.read(177_000_000_000 + i, 500) for i in range(0, n, 500)])[:n]
    return machine, SampleArrays(MID, np.arange(n) * PERIOD_S, tuple(key.layout.names), v,
                                 period_ns=10_000_000)


@pytest.mark.timeout(300)
def test_a_dropout_raises_no_event_and_every_path_agrees(tmp_path: Path, sqlite_url: str) -> None:
    from fastapi.testclient import TestClient

    from cranetwin.api import create_app
    from cranetwin.reports import StoreSource, build_report
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import tiled_blocks

    machine, base = _demo_samples(tmp_path, 150.0)
    blocks = [b for b in tiled_blocks(MID, machine, T0, 150.0, 1.0, base=base)
              if not GAP[0] <= b.t0_ns * 1e-9 < GAP[1]]
    app = create_app(Settings(database_url=sqlite_url, worker_in_process=False))
    with TestClient(app) as client:
        services = app.state.services
        key = services.backend.create_key("fleet", "test")[1]
        services.backend.store.add_machine(MID, wire_id=9, secret=b"k" * 32, model="patu655")
        services.backend.store.write_blocks(blocks)
        worker = TwinWorker(services.backend, services.settings, services.metrics,
                            services.fleet.replayer)
        assert worker.catch_up(services.backend.machine(MID)) == 2
        h = {"X-API-Key": key}
        stored = client.get(f"/api/v1/machines/{MID}/events", headers=h,
                            params={"from": T0, "to": T0 + 150}).json()
        assert stored == [], [(e["kind"], e["message"]) for e in stored]
        api = client.get(f"/api/v1/machines/{MID}/analytics", headers=h,
                         params={"from": T0, "to": T0 + 120}).json()
        # the 3D view's frames stop at the silence and resume after it
        twin = client.get(f"/api/v1/machines/{MID}/twin", headers=h,
                          params={"from": T0 + 60, "to": T0 + 120, "rate_hz": 25}).json()
        hist = client.get(f"/api/v1/machines/{MID}/history", headers=h,
                          params={"from": T0 + 60, "to": T0 + 120, "channels": "force:lift",
                                  "max_points": 600}).json()
    assert api["events"] == []
    # 100 s of the 120 s measured (100 Hz), none of the 20 s bridged
    assert 9_900 <= api["n_samples"] <= 10_000, api["n_samples"]
    cli = build_report(StoreSource(sqlite_url, MID, T0, T0 + 120))
    assert cli.n_samples == api["n_samples"] and cli.events == []
    assert [c["t_grab"] for c in api["cycles"]] == pytest.approx([c.t_grab for c in cli.cycles])
    t = np.asarray(twin["t"])
    assert not np.any((t > GAP[0] + 0.2) & (t < GAP[1] - 0.2)), t[(t > GAP[0]) & (t < GAP[1])]
    assert np.any(t < GAP[0]) and np.any(t > GAP[1])
    ht = np.asarray(hist["channels"]["force:lift"]["t"])
    assert not np.any((ht > GAP[0] + 1) & (ht < GAP[1] - 1))
