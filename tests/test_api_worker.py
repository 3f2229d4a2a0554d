"""The background twin worker (windows processed once, catch-up after downtime, gaps) and the
API's happy path on every database (SQLite and PostgreSQL through the shared ``db_url``)."""

from __future__ import annotations

import time
from dataclasses import asdict

import numpy as np
import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend
from cranetwin.service.worker import TwinWorker, derived_channels
from cranetwin.settings import Settings
from cranetwin.testing.blocks import PAYLOAD_KG, kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole minute
MID = "crane-w"
MACHINE = load_machine("patu655")


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _backend(url: str) -> Backend:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=7, secret=b"k" * 32)
    return b


def _write(b: Backend, base: SampleArrays, start: float, seconds: float, seq0: int) -> None:
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base,
                                           seq0=seq0, origin_s=T0)))


def _derived(b: Backend, t1: float) -> dict[str, np.ndarray]:
    names = derived_channels(MACHINE)
    out = b.summaries(MID, names, T0 - 3600, t1, 100_000)
    return {n: np.column_stack(list(out[n])) for n in names}


def _worker(b: Backend) -> TwinWorker:
    return TwinWorker(b, Settings(database_url="unused", worker_in_process=False))


def test_worker_never_processes_a_window_twice_and_resumes(sqlite_url: str, tmp_path,
                                                           base: SampleArrays) -> None:
    b = _backend(sqlite_url)
    _write(b, base, T0, 180.0, 0)
    rec = b.machine(MID)
    assert _worker(b).catch_up(rec) == 2  # the third minute waits for samples past its end
    first = b.progress(MID)
    assert first is not None and first.watermark_s == T0 + 120 and first.windows == 2
    assert _worker(b).catch_up(rec) == 0  # a restarted worker finds nothing to do
    assert b.progress(MID) == first
    _write(b, base, T0 + 180, 125.0, 10_000)  # later: more data arrives
    assert _worker(b).catch_up(rec) == 3
    incremental = b.progress(MID)
    derived_inc = _derived(b, T0 + 600)

    # the same data processed in one go on a fresh database gives the same summaries/counters
    other = _backend(f"sqlite:///{tmp_path / 'batch.db'}")
    _write(other, base, T0, 180.0, 0)
    _write(other, base, T0 + 180, 125.0, 10_000)
    assert _worker(other).catch_up(other.machine(MID)) == 5
    batch = other.progress(MID)
    assert incremental is not None and batch is not None
    # each worker instance chooses its smoothing windows from the first window it replays
    # (api.replayer): a restarted worker may choose from another minute, which moves the
    # results by ~1e-4 relative (1e-3 at a payload step); counts and watermarks are identical
    a, c = asdict(incremental), asdict(batch)
    for k in a:
        if isinstance(a[k], float):
            assert a[k] == pytest.approx(c[k], rel=1e-3, abs=1e-3), k
        else:
            assert a[k] == c[k], k
    derived_batch = _derived(other, T0 + 600)
    for name, arr in derived_inc.items():
        scale = float(np.nanmax(np.abs(derived_batch[name][:, 1:]))) or 1.0
        np.testing.assert_allclose(arr, derived_batch[name], rtol=1e-4, atol=1e-4 * scale,
                                   err_msg=name)
    # a lift (400 kg from second 30 to 60 of every minute) ends at 60, 120, 180 and 240 s;
    # the one ending at 300 s is still held at the watermark (in_lift)
    assert incremental.load_count == 4 and incremental.in_lift
    assert incremental.payload_total_kg == pytest.approx(4 * PAYLOAD_KG, rel=0.01)
    b.close()
    other.close()


def test_worker_skips_gaps_in_one_step(sqlite_url: str, base: SampleArrays) -> None:
    b = _backend(sqlite_url)
    _write(b, base, T0, 60.0, 0)
    _write(b, base, T0 + 7200, 125.0, 1000)  # two hours off
    n = _worker(b).catch_up(b.machine(MID))
    assert n == 3  # minute 0, then the two minutes after the gap
    prog = b.progress(MID)
    assert prog is not None and prog.watermark_s == T0 + 7320
    assert prog.operating_s == pytest.approx(180.0, abs=0.5)
    b.close()


def test_background_worker_follows_the_store(sqlite_url: str, base: SampleArrays) -> None:
    app = create_app(Settings(database_url=sqlite_url, worker_in_process=True,
                              worker_interval_s=0.05))
    with TestClient(app):
        b: Backend = app.state.services.backend
        b.store.add_machine(MID, wire_id=7, secret=b"k" * 32)
        _write(b, base, T0, 125.0, 0)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            prog = b.progress(MID)
            if prog is not None and prog.windows == 2:
                break
            time.sleep(0.05)
        assert prog is not None and prog.windows == 2


