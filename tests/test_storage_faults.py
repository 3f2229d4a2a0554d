"""Storage under faults, on SQLite and PostgreSQL: the (machine, epoch, seq) identity and its
migration, per-block outcomes of ``write_batch`` (duplicates, reused sequence numbers, overlapping
samples, poison values, blocks the database itself rejects), outages (a lock held too long, a cut
connection, terminated backends), a rollup that never stops at a bad row, reading across long
gaps, and private database files."""

from __future__ import annotations

import os
import socket
import sqlite3
import stat
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import event, text

from cranetwin.errors import StorageError, StorageUnavailableError
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, WriteResult, bulk
from cranetwin.storage import blocks as blocks_mod
from cranetwin.storage import summaries as summaries_mod
from cranetwin.storage.engine import make_engine, migrate

CHANNELS = ("lift_pA", "lift_pB", "lift_s", "slew_torque")
RES = (5000.0, 5000.0, 1e-4, 5.0)
T0_NS = 1_700_000_000 * 10**9 + 250_000_000
PERIOD = 10_000_000  # 100 Hz
SECRET = b"0123456789abcdef0123456789abcdef"
DAY_NS = 86_400 * 10**9

pytestmark = pytest.mark.timeout(60)


def blk(machine: str, seq: int, *, epoch: int = 0, n: int = 100, t0_ns: int | None = None,
        period: int = PERIOD, values: np.ndarray | None = None) -> SampleBlock:
    """Block ``seq`` of ``n`` samples right after block ``seq - 1`` (random-walk values)."""
    rng = np.random.default_rng(seq * 7 + epoch)
    if values is None:
        k = np.cumsum(rng.integers(-30, 31, size=(n, len(CHANNELS))), axis=0) + 2000
        values = k * np.asarray(RES)
    t0 = T0_NS + seq * n * period if t0_ns is None else t0_ns
    return SampleBlock(machine, seq, t0, period, CHANNELS, RES, values, epoch)


@pytest.fixture
def store(db_url: str) -> Iterator[Store]:
    s = Store.open(db_url)
    s.add_machine("crane-1", 1, SECRET)
    s.add_machine("crane-2", 2, SECRET[::-1])
    s.maintain_partitions(T0_NS / 1e9)  # PostgreSQL: T0's time partition made ahead (a commit)
    yield s
    s.close()


def statuses(res: WriteResult) -> list[str]:
    return [o.reason or o.status for o in res.outcomes]


def stored_keys(store: Store) -> set[tuple[str, int, int]]:
    with store.engine.connect() as c:
        rows = c.execute(text("SELECT m.machine_id, b.epoch, b.seq FROM sample_blocks b "
                              "JOIN machines m ON m.id = b.machine_pk")).all()
    return {(str(m), int(e), int(q)) for m, e, q in rows}


def scalar(store: Store, sql: str) -> Any:
    with store.engine.connect() as c:
        return c.execute(text(sql)).scalar()


# --- identity and migration ----------------------------------------------------------------------
def test_migration_keeps_old_rows_as_epoch_0_and_keys_on_epoch(db_url: str) -> None:
    engine = make_engine(db_url)
    migrate(engine, "0001a")  # the schema before the epoch
    with engine.begin() as c:
        c.execute(text("INSERT INTO machines (machine_id, wire_id, model, secret, meta_json) "
                       "VALUES ('crane-1', 1, 'patu655', :s, '{}')"), {"s": SECRET})
        pk = c.execute(text("SELECT id FROM machines")).scalar()
        old = blocks_mod.block_rows([(pk, blk("crane-1", 0)), (pk, blk("crane-1", 1))])
        cols = [c for c in blocks_mod.COLUMNS if c != "epoch"]
        bulk.insert_rows(c, "sample_blocks", cols,
                         [r[:1] + r[2:] for r in old if not isinstance(r, str)])
    engine.dispose()
    s = Store.open(db_url)  # migrates to the newest revision
    assert stored_keys(s) == {("crane-1", 0, 0), ("crane-1", 0, 1)}
    # the same seq in another epoch is another block (later in time: no overlap)
    later = blk("crane-1", 0, epoch=7, t0_ns=T0_NS + DAY_NS)
    assert statuses(s.write_batch([later, blk("crane-1", 1)])) == ["stored", "duplicate"]
    assert stored_keys(s) == {("crane-1", 0, 0), ("crane-1", 0, 1), ("crane-1", 7, 0)}
    got = s.read_samples("crane-1", 0, 2e9)
    assert got.t_s.size == 300
    s.close()


