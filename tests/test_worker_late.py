"""Late blocks behind the twin worker's progress mark: on PostgreSQL a block whose transaction
commits after a later-numbered block was seen is still processed (commit-order mark, migration
``0006c``), and the lift counters after a late block equal a fresh processing of the history."""

from __future__ import annotations

import time

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.service.backend import Backend, Progress
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.storage import late_version, writes
from cranetwin.storage.engine import make_engine, migrate
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MID = "crane-l"
MACHINE = load_machine("patu655")
LIFT = ("load_count", "payload_total_kg", "load_cube_sum", "overloads", "max_payload_kg",
        "in_lift", "lift_peak_kg", "lift_peak_ratio")


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _backend(url: str) -> Backend:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    return b


def _blocks(base: SampleArrays, start: float, seconds: float, seq0: int) -> list[SampleBlock]:
    return list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base, seq0=seq0,
                             origin_s=T0))


def _worker(b: Backend) -> TwinWorker:
    return TwinWorker(b, Settings(database_url="unused", worker_in_process=False))


def _minutes(b: Backend) -> dict[float, int]:
    return {a: n for a, _, n, _ in aw.windows(b.store.engine, MID, 60, T0 - 600, T0 + 3600)}


def _op(b: Backend, w0: float) -> float:
    got = aw.window_times(b.store.engine, MID, 60, w0)
    assert got is not None
    return got[0]