def test_happy_path_on_each_database(db_url: str, base: SampleArrays) -> None:
    app = create_app(Settings(database_url=db_url, worker_in_process=False))
    with TestClient(app) as client:
        services = app.state.services
        _, key = services.backend.create_key("admin")
        h = {"Authorization": f"Bearer {key}"}
        r = client.post("/api/v1/machines", headers=h,
                        json={"machine_id": MID, "model": "patu655"})
        assert r.status_code == 201
        _write(services.backend, base, T0, 125.0, 0)
        assert _worker(services.backend).catch_up(services.backend.machine(MID)) == 2
        p = {"from": T0, "to": T0 + 120}
        assert client.get(f"/api/v1/machines/{MID}", headers=h).json()["data_range"]["to"] \
            .startswith("2026-11-23T08:02:04.99")
        s = client.get(f"/api/v1/machines/{MID}/samples", headers=h,
                       params={**p, "limit": 50}).json()
        assert len(s["t"]) == 50 and s["next_cursor"] is not None
        hist = client.get(f"/api/v1/machines/{MID}/history", headers=h,
                          params={**p, "channels": "lift_pA,payload", "max_points": 120}).json()
        assert len(hist["channels"]["payload"]["t"]) == 120
        twin = client.get(f"/api/v1/machines/{MID}/twin", headers=h,
                          params={"from": T0 + 40, "to": T0 + 50, "rate_hz": 20}).json()
        assert len(twin["t"]) == 200
        np.testing.assert_allclose(twin["payload"]["kg"], PAYLOAD_KG, atol=0.02 * PAYLOAD_KG)
        find = client.get(f"/api/v1/machines/{MID}/find", headers=h,
                          params={**p, "channel": "payload", "op": "gt",
                                  "value": PAYLOAD_KG / 2}).json()
        assert find["t"] == pytest.approx(T0 + 30, abs=1.0)
        aemp = client.get(f"/api/v1/aemp/Equipment/{MID}", headers=h,
                          params={"format": "json"}).json()
        assert aemp["CumulativeLoadCount"]["Count"] == 1  # the 2nd lift ends at the watermark


def test_worker_stores_detected_events_once(sqlite_url: str, base: SampleArrays) -> None:
    from cranetwin.analytics import EventDetector
    from cranetwin.service.analytics import load_history
    from cranetwin.service.backend import Progress
    from cranetwin.twin import replay

    b = _backend(sqlite_url)
    _write(b, base, T0, 185.0, 0)
    assert _worker(b).catch_up(b.machine(MID)) == 3
    stored = b.events(MID, T0, T0 + 400)
    # independently: each minute replayed with its margins and run through the detector
    expected = []
    for k in range(3):
        a = T0 + 60 * k
        res = replay(b.read_samples(MID, a - 2, a + 62), MACHINE, grid_hz=100.0)
        keep = (res.t_s >= a) & (res.t_s < a + 60)
        det = EventDetector(MACHINE)
        det.update(load_history(MACHINE, res, keep))
        expected += [(round(e.t_start, 2), e.kind) for e in det.all_events()]
    assert expected, "the synthetic 400 kg at ~5.4 m reach exceeds the rated load"
    assert [(round(e["t"], 2), e["kind"]) for e in stored] == expected
    assert all(e["message"] and "limit" in e["evidence"] for e in stored)
    # a crash before the watermark moved: the windows are redone, events are not doubled
    b.reset_progress(Progress.empty(MID, T0))
    assert _worker(b).catch_up(b.machine(MID)) == 3
    assert len(b.events(MID, T0, T0 + 400)) == len(stored)
    b.close()


def test_two_workers_never_count_a_window_twice(db_url: str, base: SampleArrays) -> None:
    """Two workers on one machine: the one that commits second finds the watermark moved,
    stores nothing of its replay, and leaves counters and summaries as one worker would."""
    b = _backend(db_url)
    _write(b, base, T0, 130.0, 0)
    rec = b.machine(MID)
    first, second = _worker(b), _worker(b)
    from cranetwin.service.backend import Progress

    start = Progress.empty(MID, T0)
    done = first.process_window(rec, start, None)
    assert done is not None and done.watermark_s == T0 + 60
    before = _derived(b, T0 + 130)
    assert second.process_window(rec, start, None) is None  # same window, same start: refused
    assert b.progress(MID) == done
    after = _derived(b, T0 + 130)
    for name, arr in before.items():
        np.testing.assert_array_equal(after[name], arr)
    assert second.catch_up(rec) == 1  # re-reads the progress and does the next window only
    prog = b.progress(MID)
    assert prog is not None and prog.windows == 2 and prog.watermark_s == T0 + 120
    b.close()