# --- write_batch outcomes ------------------------------------------------------------------------
def test_write_batch_outcomes_new_duplicate_reused_unknown(store: Store) -> None:
    a = [blk("crane-1", s, epoch=5) for s in range(4)]
    res = store.write_batch(a)
    assert statuses(res) == ["stored"] * 4 and res.new == a and res.durable == a
    moved = blk("crane-1", 2, epoch=5, t0_ns=T0_NS + 10 * DAY_NS)  # same key, other t0
    shorter = blk("crane-1", 3, epoch=5, n=50)  # same key and t0, other n
    other_epoch = blk("crane-1", 2, epoch=6, t0_ns=T0_NS + 20 * DAY_NS)
    res = store.write_batch([a[1], moved, shorter, blk("nope", 0), other_epoch,
                             blk("crane-2", 2, epoch=5)])
    assert statuses(res) == ["duplicate", "seq_reused", "seq_reused", "unknown_machine",
                             "stored", "stored"]
    assert [o.durable for o in res.outcomes] == [True, False, False, False, True, True]
    assert res.counts() == {"duplicate": 1, "seq_reused": 2, "unknown_machine": 1, "stored": 2}
    assert "seq 2" in res.outcomes[1].detail
    # nothing of a refused block is stored: crane-1 epoch 5 reads back exactly the first four
    got = store.read_samples("crane-1", 0, (T0_NS + DAY_NS) / 1e9)
    assert np.array_equal(got.values, np.concatenate([b.values for b in a]))
    assert store.stats().blocks == 6


def test_write_batch_same_key_twice_in_one_batch(store: Store) -> None:
    b = blk("crane-1", 0)
    other = blk("crane-1", 0, t0_ns=T0_NS + DAY_NS)
    res = store.write_batch([b, b, other])
    assert statuses(res) == ["stored", "duplicate", "seq_reused"]
    bad = blk("crane-1", 1, values=np.full((100, 4), np.inf))
    assert statuses(store.write_batch([bad, bad])) == ["unstorable", "unstorable"]
    assert store.stats().blocks == 1


