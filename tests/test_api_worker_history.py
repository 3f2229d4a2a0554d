"""Analytics of any range merged from the parts the twin worker stores: the same
report as replaying every minute of the range, on SQLite and PostgreSQL; hours rolled up."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.analytics import AnalyticsReport, AnalyticsState, LoadHistory
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend
from cranetwin.service.errors import InvalidRequestError
from cranetwin.service.replayer import Replayer
from cranetwin.service.timerange import TimeRange
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks
from cranetwin.testing.histories import SyntheticCrane

T0 = 1795420800.0  # a whole day
MID = "crane-h"
MACHINE = load_machine("patu655")


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _same(a: AnalyticsReport, b: AnalyticsReport, rel: float = 0.0) -> None:
    assert (a.t_start, a.t_end, a.n_samples) == (b.t_start, b.t_end, b.n_samples)
    for sa, sb in zip(a.spectra, b.spectra, strict=True):
        assert np.array_equal(sa.cycles.lower, sb.cycles.lower), sa.channel
        assert np.array_equal(sa.cycles.upper, sb.cycles.upper), sa.channel
        assert np.array_equal(sa.cycles.count, sb.cycles.count), sa.channel
    assert [e.damage for e in b.life] == pytest.approx([e.damage for e in a.life], rel=1e-12)
    assert [(e.kind, e.t_start, e.t_end, e.component) for e in a.events] == \
        [(e.kind, e.t_start, e.t_end, e.component) for e in b.events]
    assert [(c.t_grab, c.t_release) for c in a.cycles] == [(c.t_grab, c.t_release)
                                                          for c in b.cycles]
    assert b.recorded_s == pytest.approx(a.recorded_s, rel=1e-12)
    assert b.idle_s == pytest.approx(a.idle_s, rel=1e-12)


@pytest.mark.timeout(300)
def test_merged_report_equals_replaying_the_range(db_url: str, base: SampleArrays) -> None:
    from cranetwin.service.analytics import analytics_report, direct_report

    b = Backend.open(db_url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, T0, 235.0, 1.0, base=base,
                                           origin_s=T0)))
    replayer = Replayer()
    worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                        replayer=replayer)
    assert worker.catch_up(b.machine(MID)) == 3  # the fourth minute waits for later samples
    assert len(aw.windows(b.store.engine, MID, 60, T0, T0 + 600)) == 3
    # edges inside minutes, three stored minutes, one minute past the worker replayed
    rng = TimeRange(T0 + 17.3, T0 + 232.05)
    calls: list[tuple[float, float]] = []
    orig = replayer.replay

    def counting(*a: object, **k: object) -> object:
        s = a[2]
        calls.append((float(s.t_s[0]), float(s.t_s[-1])))  # type: ignore[attr-defined]
        return orig(*a, **k)  # type: ignore[arg-type]
    replayer.replay = counting  # type: ignore[assignment,method-assign]
    merged = analytics_report(b, replayer, MACHINE, MID, rng)
    n_merged = len(calls)
    direct = direct_report(b, replayer, MACHINE, MID, rng)
    assert n_merged == 2 and len(calls) == 2 + 4  # only the edge minutes were replayed
    assert merged is not None and direct is not None and merged.n_samples > 20_000
    _same(direct, merged)
    assert merged.events, "the synthetic 400 kg at ~5.4 m reach exceeds the rated load"
    # the requested range, not the data, sets the basis; the worker's history gives the usage
    assert merged.basis is not None and merged.basis.usage_source == "history"
    # more than max_replay_s of data without stored parts: refused, not replayed on the request
    # thread (minute 3 is past the worker); the empty hours after the data cost nothing
    with pytest.raises(InvalidRequestError):
        analytics_report(b, replayer, MACHINE, MID, TimeRange(T0, T0 + 7200), max_replay_s=30)
    assert analytics_report(b, replayer, MACHINE, MID, TimeRange(T0, T0 + 7200),
                            max_replay_s=60) is not None
    b.close()


@pytest.mark.timeout(120)
def test_hours_roll_up_and_merge_exactly(sqlite_url: str) -> None:
    from cranetwin.service.history import range_state, roll_up, store_part

    b = Backend.open(sqlite_url)
    crane = SyntheticCrane(MACHINE, seed=2, days=1, shift_h=2.0)
    s0 = crane.shift_bounds(0)[0]  # 06:00, a whole hour
    minutes: dict[float, LoadHistory] = {}
    for k in range(150):  # 2 h 30 min of minutes (the shift ends at 2 h)
        a = s0 + 60 * k
        t = a + np.arange(600) / 10.0
        t = t[t < crane.shift_bounds(0)[1]]
        if t.size:
            minutes[a] = crane.history(t)
            store_part(b.store.engine, MACHINE, MID, a, a + 60, minutes[a])
    assert roll_up(b.store.engine, MACHINE, MID, s0, s0 + 150 * 60) == 2
    assert len(aw.windows(b.store.engine, MID, 3600, s0, s0 + 86400)) == 2

    def edge(a: float, c: float) -> LoadHistory | None:
        return minutes.get(a)
    for t0, t1 in ((s0 - 100.0, s0 + 9000.0), (s0 + 33.5, s0 + 7100.25), (s0, s0 + 3600.0)):
        got = range_state(b.store.engine, MACHINE, MID, t0, t1, edge, s0 + 150 * 60).report()
        want = AnalyticsState(MACHINE)
        for a in sorted(minutes):
            h = minutes[a]
            i, j = np.searchsorted(h.t_s, [t0, t1])
            if j > i:
                want.update(h.slice(int(i), int(j)))
        _same(want.report(), got)
    b.close()


def _backend_with(url: str) -> Backend:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    return b


def _write(b: Backend, base: SampleArrays, start: float, seconds: float, seq0: int) -> None:
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base,
                                           seq0=seq0, origin_s=T0)))


def _minutes(b: Backend) -> dict[float, int]:
    return {a: n for a, _, n, _ in aw.windows(b.store.engine, MID, 60, T0 - 600, T0 + 3600)}


@pytest.mark.timeout(300)
def test_backfill_behind_the_watermark_is_processed(db_url: str, base: SampleArrays) -> None:
    from cranetwin.service.analytics import analytics_report, direct_report
    from cranetwin.service.worker import derived_channels

    b = _backend_with(db_url)
    replayer = Replayer()
    worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                        replayer=replayer)
    _write(b, base, T0, 125.0, 0)
    _write(b, base, T0 + 245.0, 125.0, 1000)  # a hole of two minutes
    rec = b.machine(MID)
    assert worker.catch_up(rec) == 5  # minutes 0-2, the empty minute 3 skipped, 4, 5
    before = b.progress(MID)
    assert before is not None and before.watermark_s == T0 + 360
    assert sorted(_minutes(b)) == [T0, T0 + 60, T0 + 120, T0 + 240, T0 + 300]
    _write(b, base, T0 + 125.0, 120.0, 2000)  # the hole arrives late (backfill)
    assert worker.catch_up(rec) == 3  # minutes 2-4 redone (the margin reaches 2 and 4)
    after = b.progress(MID)
    assert after is not None and after.watermark_s == T0 + 360
    assert sorted(_minutes(b)) == [T0 + 60 * k for k in range(6)]
    # forces and payload of the backfilled minutes are in the derived summaries
    names = derived_channels(MACHINE)
    summ = b.summaries(MID, ["force:lift", "payload"], T0 + 130, T0 + 240, 1000)
    assert all(np.asarray(summ[n][0]).size >= 100 for n in ("force:lift", "payload")), names
    # and in the AEMP hours: the 120 backfilled seconds counted once
    assert after.operating_s - before.operating_s == pytest.approx(120.0, abs=0.1)
    assert worker.catch_up(rec) == 0  # nothing redone twice
    rng = TimeRange(T0 + 30.5, T0 + 350.0)
    merged = analytics_report(b, replayer, MACHINE, MID, rng)
    direct = direct_report(b, replayer, MACHINE, MID, rng)
    assert merged is not None and direct is not None
    _same(direct, merged)
    b.close()


@pytest.mark.timeout(300)
def test_last_minute_of_a_quiet_machine_is_processed(sqlite_url: str,
                                                     base: SampleArrays) -> None:
    b = _backend_with(sqlite_url)
    now = [0.0]
    worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                        quiet_s=60.0, clock=lambda: now[0])
    _write(b, base, T0, 150.0, 0)
    rec = b.machine(MID)
    assert worker.catch_up(rec) == 2  # the third minute waits for samples past its end...
    now[0] = 30.0
    assert worker.catch_up(rec) == 0
    now[0] = 61.0
    assert worker.catch_up(rec) == 1  # ...until the machine has been quiet for a minute
    prog = b.progress(MID)
    assert prog is not None and prog.watermark_s == T0 + 180
    assert _minutes(b)[T0 + 120] == pytest.approx(3000, abs=5)  # 30 s at 100 Hz
    _write(b, base, T0 + 150.0, 50.0, 5000)  # the machine resumes inside that minute
    now[0] = 62.0
    assert worker.catch_up(rec) == 1  # minute 2 redone with the new samples
    assert _minutes(b)[T0 + 120] == pytest.approx(6000, abs=5)
    b.close()


@pytest.mark.timeout(300)
def test_aemp_api_and_cli_report_give_one_kp_and_life_used(sqlite_url: str,
                                                           base: SampleArrays) -> None:
    from fastapi.testclient import TestClient

    from cranetwin.api import create_app
    from cranetwin.reports import StoreSource, build_report

    app = create_app(Settings(database_url=sqlite_url, worker_in_process=False))
    with TestClient(app) as client:
        services = app.state.services
        key = services.backend.create_key("fleet", "test")[1]
        services.backend.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
        _write(services.backend, base, T0, 245.0, 0)
        worker = TwinWorker(services.backend, services.settings, services.metrics,
                            services.fleet.replayer)
        assert worker.catch_up(services.backend.machine(MID)) == 4
        _write(services.backend, base, T0 + 245.0, 65.0, 1000)
        assert worker.catch_up(services.backend.machine(MID)) == 1  # duty folded on
        wm = services.backend.progress(MID).watermark_s
        assert wm == T0 + 300
        h = {"X-API-Key": key}
        aemp = client.get(f"/api/v1/aemp/Equipment/{MID}", headers=h,
                          params={"format": "json"}).json()
        ext = aemp["Extension"]["cranetwin"]
        api = client.get(f"/api/v1/machines/{MID}/analytics", headers=h,
                         params={"from": T0, "to": wm}).json()
        cli = build_report(StoreSource(sqlite_url, MID, T0, wm))
    assert api["classification"]["cycles"] == len(cli.cycles) >= 3
    assert cli.classification is not None and cli.duty is not None
    kp, used = cli.classification.kp, cli.duty.used_fraction
    assert api["classification"]["kp"] == pytest.approx(kp, rel=1e-12)
    assert api["duty"]["used_fraction"] == pytest.approx(used, rel=1e-12)
    # the feed rounds kp to 5 decimals and the fraction to 6 significant digits
    assert ext["LoadSpectrumFactor"] == pytest.approx(kp, abs=5e-6)
    assert ext["DesignLifeUsedFraction"] == pytest.approx(used, rel=1e-5)
    assert ext["LoadSpectrumFactor"] != pytest.approx(0.0)
