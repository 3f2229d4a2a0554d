"""A twin worker that is behind replays several ready windows as one span: what it stores
equals processing them window by window, a span never crosses a minute, and late data redoes
the stored span it falls in (no part counted twice)."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.service.backend import Backend, Progress
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MID = "crane-s"
MACHINE = load_machine("patu655")
WIN = 4.0


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0, rate_hz=20.0)


def _blocks(base: SampleArrays, start: float, seconds: float, seq0: int) -> list[SampleBlock]:
    return list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base, seq0=seq0,
                             origin_s=T0))


def _setup(url: str) -> tuple[Backend, TwinWorker]:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    s = Settings(database_url="unused", worker_in_process=False, worker_window_s=WIN,
                 worker_settle_s=1.0, twin_margin_s=1.0)
    return b, TwinWorker(b, s)


def _parts(b: Backend) -> list[tuple[float, float, int]]:
    return [(a, z, n) for a, z, n, _ in aw.windows(b.store.engine, MID, 60, T0 - 600,
                                                      T0 + 3600)]


def _summary(b: Backend) -> dict[str, np.ndarray]:
    got = b.summaries(MID, ["force:lift", "payload", "working"], T0, T0 + 150, 1000)
    return {k: np.asarray(v[0], dtype=float) for k, v in got.items()}


def _run(worker: TwinWorker, b: Backend, one_at_a_time: bool) -> int:
    rec = b.machine(MID)
    n = 0
    while True:
        got = worker.catch_up(rec, 1 if one_at_a_time else None)
        n += got
        if got == 0:
            return n


@pytest.mark.timeout(300)
def test_spans_store_what_windows_one_by_one_store(tmp_path: object, base: SampleArrays) -> None:
    urls = [f"sqlite:///{tmp_path}/{name}.db" for name in ("spans", "single")]
    (bs, ws), (b1, w1) = _setup(urls[0]), _setup(urls[1])
    for b in (bs, b1):
        b.store.write_blocks(_blocks(base, T0, 150.0, 0))
    assert _run(ws, bs, False) == _run(w1, b1, True) == 37  # 148 s of ready windows
    ps, p1 = bs.progress(MID), b1.progress(MID)
    assert ps is not None and p1 is not None
    assert ps.watermark_s == p1.watermark_s == T0 + 148 and ps.windows == p1.windows == 37
    spans, single = _parts(bs), _parts(b1)
    assert len(single) == 37 and len(spans) == 3  # minutes 0, 1 and the 28 s of minute 2
    assert [(a - T0, z - T0) for a, z, _ in spans] == [(0, 60), (60, 120), (120, 148)]
    assert sum(n for *_, n in spans) == sum(n for *_, n in single)  # every instant once
    assert (ps.operating_s, ps.idle_s) == pytest.approx((p1.operating_s, p1.idle_s), abs=0.1)
    assert ps.load_count == p1.load_count
    assert ps.payload_total_kg == pytest.approx(p1.payload_total_kg, rel=0.02)
    s_sp, s_1 = _summary(bs), _summary(b1)
    for k in s_sp:  # the same data replayed with the same margins: equal up to edge effects
        assert s_sp[k].shape == s_1[k].shape
        np.testing.assert_allclose(s_sp[k], s_1[k], rtol=0.02, atol=1.0, err_msg=k)
    bs.close()
    b1.close()


@pytest.mark.timeout(300)
def test_the_kept_look_back_part_stores_what_the_stored_one_stores(
        tmp_path: object, base: SampleArrays) -> None:
    """The worker folds its last part as it made it (not decoded from its stored bytes) into
    the next window's events: a worker that forgets it before every window (and so reads and
    decodes the stored one) stores the same parts and events, to the bit (the fleet
    senders' data: events in most windows)."""
    from sqlalchemy import text

    from cranetwin.bench.worker import _source_base

    fleet = _source_base(10.0, 70.0, 3)
    urls = [f"sqlite:///{tmp_path}/{name}.db" for name in ("kept", "read")]
    (bk, wk), (br, wr) = _setup(urls[0]), _setup(urls[1])
    got = []
    for b, w, forget in ((bk, wk, False), (br, wr, True)):
        b.store.write_blocks(_blocks(fleet, T0, 66.0, 0))
        rec = b.machine(MID)
        n = 0
        while True:
            if forget:
                w._forget(MID)
            elif n:
                assert w._last_part[MID].part is not None  # kept as made
            if not w.catch_up(rec, 1):
                break
            n += 1
        assert n == 16
        with b.store.engine.connect() as c:
            got.append((
                sorted(tuple(r) for r in c.execute(text(
                    "SELECT level_s, t0_ns, t1_ns, n, data FROM analytics_windows "
                    "WHERE level_s = 60"))),
                sorted(tuple(r) for r in c.execute(text(
                    "SELECT t_ns, kind, severity, evidence_json FROM events")))))
        b.close()
    (parts_k, events_k), (parts_r, events_r) = got
    assert len(parts_k) == 16 and len(events_k) >= 5
    assert parts_k == parts_r
    assert events_k == events_r


@pytest.mark.timeout(300)
def test_late_data_redoes_the_stored_span(sqlite_url: str, base: SampleArrays) -> None:
    b, worker = _setup(sqlite_url)
    b.store.write_blocks(_blocks(base, T0, 10.0, 0))
    b.store.write_blocks(_blocks(base, T0 + 40.0, 90.0, 1000))
    _run(worker, b, False)
    before = _parts(b)
    assert [(a - T0, z - T0) for a, z, _ in before] == [(0, 60), (60, 120), (120, 128)]
    prog = b.progress(MID)
    assert prog is not None
    b.store.write_blocks(_blocks(base, T0 + 10.0, 30.0, 2000))  # fills the hole of minute 0
    assert worker.catch_up(b.machine(MID)) >= 1
    after = _parts(b)
    assert [(a, z) for a, z, _ in after] == [(a, z) for a, z, _ in before]  # no part overlaps
    assert after[0][2] == 1200 > before[0][2]  # the span holds the late samples now
    new = b.progress(MID)
    assert isinstance(new, Progress) and new.watermark_s == prog.watermark_s
    assert new.operating_s + new.idle_s == pytest.approx(prog.operating_s + prog.idle_s + 30,
                                                          abs=0.2)
    assert worker.catch_up(b.machine(MID)) == 0  # nothing redone twice
    b.close()


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_threads_store_what_one_thread_stores(pg_url: str, base: SampleArrays) -> None:
    from sqlalchemy import text

    from cranetwin.storage.engine import make_engine

    urls = [pg_url]
    e = make_engine(pg_url)
    with e.connect().execution_options(isolation_level="AUTOCOMMIT") as c:
        c.execute(text("DROP DATABASE IF EXISTS cranetwin_threads_b"))
        c.execute(text("CREATE DATABASE cranetwin_threads_b"))
    e.dispose()
    urls.append(pg_url.rsplit("/", 1)[0] + "/cranetwin_threads_b")
    got = []
    try:
        for url, threads in zip(urls, (1, 4), strict=True):
            b = Backend.open(url)
            ids = [f"crane-t{i}" for i in range(6)]
            blocks = []
            for i, mid in enumerate(ids):
                b.store.add_machine(mid, wire_id=20 + i, secret=b"k" * 32)
                blocks += list(tiled_blocks(mid, MACHINE, T0 + 7 * i, 90.0, 1.0, base=base,
                                            seq0=0, origin_s=T0))
            b.store.write_blocks(blocks)
            s = Settings(database_url="unused", worker_in_process=False, worker_window_s=WIN,
                         worker_settle_s=1.0, twin_margin_s=1.0, worker_threads=threads)
            w = TwinWorker(b, s)
            while w.run_once():
                pass
            got.append({m: b.progress(m) for m in ids})
            b.close()
    finally:
        e = make_engine(pg_url)
        with e.connect().execution_options(isolation_level="AUTOCOMMIT") as c:
            c.execute(text("DROP DATABASE IF EXISTS cranetwin_threads_b WITH (FORCE)"))
        e.dispose()
    one, four = got
    assert all(p is not None and p.windows >= 20 for p in one.values())
    for m in one:
        a, z = one[m], four[m]
        assert a is not None and z is not None
        assert (a.watermark_s, a.windows, a.load_count) == (z.watermark_s, z.windows, z.load_count)
        assert a.operating_s == pytest.approx(z.operating_s, abs=1e-6)