def _poison(kind: str) -> SampleBlock:
    good = blk("crane-1", 1)
    v = good.values.copy()
    big = 2**63
    match kind:
        case "t0_min":
            return SampleBlock("crane-1", 1, -(2**63), 1, CHANNELS, RES, v[:1])
        case "t0_negative":
            return SampleBlock("crane-1", 1, -1, PERIOD, CHANNELS, RES, v)
        case "t0_near_max":
            return SampleBlock("crane-1", 1, big - 11, PERIOD, CHANNELS, RES, v[:1])
        case "t_end_past_limit":
            return SampleBlock("crane-1", 1, blocks_mod.T_LIMIT_NS - 5 * PERIOD, PERIOD, CHANNELS,
                               RES, v)
        case "span_too_long":
            return SampleBlock("crane-1", 1, T0_NS, 3600 * 10**9, CHANNELS, RES, v)  # 99 h
        case "inf_value":
            v[3, 2] = np.inf
        case "too_large_for_resolution":
            v[3, 0] = 1e300
        case "seq_2_63":
            return SampleBlock("crane-1", big, T0_NS, PERIOD, CHANNELS, RES, v)
        case "seq_2_64_minus_1":
            return SampleBlock("crane-1", 2**64 - 1, T0_NS, PERIOD, CHANNELS, RES, v)
        case "seq_negative":
            return SampleBlock("crane-1", -1, T0_NS, PERIOD, CHANNELS, RES, v)
        case "epoch_2_63":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, CHANNELS, RES, v, big)
        case "period_0":
            return SampleBlock("crane-1", 1, T0_NS, 0, CHANNELS, RES, v)
        case "no_samples":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, CHANNELS, RES, v[:0])
        case "channel_count":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, CHANNELS[:3], RES, v)
        case "duplicate_channel":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, ("a", "a", "b", "c"), RES, v)
        case "long_channel_name":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, ("x" * 65, *CHANNELS[1:]), RES, v)
        case "resolution_0":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, CHANNELS, (0.0, *RES[1:]), v)
        case "resolution_nan":
            return SampleBlock("crane-1", 1, T0_NS, PERIOD, CHANNELS, (float("nan"), *RES[1:]), v)
    return SampleBlock("crane-1", 1, good.t0_ns, PERIOD, CHANNELS, RES, v)


POISON = ["t0_min", "t0_negative", "t0_near_max", "t_end_past_limit", "span_too_long",
          "inf_value", "too_large_for_resolution", "seq_2_63", "seq_2_64_minus_1",
          "seq_negative", "epoch_2_63", "period_0", "no_samples", "channel_count",
          "duplicate_channel", "long_channel_name", "resolution_0", "resolution_nan"]


@pytest.mark.parametrize("kind", POISON)
def test_one_unstorable_block_is_refused_alone(store: Store, kind: str) -> None:
    others = [blk("crane-2", s) for s in range(5)] + [blk("crane-1", 0), blk("crane-1", 2)]
    batch = others[:3] + [_poison(kind)] + others[3:]
    res = store.write_batch(batch)
    assert statuses(res) == ["stored"] * 3 + ["unstorable"] + ["stored"] * 4, res.outcomes[3]
    assert res.outcomes[3].detail
    assert stored_keys(store) == {(b.machine_id, 0, b.seq) for b in others}
    assert store.rollup() >= 1  # nothing that slipped in can stop the rollup
    assert scalar(store, "SELECT count(*) FROM summary_dirty") == 0
    assert store.rollup_skipped == 0


def _add_insert_trigger(store: Store, table: str, condition: str) -> None:
    """A trigger that makes the database reject rows of ``table`` matching ``condition``
    (a data error on PostgreSQL, a constraint error on SQLite): faults validation cannot see."""
    with store.engine.begin() as c:
        if store.dialect == "sqlite":
            c.execute(text(f"CREATE TRIGGER poison_{table} BEFORE INSERT ON {table} "
                           f"WHEN {condition.replace('x.', 'NEW.')} "
                           "BEGIN SELECT RAISE(ABORT, 'poisoned row'); END"))
        else:
            c.execute(text(f"CREATE FUNCTION poison_{table}() RETURNS trigger AS $$ BEGIN "
                           f"IF {condition.replace('x.', 'NEW.')} THEN RAISE EXCEPTION "
                           "'poisoned row' USING ERRCODE = '22023'; END IF; RETURN NEW; END "
                           "$$ LANGUAGE plpgsql"))
            c.execute(text(f"CREATE TRIGGER poison_{table} BEFORE INSERT ON {table} "
                           f"FOR EACH ROW EXECUTE FUNCTION poison_{table}()"))


def _count_commits(store: Store) -> list[int]:
    commits: list[int] = []
    event.listen(store.engine, "commit", lambda _conn: commits.append(1))
    return commits


