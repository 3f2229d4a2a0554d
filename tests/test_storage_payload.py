"""A known payload stored as a time series (``payload_runs``), on SQLite and PostgreSQL: exact
read-back with NaN where not known, one run stored once, refusals, the migration onto a
database with data, and a sharded store writing to the machine's shard."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import replace as dc_replace

import numpy as np
import pytest
from sqlalchemy import func, inspect, select, text
from sqlalchemy.orm import Session

from conftest import PG_URL, _pg_conninfo, pg_unreachable_reason
from cranetwin.errors import StorageError
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, UnknownMachineError
from cranetwin.storage.engine import make_engine, migrate
from cranetwin.storage.payloads import MAX_RUN, PayloadRun, PayloadRunRow, runs_of
from cranetwin.storage.sharding import partition_of
from cranetwin.storage.shardmap import ShardMap
from cranetwin.storage.shards import ShardedStore

T0_NS = 1_767_225_600 * 10**9 + 250_000_000
PERIOD = 10_000_000  # 100 Hz
SECRET = b"0123456789abcdef0123456789abcdef"

pytestmark = pytest.mark.timeout(60)


def _series(n: int = 500) -> tuple[np.ndarray, np.ndarray]:
    t = T0_NS + np.arange(n, dtype=np.int64) * PERIOD
    kg = np.where((np.arange(n) // 50) % 2 == 1, 300.0 + np.arange(n) * 0.25, 0.0)
    kg[120:140] = np.nan  # not known there
    return t, kg


def _rows(store: Store) -> int:
    with Session(store.engine) as s:
        return int(s.scalar(select(func.count()).select_from(PayloadRunRow)) or 0)


@pytest.fixture
def store(db_url: str) -> Iterator[Store]:
    s = Store.open(db_url)
    s.add_machine("crane-1", 1, SECRET)
    s.add_machine("crane-2", 2, SECRET[::-1])
    yield s
    s.close()


def test_write_then_read_gives_the_series_back_exactly(store: Store) -> None:
    t, kg = _series()
    got = store.write_payload("crane-1", kg, t_ns=t)
    assert (got.stored, got.duplicate, got.differing, got.values_stored) == (1, 0, 0, 500)
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.array_equal(back.t_ns, t)
    assert np.array_equal(back.payload_kg, kg, equal_nan=True)  # NaN where not known
    assert back.t_s.shape == back.payload_kg.shape == (500,) and back.known
    # a range as read_samples bounds it: t0 ≤ t < t1 on the float seconds of sample times
    part = store.read_payload("crane-1", float(t[100]) / 1e9, float(t[200]) / 1e9)
    assert np.array_equal(part.t_ns, t[100:200])
    assert store.read_payload("crane-2", 0.0, 4e9).n == 0  # another machine: nothing
    assert not store.read_payload("crane-2", 0.0, 4e9).known


def test_the_same_series_twice_is_stored_once(store: Store) -> None:
    t, kg = _series()
    store.write_payload("crane-1", kg, t_ns=t)
    again = store.write_payload("crane-1", kg, t_ns=t)
    assert (again.stored, again.duplicate, again.differing, again.values_stored) == (0, 1, 0, 0)
    assert _rows(store) == 1
    other = store.write_payload("crane-1", kg + 1.0, t_ns=t)  # stored with other values: kept
    assert (other.stored, other.duplicate, other.differing) == (0, 0, 1)
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.array_equal(back.payload_kg, kg, equal_nan=True)
    # seconds instead of ns: rounded to the µs, the regular series is one run again
    secs = store.write_payload("crane-2", kg, t_s=t / 1e9)
    assert secs.stored == 1
    back2 = store.read_payload("crane-2", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.array_equal(back2.t_ns, t)


def test_overlapping_runs_read_each_time_once_from_the_earlier_run(store: Store) -> None:
    t, kg = _series()
    store.write_payload_runs("crane-1", [PayloadRun(int(t[0]), PERIOD, kg[:300])])
    store.write_payload_runs("crane-1", [PayloadRun(int(t[200]), PERIOD, kg[200:] + 7.0)])
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.array_equal(back.t_ns, t)
    assert np.array_equal(back.payload_kg[:300], kg[:300], equal_nan=True)
    assert np.array_equal(back.payload_kg[300:], kg[300:] + 7.0)
    assert store.delete_payload_runs("crane-1", [int(t[200])]) == 1
    assert store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0).n == 300


def test_a_nan_run_that_hides_known_values_asks_for_their_redo(store: Store) -> None:
    """An all-NaN run stored before (earlier start than) a run with known values over the same
    times hides them from every read: the twin worker is asked to redo its whole span; deleting
    that run reveals them again and asks the same. Found as silent before: only known values
    were recorded as changed."""
    from cranetwin.storage import redo

    t, _ = _series()
    store.write_payload_runs("crane-1", [PayloadRun(int(t[100]), PERIOD, np.full(200, 250.0))])
    redo.done(store.engine, "crane-1", redo.pending(store.engine, ["crane-1"])["crane-1"])
    store.write_payload_runs("crane-1", [PayloadRun(int(t[50]), PERIOD, np.full(200, np.nan))])
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.isnan(back.payload_kg[back.t_ns <= t[249]]).all()  # hidden from t[100] to t[249]
    asked = redo.pending(store.engine, ["crane-1"])["crane-1"]
    assert [(r.t0_ns, r.t1_ns) for r in asked] == [(int(t[50]), int(t[249]))]
    redo.done(store.engine, "crane-1", asked)
    assert store.delete_payload_runs("crane-1", [int(t[50])]) == 1
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    assert np.array_equal(back.payload_kg, np.full(200, 250.0))  # revealed again
    asked = redo.pending(store.engine, ["crane-1"])["crane-1"]
    assert [(r.t0_ns, r.t1_ns) for r in asked] == [(int(t[50]), int(t[249]))]


@pytest.mark.parametrize(("bad", "match"), [(-0.5, "finite and ≥ 0"), (np.inf, "finite")])
def test_a_negative_or_infinite_payload_is_refused_and_nothing_stored(
        store: Store, bad: float, match: str) -> None:
    t, kg = _series()
    kg[400] = bad
    with pytest.raises(StorageError, match=match):
        store.write_payload("crane-1", kg, t_ns=t)
    assert _rows(store) == 0
    with pytest.raises(StorageError, match="strictly increasing"):
        store.write_payload("crane-1", kg[::-1], t_ns=t[::-1])
    with pytest.raises(StorageError, match="t_s or t_ns"):
        store.write_payload("crane-1", kg)
    with pytest.raises(UnknownMachineError):
        store.write_payload("nope", kg[:3], t_ns=t[:3])


@pytest.mark.timeout(10)
def test_runs_of_cuts_at_each_change_of_spacing_the_same_way_every_time() -> None:
    t = np.concatenate([np.arange(0, 10) * 10, 95 + np.arange(0, 5) * 20, [300, 301, 350]])
    t = t.astype(np.int64) + T0_NS
    v = np.arange(t.size, dtype=np.float64)
    runs = runs_of(t, v)
    assert [(r.t0_ns - T0_NS, r.period_ns, r.n) for r in runs] == [
        (0, 10, 10), (95, 20, 5), (300, 1, 2), (350, 0, 1)]
    assert np.array_equal(np.concatenate([r.times_ns() for r in runs]), t)
    assert np.array_equal(np.concatenate([r.payload_kg for r in runs]), v)
    assert [r.t0_ns for r in runs_of(t, v)] == [r.t0_ns for r in runs]
    long = runs_of(T0_NS + np.arange(MAX_RUN + 5, dtype=np.int64), np.zeros(MAX_RUN + 5))
    assert [r.n for r in long] == [MAX_RUN, 5]


def _block(machine: str) -> SampleBlock:
    k = np.arange(40, dtype=np.float64).reshape(10, 4)
    return SampleBlock(machine, 0, T0_NS, PERIOD, ("lift_pA", "lift_pB", "lift_s",
                                                   "slew_torque"), (1.0, 1.0, 1e-4, 1.0),
                       k * np.array([1.0, 1.0, 1e-4, 1.0]))


def test_migration_onto_a_database_with_data_keeps_it(db_url: str) -> None:
    """A database at the previous head (0006c) with a machine and samples: opening it migrates
    to the new head, every row stays, and the payload table is there and works."""
    engine = make_engine(db_url)
    migrate(engine, "0006c")
    assert "payload_runs" not in inspect(engine).get_table_names()
    old = Store(engine)
    old.add_machine("crane-1", 1, SECRET)
    assert old.write_blocks([_block("crane-1")]) == 1
    before = old.read_samples("crane-1", T0_NS / 1e9, T0_NS / 1e9 + 1.0)
    old.close()
    with Store.open(db_url) as st:
        assert "payload_runs" in inspect(st.engine).get_table_names()
        with st.engine.connect() as c:
            assert c.execute(text("SELECT version_num FROM alembic_version")).scalar() == "0007k"
        after = st.read_samples("crane-1", T0_NS / 1e9, T0_NS / 1e9 + 1.0)
        assert np.array_equal(after.t_ns, before.t_ns)
        assert np.array_equal(after.values, before.values, equal_nan=True)
        assert [m.machine_id for m in st.machines()] == ["crane-1"]
        t, kg = _series()
        assert st.write_payload("crane-1", kg, t_ns=t).stored == 1
        assert st.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0).n == 500


@pytest.fixture
def two_schemas() -> Iterator[tuple[str, str]]:
    """Two PostgreSQL schemas standing for two shards."""
    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    import psycopg

    names = [f"t_{uuid.uuid4().hex[:12]}" for _ in range(2)]
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        for n in names:
            conn.execute(f'CREATE SCHEMA "{n}"')
    sep = "&" if "?" in PG_URL else "?"
    yield (f"{PG_URL}{sep}options=-csearch_path%3D{names[0]}",
           f"{PG_URL}{sep}options=-csearch_path%3D{names[1]}")
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        for n in names:
            conn.execute(f'DROP SCHEMA "{n}" CASCADE')


@pytest.mark.postgres
def test_sharded_store_writes_and_reads_on_the_machines_shard(
        two_schemas: tuple[str, str]) -> None:
    urls = two_schemas
    shard_map = ShardMap.parse({"0-1": urls[0], "2-3": urls[1]}, 4)
    a = next(f"crane-{w}" for w in range(1, 99) if partition_of(f"crane-{w}", 4) < 2)
    b = next(f"crane-{w}" for w in range(1, 99) if partition_of(f"crane-{w}", 4) >= 2)
    st = ShardedStore.open_map(shard_map)
    try:
        st.add_machine(a, 1, SECRET)
        st.add_machine(b, 2, SECRET)
        t, kg = _series()
        assert st.write_payload(a, kg, t_ns=t).stored == 1
        assert st.write_payload(b, kg * 2.0, t_ns=t).stored == 1
        assert st.write_payload(b, kg * 2.0, t_ns=t).duplicate == 1
        assert np.array_equal(st.read_payload(b, t[0] / 1e9, t[-1] / 1e9 + 1).payload_kg,
                              kg * 2.0, equal_nan=True)
        assert [_rows(s) for s in st.shards] == [1, 1]  # each on its own shard
        with Store.open(urls[1]) as direct:  # b's shard holds b's series only
            assert np.array_equal(direct.read_payload(b, 0.0, 4e9).payload_kg, kg * 2.0,
                                  equal_nan=True)
        assert st.delete_payload_runs(a, [int(t[0])]) == 1
        assert st.read_payload(a, 0.0, 4e9).n == 0
        # list and delete on b's shard; the redo requests live beside its analytics
        assert [x.values for x in st.payload_stretches(b)] == [500]
        assert st.delete_payload(b, 0.0, float(t[250]) / 1e9).values_deleted == 250
        assert st.read_payload(b, 0.0, 4e9).n == 250 and _rows(st.shards[1]) == 1
        from cranetwin.storage import redo

        assert set(redo.pending(st.engine_for(b), [a, b])) == {b}
        assert set(redo.pending(st.engine_for(a), [a, b])) == {a}  # its write and delete
    finally:
        st.close()


def test_delete_cuts_runs_at_the_bounds_and_asks_for_the_redo(store: Store) -> None:
    """Deleting [a, b) removes exactly what ``read_payload(a, b)`` returns: a run inside goes
    whole, one straddling a bound is cut there (the rest stays, readable as before); the
    changed known times are recorded for the twin worker (merged, NaN values not)."""
    from cranetwin.storage import redo

    t, kg = _series()  # one run: 500 values, NaN at 120-139
    store.write_payload("crane-1", kg, t_ns=t)
    t2 = t[-1] + 3600 * 10**9 + np.arange(50, dtype=np.int64) * PERIOD  # an hour later
    store.write_payload("crane-1", np.full(50, 80.0), t_ns=t2)
    asked = redo.pending(store.engine, ["crane-1", "crane-2"])
    assert set(asked) == {"crane-1"}
    assert [(r.t0_ns, r.t1_ns) for r in asked["crane-1"]] == [
        (int(t[0]), int(t[-1])), (int(t2[0]), int(t2[-1]))]  # two stretches, an hour apart
    assert redo.done(store.engine, "crane-1", asked["crane-1"]) == 2
    all_s = store.payload_stretches("crane-1")
    assert [(s.t_first_ns, s.t_last_ns, s.runs, s.values, s.known) for s in all_s] == [
        (int(t[0]), int(t[-1]), 1, 500, 480), (int(t2[0]), int(t2[-1]), 1, 50, 50)]
    assert (all_s[0].min_kg, all_s[0].max_kg) == (0.0, float(np.nanmax(kg)))
    assert store.payload_stretches("crane-2") == []

    a, b = float(t[100]) / 1e9, float(t[150]) / 1e9  # a cut inside the run, NaN 120-139 in
    gone = store.delete_payload("crane-1", a, b)
    assert (gone.runs_deleted, gone.runs_cut, gone.values_deleted, gone.known_deleted) == (
        0, 1, 50, 30)
    assert gone.changed_ns == ((int(t[100]), int(t[149])),)
    back = store.read_payload("crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)
    keep = np.r_[0:100, 150:500]
    assert np.array_equal(back.t_ns, t[keep])
    assert np.array_equal(back.payload_kg, kg[keep], equal_nan=True)
    assert [(s.t_first_ns, s.t_last_ns, s.runs) for s in store.payload_stretches(
        "crane-1", t[0] / 1e9, t[-1] / 1e9 + 1.0)] == [(int(t[0]), int(t[99]), 1),
                                                        (int(t[150]), int(t[-1]), 1)]
    asked = redo.pending(store.engine, ["crane-1"])["crane-1"]
    assert [(r.t0_ns, r.t1_ns) for r in asked] == [(int(t[100]), int(t[149]))]
    # a request on the same start while the worker redoes: its version moves, it stays
    store.write_payload_runs("crane-1", [PayloadRun(int(t[100]), PERIOD, np.full(3, 5.0))])
    assert redo.done(store.engine, "crane-1", asked) == 0
    assert [r.version for r in redo.pending(store.engine, ["crane-1"])["crane-1"]] == [2]
    # NaN only deleted: nothing to redo; everything: the rest goes, and only that is asked
    gone = store.delete_payload("crane-1", float(t[100]) / 1e9, float(t[103]) / 1e9)
    assert gone.values_deleted == 3 and gone.changed_ns == ((int(t[100]), int(t[102])),)
    gone = store.delete_payload("crane-1", -np.inf, np.inf)
    assert (gone.runs_deleted, gone.runs_cut, gone.values_deleted) == (3, 0, 100 + 350 + 50)
    assert store.read_payload("crane-1", 0.0, 4e9).n == 0 and _rows(store) == 0
    with pytest.raises(UnknownMachineError):
        store.delete_payload("nope", 0.0, 1.0)


@pytest.mark.postgres
def test_retention_drops_the_payload_runs_of_a_dropped_partition(pg_url: str) -> None:
    """A run goes with the time partition its start falls in, as a sample block does: the run
    of a block reaching from February into March goes with February."""
    import datetime as dt

    from cranetwin.service.backend import Backend, Progress

    def ns(*args: int) -> int:
        return int(dt.datetime(*args, tzinfo=dt.UTC).timestamp()) * 10**9

    feb, end, mar = ns(2026, 2, 10), ns(2026, 2, 28, 23, 59, 59) + 950 * 10**6, ns(2026, 3, 5)
    b = Backend.open(pg_url)
    s = b.store
    s.add_machine("crane-1", 1, SECRET)
    blocks = [dc_replace(_block("crane-1"), seq=i, t0_ns=t) for i, t in enumerate((feb, end,
                                                                                  mar))]
    assert [o.status for o in s.write_batch(blocks).outcomes] == ["stored"] * 3
    s.write_payload_runs("crane-1", [PayloadRun(t, PERIOD, np.full(10, 100.0 + i))
                                     for i, t in enumerate((feb, end, mar))])
    s.rollup()
    b.reset_progress(Progress.empty("crane-1", (mar + 10 * 86_400 * 10**9) / 1e9))
    res = s.maintain_partitions(ns(2026, 4, 20) / 1e9, keep_days=30)
    assert res.dropped == ["sample_blocks_p20260201"] and res.payload_runs == 2
    left = s.read_payload("crane-1", 0.0, 4e9)
    assert np.array_equal(left.t_ns, mar + np.arange(10, dtype=np.int64) * PERIOD)
    assert s.read_samples("crane-1", 0.0, 4e9).t_s.size == 10
    b.close()