def _xmin(b: Backend) -> int:
    with b.store.engine.connect() as c:
        return int(c.execute(text(
            "SELECT pg_snapshot_xmin(pg_current_snapshot())::text::bigint")).scalar_one())


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_block_committed_after_a_higher_id_was_seen_is_processed(
        pg_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    from cranetwin.service.worker import derived_channels

    b = _backend(pg_url)
    worker = _worker(b)
    rec = b.machine(MID)
    b.store.write_blocks(_blocks(base, T0, 125.0, 0))
    b.store.write_blocks(_blocks(base, T0 + 245.0, 125.0, 1000))
    assert worker.catch_up(rec) == 5  # minutes 0-2, 4, 5 (3 is empty); the mark is set
    before = b.progress(MID)
    assert before is not None and before.watermark_s == T0 + 360
    was = sum(_op(b, a) for a in _minutes(b))
    # writer 1 inserts the lower ids (minute 2's hole) and keeps its transaction open...
    with b.store.engine.connect() as held:
        tx = held.begin()
        with Session(bind=held) as s:
            pk = int(s.execute(text("SELECT id FROM machines WHERE machine_id = :m"),
                               {"m": MID}).scalar_one())

        def joined() -> Session:
            return Session(bind=held, join_transaction_mode="create_savepoint")
        low = _blocks(base, T0 + 125.0, 55.0, 2000)
        # its late-data note (the statement that makes writers of one machine pass one after
        # the other: storage.late_version) comes last, just before its commit below
        noted: list[list[tuple[str, int, int, int]]] = []
        with monkeypatch.context() as m:
            m.setattr(late_version, "note", lambda _s, stored: noted.append(list(stored)))
            res = writes.write(joined, low, {MID: pk})
        assert all(o.status == "stored" for o in res.outcomes) and len(noted) == 1
        xid = int(held.execute(text("SELECT pg_current_xact_id()::text::bigint")).scalar_one())
        # ...while writer 2 commits higher ids (minute 3) and a pass runs
        b.store.write_blocks(_blocks(base, T0 + 185.0, 55.0, 3000))
        ids: dict[int, int] = dict(held.execute(text("SELECT seq, id FROM sample_blocks "
                                                 "WHERE seq IN (2000, 3000)")).all())
        assert ids[2000] < ids[3000]  # writer 1's ids are the lower ones
        worker.catch_up(rec)
        with Session(bind=held) as s:
            late_version.note(s, noted[0])
        tx.commit()
    # every transaction below the writer's has to end (other clients of this server too)
    deadline = time.monotonic() + 60
    while _xmin(b) <= xid and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _xmin(b) > xid
    worker.catch_up(rec)  # the next pass processes writer 1's blocks
    after = b.progress(MID)
    assert after is not None and after.watermark_s == T0 + 360
    mins = _minutes(b)
    assert sorted(mins) == [T0 + 60 * k for k in range(6)]
    assert mins[T0 + 120] == pytest.approx(6000, abs=5)  # 60 s at 100 Hz: the late 55 s in
    assert mins[T0 + 180] == pytest.approx(5500, abs=5)  # the 5-s hole before it is not counted
    summ = b.summaries(MID, ["force:lift", "payload"], T0 + 126, T0 + 179, 1000)
    assert all(np.asarray(summ[n][0]).size >= 50 for n in ("force:lift", "payload")), \
        derived_channels(MACHINE)
    # counted once: the operating hours grew by what the redone minutes count now
    now = sum(_op(b, a) for a in mins)
    assert after.operating_s - before.operating_s == pytest.approx(now - was, abs=1e-6)
    assert now - was >= 110.0
    assert worker.catch_up(rec) == 0  # nothing redone twice
    assert b.progress(MID) == after
    b.close()


def _lifts(p: Progress | None) -> tuple[object, ...]:
    assert p is not None
    return tuple(getattr(p, k) for k in LIFT)



def _fresh(sqlite_url: str, base: SampleArrays) -> tuple[Backend, Progress | None]:
    """A fresh processing of the whole history, everything stored at once (its own SQLite
    file beside ``sqlite_url``): the backend and its progress."""
    fresh_b = _backend(sqlite_url.replace("cranetwin.db", "fresh.db"))
    fresh_b.store.write_blocks(_blocks(base, T0, 250.0, 0))
    assert _worker(fresh_b).catch_up(fresh_b.machine(MID)) == 4
    return fresh_b, fresh_b.progress(MID)

@pytest.mark.timeout(300)
def test_late_block_into_a_processed_minute_recounts_the_lifts(sqlite_url: str,
                                                               base: SampleArrays) -> None:
    b = _backend(sqlite_url)
    worker = _worker(b)
    rec = b.machine(MID)
    b.store.write_blocks(_blocks(base, T0, 70.0, 0))
    b.store.write_blocks(_blocks(base, T0 + 110.0, 140.0, 1000))
    assert worker.catch_up(rec) == 4  # minutes 0-3; minute 1 has a 40-s hole
    before = b.progress(MID)
    assert before is not None
    b.store.write_blocks(_blocks(base, T0 + 70.0, 40.0, 2000))
    assert worker.catch_up(rec) >= 1  # minute 1 (and its neighbours) redone
    after = b.progress(MID)
    fresh_b, fresh = _fresh(sqlite_url, base)
    assert fresh is not None and after is not None
    assert _lifts(before) != _lifts(fresh), "the late samples change a lift"
    assert _lifts(after) == pytest.approx(_lifts(fresh), rel=1e-9)
    assert (after.operating_s, after.idle_s) == pytest.approx((fresh.operating_s, fresh.idle_s),
                                                              abs=0.02)
    assert worker.catch_up(rec) == 0 and b.progress(MID) == after  # nothing recounted twice
    b.close()
    fresh_b.close()


@pytest.mark.timeout(300)
def test_late_block_into_a_minute_whose_replay_failed_counts_it_once(
        sqlite_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    """A minute whose replay failed is passed and recorded (``storage/failed_windows.py``); a
    late block into it has it processed again, its window counted once (as processed, not as
    new) and its operating time added once: the state equals a fresh processing."""
    from cranetwin.errors import TwinError
    from cranetwin.storage.failed_windows import failed_spans

    b = _backend(sqlite_url)
    worker = _worker(b)
    rec = b.machine(MID)
    b.store.write_blocks(_blocks(base, T0, 70.0, 0))
    b.store.write_blocks(_blocks(base, T0 + 110.0, 140.0, 1000))
    real = worker.replayer.replay
    margin = worker.settings.twin_margin_s

    def replay(machine_id: str, machine: object, samples: SampleArrays, *a: object,
               **k: object) -> object:
        if abs(float(samples.t_s[0]) - (T0 + 60.0 - margin)) < 0.5:
            raise TwinError("injected: the replay of minute 1 fails")
        return real(machine_id, machine, samples, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(worker.replayer, "replay", replay)
    assert worker.catch_up(rec) == 4  # minutes 0-3; minute 1 (a 40-s hole) failed
    assert T0 + 60 not in _minutes(b)
    assert failed_spans(b.store.engine, MID, T0, T0 + 300) == [(T0 + 60, T0 + 120)]
    monkeypatch.undo()
    b.store.write_blocks(_blocks(base, T0 + 70.0, 40.0, 2000))
    assert worker.catch_up(rec) >= 1  # minute 1 (and its neighbours) redone
    assert failed_spans(b.store.engine, MID, T0, T0 + 300) == []
    after = b.progress(MID)
    fresh_b, fresh = _fresh(sqlite_url, base)
    assert fresh is not None and after is not None
    assert after.windows == fresh.windows == 4
    assert (after.operating_s, after.idle_s) == pytest.approx((fresh.operating_s, fresh.idle_s),
                                                              abs=0.02)
    assert _lifts(after) == pytest.approx(_lifts(fresh), rel=1e-9)
    assert _minutes(b) == _minutes(fresh_b)
    b.close()
    fresh_b.close()


@pytest.mark.postgres
@pytest.mark.timeout(120)
def test_migration_0006c_keeps_blocks_on_the_partitioned_table(pg_url: str,
                                                               base: SampleArrays) -> None:
    from cranetwin.storage import Store

    engine = make_engine(pg_url)
    migrate(engine, "0005")
    with engine.begin() as c:
        c.execute(text("INSERT INTO machines (machine_id, wire_id, model, secret, meta_json) "
                       "VALUES (:m, 9, 'patu655', :s, '{}')"), {"m": MID, "s": b"k" * 32})
        pk = int(c.execute(text("SELECT id FROM machines")).scalar_one())
        from cranetwin.storage import blocks as blocks_mod
        from cranetwin.storage import bulk, partitions

        partitions.create_covering(c, [int(T0) * 10**9])

        rows = blocks_mod.block_rows([(pk, blk) for blk in _blocks(base, T0, 5.0, 0)])
        bulk.insert_rows(c, "sample_blocks", blocks_mod.COLUMNS,
                         [r for r in rows if not isinstance(r, str)])
    q = "SELECT seq, t_start_ns, data, writer_xid::text FROM sample_blocks ORDER BY id"
    with engine.connect() as c:
        before = [tuple(r) for r in c.execute(text(q.replace(", writer_xid::text", "")))]
    migrate(engine)
    with engine.connect() as c:
        got = [tuple(r) for r in c.execute(text(q))]
        assert c.execute(text("SELECT relkind FROM pg_class "
                              "WHERE oid = to_regclass('sample_blocks')")).scalar() == "p"
    assert [r[:3] for r in got] == before and {r[3] for r in got} == {"0"}
    store = Store.open(pg_url)
    try:
        store.write_blocks(_blocks(base, T0 + 5.0, 1.0, 100))
        with store.engine.connect() as c:
            new = c.execute(text("SELECT writer_xid::text::bigint FROM sample_blocks "
                                 "WHERE seq = 100")).scalar_one()
        assert int(new) > 0  # new rows record their writing transaction
    finally:
        store.close()
        engine.dispose()