def test_blocks_the_database_rejects_are_isolated_by_bisection(store: Store) -> None:
    _add_insert_trigger(store, "sample_blocks", "x.seq IN (3, 17, 18)")
    batch = [blk(m, s) for s in range(30) for m in ("crane-1", "crane-2")]
    commits = _count_commits(store)
    res = store.write_batch(batch)
    assert len(commits) == 1  # trials are rolled back; one transaction stores all good blocks
    bad = {i for i, b in enumerate(batch) if b.seq in (3, 17, 18)}
    assert [i for i, o in enumerate(res.outcomes) if not o.durable] == sorted(bad)
    for i in bad:
        assert res.outcomes[i].reason == "unstorable"
        assert "poisoned row" in res.outcomes[i].detail
    assert stored_keys(store) == {(b.machine_id, 0, b.seq) for i, b in enumerate(batch)
                                  if i not in bad}
    # the minutes of the stored blocks are dirty, and roll up
    assert store.rollup() >= 2 and scalar(store, "SELECT count(*) FROM summary_dirty") == 0


def test_an_out_of_range_integer_that_passes_the_checks_is_isolated_by_the_database(
        store: Store, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(blocks_mod, "check_block", lambda _b: None)  # validation "forgot" it
    good = [blk("crane-2", s) for s in range(4)]
    batch = [*good[:2], _poison("seq_2_63"), *good[2:]]
    res = store.write_batch(batch)
    assert statuses(res) == ["stored", "stored", "unstorable", "stored", "stored"]
    assert stored_keys(store) == {("crane-2", 0, s) for s in range(4)}


def test_a_batch_that_fails_but_no_block_alone_raises_and_stores_nothing(
        store: Store, monkeypatch: pytest.MonkeyPatch) -> None:
    from sqlalchemy.exc import IntegrityError

    real = summaries_mod.mark_dirty

    def fail_when_big(session: Any, minutes: Any) -> None:
        minutes = list(minutes)
        if len(minutes) > 3:  # a fault of the batch as a whole (4 minutes; a half spans ≤ 3)
            raise IntegrityError("INSERT", {}, Exception("batch too big"))
        real(session, minutes)

    monkeypatch.setattr(summaries_mod, "mark_dirty", fail_when_big)
    with pytest.raises(StorageError, match="no block fails alone") as err:
        store.write_batch([blk("crane-1", s, n=3000) for s in range(6)])  # 30 s each
    assert not isinstance(err.value, StorageUnavailableError)
    assert store.stats().blocks == 0


def test_a_failure_that_is_no_data_error_refuses_nothing_and_stores_nothing(
        store: Store, monkeypatch: pytest.MonkeyPatch) -> None:
    from sqlalchemy.exc import ProgrammingError

    def bug(*_a: Any) -> None:  # e.g. a broken statement: not the blocks' fault
        raise ProgrammingError("INSERT INTO summary_dirty", {}, Exception("syntax error"))

    monkeypatch.setattr(summaries_mod, "mark_dirty", bug)
    commits = _count_commits(store)
    with pytest.raises(StorageError, match="nothing stored") as err:
        store.write_batch([blk("crane-1", s) for s in range(4)])
    assert not isinstance(err.value, StorageUnavailableError)
    assert store.stats().blocks == 0 and commits == []


# --- overlapping samples -------------------------------------------------------------------------
def test_overlapping_blocks_are_refused_so_samples_and_history_agree(store: Store) -> None:
    a = blk("crane-1", 0, n=250)  # 2.5 s from T0
    assert statuses(store.write_batch([a])) == ["stored"]
    same_times = blk("crane-1", 1, t0_ns=a.t0_ns, n=250)  # another seq, the same timestamps
    touching = blk("crane-1", 2, t0_ns=a.t_end_ns)  # shares the last sample time
    inside = blk("crane-1", 3, t0_ns=a.t0_ns + 5 * PERIOD, n=3, epoch=9)
    adjacent = blk("crane-1", 4, t0_ns=a.t_end_ns + PERIOD, n=100)
    in_batch = blk("crane-1", 5, t0_ns=adjacent.t0_ns + 50 * PERIOD, n=100)  # overlaps #4
    elsewhere = blk("crane-2", 1, t0_ns=a.t0_ns, n=250)  # another machine: independent
    before = blk("crane-1", 6, t0_ns=a.t0_ns - 100 * PERIOD, n=100)  # ends right before a
    res = store.write_batch([same_times, touching, inside, adjacent, in_batch, elsewhere, before])
    assert statuses(res) == ["overlap", "overlap", "overlap", "stored", "overlap", "stored",
                             "stored"]
    assert "seq 0" in res.outcomes[0].detail and "same batch" in res.outcomes[4].detail
    # a retransmission of a stored block is a duplicate, not an overlap
    assert statuses(store.write_batch([a, adjacent])) == ["duplicate", "duplicate"]
    raw = store.read_samples("crane-1", 0, 2e9)
    assert raw.t_s.size == 450 and np.all(np.diff(raw.t_s) > 0)
    store.rollup()
    for mp in (1000, 3):
        summ = store.summaries("crane-1", ["lift_s"], raw.t_s[0] - 1, raw.t_s[-1] + 1, mp)
        assert int(summ.count.sum()) == raw.t_s.size  # /history counts what /samples shows


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(spans=st.lists(st.tuples(st.integers(0, 60), st.integers(1, 12)), min_size=1, max_size=12),
       split=st.integers(0, 12))
def test_stored_blocks_never_overlap_and_refusals_are_real_overlaps(
        store: Store, spans: list[tuple[int, int]], split: int) -> None:
    machine = f"m-{uuid.uuid4().hex[:8]}"
    store.add_machine(machine, int(uuid.uuid4().int % 2**32), SECRET)
    bl = [blk(machine, i, t0_ns=T0_NS + a * PERIOD, n=n) for i, (a, n) in enumerate(spans)]
    outcomes = (list(store.write_batch(bl[:split]).outcomes)
                + list(store.write_batch(bl[split:]).outcomes))
    kept = [b for b, o in zip(bl, outcomes, strict=True) if o.status == "stored"]
    iv = sorted((b.t0_ns, b.t_end_ns) for b in kept)
    assert all(e < s for (_, e), (s, _) in zip(iv, iv[1:], strict=False))
    for b, o in zip(bl, outcomes, strict=True):
        if o.reason == "overlap":  # refused only if it really meets a stored block
            assert any(b.t0_ns <= k.t_end_ns and k.t0_ns <= b.t_end_ns for k in kept)
        else:
            assert o.status == "stored"
    raw = store.read_samples(machine, 0, 2e9)
    assert raw.t_s.size == sum(b.n for b in kept)


# --- outages -------------------------------------------------------------------------------------
@pytest.fixture
def sqlite_store(sqlite_url: str) -> Iterator[Store]:
    s = Store.open(sqlite_url, busy_timeout_s=0.2)
    s.add_machine("crane-1", 1, SECRET)
    yield s
    s.close()


@contextmanager
def sqlite_locked(store: Store) -> Iterator[None]:
    """Another connection holding the write lock (a writer that does not let go)."""
    path = store.engine.url.database
    assert path
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN IMMEDIATE")
    try:
        yield
    finally:
        other.execute("ROLLBACK")
        other.close()


def test_sqlite_locked_too_long_is_unavailable_and_stores_nothing(sqlite_store: Store) -> None:
    s = sqlite_store
    s.write_batch([blk("crane-1", 0)])
    batch = [blk("crane-1", q) for q in range(1, 6)]
    with sqlite_locked(s):
        t = time.monotonic()
        with pytest.raises(StorageUnavailableError, match="locked"):
            s.write_batch(batch)
        assert time.monotonic() - t < 5
        with pytest.raises(StorageUnavailableError):
            s.rollup()
    assert s.stats().blocks == 1
    assert scalar(s, "SELECT count(*) FROM summary_dirty") >= 1  # the rollup did not run
    assert statuses(s.write_batch(batch)) == ["stored"] * 5  # the retry
    assert s.rollup() >= 1 and scalar(s, "SELECT count(*) FROM summary_dirty") == 0


def test_connection_lost_mid_transaction_commits_nothing(
        store: Store, monkeypatch: pytest.MonkeyPatch) -> None:
    from sqlalchemy.exc import OperationalError

    def lost(*_a: Any) -> None:  # the blocks are inserted, then the connection goes
        raise OperationalError("INSERT INTO summary_dirty", {}, Exception("connection lost"))

    monkeypatch.setattr(summaries_mod, "mark_dirty", lost)
    with pytest.raises(StorageUnavailableError, match="connection lost"):
        store.write_batch([blk("crane-1", s) for s in range(5)])
    assert store.stats().blocks == 0


class Proxy:
    """A TCP forwarder to PostgreSQL that can be cut (every connection closed, new ones
    refused) and restored on the same port: a database outage as the client sees it."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self.port = 0
        self.conns: set[socket.socket] = set()
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.acceptor: threading.Thread | None = None
        self.restore()

    def restore(self) -> None:
        srv = socket.create_server(("127.0.0.1", self.port))  # SO_REUSEADDR: the same port
        srv.settimeout(0.05)
        self.port = srv.getsockname()[1]
        self.stop.clear()
        self.acceptor = threading.Thread(target=self._accept, args=(srv,), daemon=True)
        self.acceptor.start()

    def cut(self) -> None:
        self.stop.set()
        if self.acceptor is not None:
            self.acceptor.join(5)  # the listening socket is closed: connects are refused
        with self.lock:
            for c in self.conns:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self.conns.clear()

    def _accept(self, srv: socket.socket) -> None:
        with srv:
            while not self.stop.is_set():
                try:
                    client, _ = srv.accept()
                except TimeoutError:
                    continue
                client.settimeout(None)
                try:
                    upstream = socket.create_connection(self.target, timeout=5)
                except OSError:
                    client.close()
                    continue
                upstream.settimeout(None)
                with self.lock:
                    self.conns.update((client, upstream))
                for a, b in ((client, upstream), (upstream, client)):
                    threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            for s in (a, b):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


@pytest.mark.postgres
def test_postgres_outage_is_unavailable_then_the_store_reconnects(pg_url: str) -> None:
    from sqlalchemy.engine import make_url

    u = make_url(pg_url)
    proxy = Proxy((u.host or "127.0.0.1", u.port or 5432))
    s = Store.open(u.set(port=proxy.port).render_as_string(hide_password=False))
    try:
        s.add_machine("crane-1", 1, SECRET)
        assert statuses(s.write_batch([blk("crane-1", 0)])) == ["stored"]
        s.write_batch([blk("crane-1", 1)])
        batch = [blk("crane-1", q) for q in range(2, 8)]
        proxy.cut()
        for _ in range(3):  # the daemon's retries during the outage, with backoff
            with pytest.raises(StorageUnavailableError):
                s.write_batch(batch)
            with pytest.raises(StorageUnavailableError):
                s.rollup()
            time.sleep(0.2)
        proxy.restore()
        assert statuses(s.write_batch(batch)) == ["stored"] * 6
        assert statuses(s.write_batch(batch[:2])) == ["duplicate"] * 2
        assert s.stats().blocks == 8
        assert s.read_samples("crane-1", 0, 2e9).t_s.size == 800
        assert s.rollup() >= 1
    finally:
        s.close()
        proxy.cut()


@pytest.mark.postgres
def test_postgres_terminated_backends_are_replaced(pg_url: str) -> None:
    import psycopg

    conninfo = "postgresql://" + pg_url.split("://", 1)[1].split("?", 1)[0]
    app = f"cranetwin-test-{uuid.uuid4().hex[:8]}"
    s = Store.open(f"{pg_url}&application_name={app}")
    try:
        s.add_machine("crane-1", 1, SECRET)
        for q in range(3):
            s.write_batch([blk("crane-1", q)])
            with psycopg.connect(conninfo, autocommit=True) as c:
                n = c.execute("SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                              "WHERE application_name = %s", (app,)).fetchone()
            assert n is not None and n[0] >= 1  # the store's pooled connection was killed
        assert statuses(s.write_batch([blk("crane-1", 3)])) == ["stored"]
        assert s.rollup() >= 1
        assert s.stats().blocks == 4
    finally:
        s.close()


# --- the rollup never stops at one bad row -------------------------------------------------------
def _insert_unchecked(store: Store, b: SampleBlock) -> None:
    """Store a block as an older version did, without today's checks (a row that slipped in)."""
    pk = store._machine_pks({b.machine_id})[b.machine_id]
    (row,) = blocks_mod.block_rows([(pk, b)])
    assert not isinstance(row, str)
    with store._session() as s, s.begin():
        bulk.insert_rows(s.connection(), "sample_blocks", blocks_mod.COLUMNS, [row])
        summaries_mod.mark_dirty(s, summaries_mod.block_minutes(pk, b.t0_ns, b.t_end_ns))


def test_rollup_survives_rows_that_slipped_in_and_corrupt_summaries(store: Store) -> None:
    v = blk("crane-1", 0).values
    _insert_unchecked(store, SampleBlock("crane-1", 90, -(2**63), 5, CHANNELS, RES, v[:2]))
    _insert_unchecked(store, SampleBlock("crane-1", 91, 2**63 - 11, PERIOD, CHANNELS, RES,
                                         v[:1]))
    good = [blk("crane-1", q, n=250) for q in range(60)]  # 150 s: three minutes
    store.write_batch(good)
    victim = good[30]
    with store.engine.begin() as c:
        c.execute(text("UPDATE sample_blocks SET summary = :b WHERE seq = 30"),
                  {"b": b"\x01\x08\x80\x00garbage"})
    assert store.rollup() == 5  # the two far minutes too (bounds clamped) and the three good ones
    assert scalar(store, "SELECT count(*) FROM summary_dirty") == 0
    assert store.corrupt_summaries == 1 and store.rollup_skipped == 0
    raw = store.read_samples("crane-1", good[0].t0_ns / 1e9, good[-1].t_end_ns / 1e9 + 1)
    assert raw.t_s.size == 60 * 250
    for mp in (1000, 3):  # 1-s and 1-min levels leave out only the corrupt row's samples
        summ = store.summaries("crane-1", ["lift_s"], raw.t_s[0] - 1, raw.t_s[-1] + 1, mp)
        assert int(summ.count.sum()) == raw.t_s.size - victim.n
    # the far-away rows break neither reads nor summaries of any range (the sample at
    # 2**63 − 11 ns lies above the largest upper bound, 2**63 − 1 ns − 1 µs)
    assert store.read_samples("crane-1", -1e12, 1e12).t_s.size == 60 * 250 + 2
    store.summaries("crane-1", ["lift_s"], -1e10, 1e10, 100)


def test_rollup_drops_a_minute_it_cannot_write_and_rolls_up_the_rest(store: Store) -> None:
    good = [blk("crane-1", q, n=250) for q in range(60)]  # minutes m0, m0+60, m0+120
    store.write_batch(good)
    m1 = (good[0].t0_ns // 60_000_000_000 + 1) * 60
    _add_insert_trigger(store, "summaries", f"x.bucket_s = {m1}")
    assert store.rollup() == 2
    assert store.rollup_skipped == 1
    assert scalar(store, "SELECT count(*) FROM summary_dirty") == 0
    assert scalar(store, f"SELECT count(*) FROM summaries WHERE bucket_s = {m1}") == 0
    assert scalar(store, f"SELECT count(*) FROM summaries WHERE bucket_s = {m1 - 60}") == 4


def test_rollup_drops_a_minute_it_cannot_compute(store: Store,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    good = [blk("crane-1", q, n=250) for q in range(60)]
    store.write_batch(good)
    m0 = good[0].t0_ns // 60_000_000_000 * 60
    real = summaries_mod._minute_from_seconds

    def broken(session: Any, pk: int, minute: int, corrupt: Any = None) -> Any:
        if minute == m0:
            raise ZeroDivisionError("a bug met by one minute's data")
        return real(session, pk, minute, corrupt)

    monkeypatch.setattr(summaries_mod, "_minute_from_seconds", broken)
    assert store.rollup() == 2 and store.rollup_skipped == 1
    assert scalar(store, "SELECT count(*) FROM summary_dirty") == 0
    assert store.rollup() == 0


# --- reading back across gaps --------------------------------------------------------------------
def test_reads_continue_past_a_500_day_gap(store: Store) -> None:
    a = blk("crane-1", 0)
    b = blk("crane-1", 1, t0_ns=a.t0_ns + 500 * DAY_NS)
    store.write_batch([a, b])
    got = store.read_samples("crane-1", a.t0_ns / 1e9, b.t_end_ns / 1e9 + 1)
    assert got.t_s.size == 200
    assert np.array_equal(got.values, np.concatenate([a.values, b.values]))
    nxt = store.next_block_start("crane-1", a.t_end_ns / 1e9 + 1)
    assert nxt == pytest.approx(b.t0_ns / 1e9, abs=1e-6)
    lo, hi = store.data_range("crane-1") or (0.0, 0.0)
    assert (lo, hi) == (pytest.approx(a.t0_ns / 1e9), pytest.approx(b.t_end_ns / 1e9))


# --- private database files ----------------------------------------------------------------------
@pytest.fixture
def umask_022() -> Iterator[None]:
    old = os.umask(0o022)  # the usual umask, under which files are created 0644
    yield
    os.umask(old)


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_sqlite_files_are_private(tmp_path: Path, umask_022: None) -> None:
    path = tmp_path / "secrets.db"
    s = Store.open(f"sqlite:///{path}")
    s.add_machine("crane-1", 1, SECRET)
    s.write_batch([blk("crane-1", 0)])
    with s.engine.connect() as c:  # keep a connection open: -wal and -shm exist meanwhile
        c.execute(text("SELECT count(*) FROM machines")).scalar()
        for suffix in ("", "-wal", "-shm"):
            f = Path(f"{path}{suffix}")
            assert f.exists(), suffix
            assert _mode(f) == 0o600, (suffix, oct(_mode(f)))
    s.close()
    # a rollback journal (a tool opening the file in DELETE mode) inherits the mode as well
    con = sqlite3.connect(path, isolation_level=None)
    con.execute("PRAGMA journal_mode=DELETE")
    con.execute("BEGIN IMMEDIATE")
    con.execute("UPDATE machines SET meta_json = '{\"x\": 1}'")
    journal = Path(f"{path}-journal")
    assert journal.exists() and _mode(journal) == 0o600
    con.execute("ROLLBACK")
    con.close()
    # the check of the test itself: without the engine, the same umask gives 0644
    plain = tmp_path / "plain.db"
    sqlite3.connect(plain).execute("CREATE TABLE t (x)").connection.close()
    assert _mode(plain) == 0o644


def test_existing_world_readable_database_is_reported(tmp_path: Path, umask_022: None,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "old.db"
    sqlite3.connect(path).execute("CREATE TABLE t (x)").connection.close()
    with caplog.at_level("WARNING", logger="cranetwin.storage.engine"):
        Store.open(f"sqlite:///{path}").close()
    assert "chmod 600" in caplog.text and str(path) in caplog.text
