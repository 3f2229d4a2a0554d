"""Time-partitioned ``sample_blocks`` on PostgreSQL: the migration from revision 0003b keeps every
row, retransmissions stay duplicates under the (machine, epoch, seq, t_start) key, partitions are
made on demand and ahead, and retention drops only partitions analytics has processed. SQLite
keeps its one table."""

from __future__ import annotations

import datetime as dt
import threading
from typing import Any

import numpy as np
import pytest
from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, text

from cranetwin.samples import SampleBlock
from cranetwin.service.backend import Backend, Progress
from cranetwin.storage import Store, bulk
from cranetwin.storage import blocks as blocks_mod
from cranetwin.storage import partitions as parts
from cranetwin.storage.engine import MIGRATIONS, make_engine, migrate

CHANNELS = ("lift_pA", "lift_pB", "lift_s", "slew_torque")
RES = (5000.0, 5000.0, 1e-4, 5.0)
SECRET = b"0123456789abcdef0123456789abcdef"
SEC = 10**9
DAY_NS = 86_400 * SEC
PERIOD = 10_000_000  # 100 Hz
JAN = int(dt.datetime(2026, 1, 10, tzinfo=dt.UTC).timestamp()) * SEC
MAR = int(dt.datetime(2026, 3, 31, 23, 59, 59, tzinfo=dt.UTC).timestamp()) * SEC
JUL = int(dt.datetime(2026, 7, 1, tzinfo=dt.UTC).timestamp()) * SEC

pytestmark = [pytest.mark.timeout(90)]


def blk(machine: str, seq: int, t0_ns: int, *, epoch: int = 0, n: int = 100) -> SampleBlock:
    rng = np.random.default_rng(seq * 7 + epoch)
    k = np.cumsum(rng.integers(-30, 31, size=(n, len(CHANNELS))), axis=0) + 2000
    return SampleBlock(machine, seq, t0_ns, PERIOD, CHANNELS, RES, k * np.asarray(RES), epoch)


def all_rows(engine: Engine) -> list[tuple[Any, ...]]:
    with engine.connect() as c:
        return [tuple(r) for r in c.execute(text(
            "SELECT id, machine_pk, epoch, seq, t_start_ns, t_end_ns, period_ns, n, channels, "
            "resolution, summary, data FROM sample_blocks ORDER BY id"))]


def statuses(store: Store, blocks: list[SampleBlock]) -> list[str]:
    return [o.reason or o.status for o in store.write_batch(blocks).outcomes]


def relkind(engine: Engine) -> str:
    with engine.connect() as c:
        return str(c.execute(text("SELECT relkind FROM pg_class "
                                  "WHERE oid = to_regclass('sample_blocks')")).scalar())


def partition_names(engine: Engine) -> list[str]:
    with engine.connect() as c:
        return [p.name for p in parts.list_partitions(c)]


# --- the migration ------------------------------------------------------------------------------
def _old_schema_with_blocks(url: str) -> tuple[Engine, list[SampleBlock]]:
    """The schema at 0003b (one plain table), filled the way that code filled it."""
    engine = make_engine(url)
    migrate(engine, "0003b")
    blocks = ([blk("crane-1", s, JAN + s * SEC) for s in range(40)]
              + [blk("crane-1", 100 + s, MAR + s * SEC) for s in range(3)]  # 31 Mar, 1 Apr
              + [blk("crane-2", s, JUL + s * SEC, epoch=3) for s in range(20)])
    with engine.begin() as c:
        for mid, wire in (("crane-1", 1), ("crane-2", 2)):
            c.execute(text("INSERT INTO machines (machine_id, wire_id, model, secret, meta_json) "
                           "VALUES (:m, :w, 'patu655', :s, '{}')"), {"m": mid, "w": wire,
                                                                     "s": SECRET})
        pks = dict(c.execute(text("SELECT machine_id, id FROM machines")).all())
        rows = blocks_mod.block_rows([(pks[b.machine_id], b) for b in blocks])
        bulk.insert_rows(c, "sample_blocks", blocks_mod.COLUMNS,
                         [r for r in rows if not isinstance(r, str)])
        # a legacy row outside the times writers accept now (before the checks existed)
        legacy = blocks_mod.block_rows([(pks["crane-1"], blk("crane-1", 900, JAN))])[0]
        assert not isinstance(legacy, str)
        bulk.insert_rows(c, "sample_blocks", blocks_mod.COLUMNS,
                         [(legacy[0], 0, 900, -5 * SEC, -5 * SEC + 99 * PERIOD) + legacy[5:]])
    return engine, blocks


@pytest.mark.postgres
def test_migration_0004p_keeps_every_block_and_duplicates_stay_duplicates(pg_url: str) -> None:
    engine, blocks = _old_schema_with_blocks(pg_url)
    before = all_rows(engine)
    assert len(before) == len(blocks) + 1 and relkind(engine) == "r"
    store = Store.open(pg_url)  # upgrades 0003b -> head, through 0004p
    try:
        assert relkind(store.engine) == "p"
        assert all_rows(store.engine) == before  # every column of every row, ids included
        assert partition_names(store.engine) == ["sample_blocks_p20260101",
                                                 "sample_blocks_p20260301",  # 31 Mar 23:59:59
                                                 "sample_blocks_p20260401",  # its next blocks
                                                 "sample_blocks_p20260701"]
        with store.engine.connect() as c:
            assert c.execute(text("SELECT count(*) FROM sample_blocks_default")).scalar() == 1
        got = store.read_samples("crane-1", JAN / SEC, (JAN + 40 * SEC) / SEC)
        assert np.array_equal(got.values, np.concatenate([b.values[:100] for b in blocks[:40]]))
        # every stored block written again is a duplicate; nothing new is stored
        assert set(statuses(store, blocks)) == {"duplicate"}
        assert len(all_rows(store.engine)) == len(before)
        # the same seq at another time is still found across partitions
        moved = blk("crane-1", 5, JUL + DAY_NS)
        assert statuses(store, [moved]) == ["seq_reused"]
        # new rows continue the id sequence the old table used
        assert statuses(store, [blk("crane-1", 41, JAN + 41 * SEC)]) == ["stored"]
        assert all_rows(store.engine)[-1][0] > before[-1][0]
    finally:
        store.close()
        engine.dispose()


@pytest.mark.postgres
def test_migration_0004p_downgrade_restores_one_table(pg_url: str) -> None:
    engine, _ = _old_schema_with_blocks(pg_url)
    before = all_rows(engine)
    migrate(engine, "0004p")
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.downgrade(cfg, "0003b")
    assert relkind(engine) == "r" and all_rows(engine) == before
    migrate(engine, "0004p")  # and up again
    assert relkind(engine) == "p" and all_rows(engine) == before
    engine.dispose()


# --- the key: retransmissions deduplicate -------------------------------------------------------
@pytest.fixture
def store(db_url: str) -> Any:
    s = Store.open(db_url)
    s.add_machine("crane-1", 1, SECRET)
    s.add_machine("crane-2", 2, SECRET[::-1])
    yield s
    s.close()


def test_retransmission_is_a_duplicate_under_the_partitioned_key(store: Store, db_url: str
                                                                 ) -> None:
    first = [blk("crane-1", s, JAN + s * SEC) for s in range(10)]
    assert set(statuses(store, first)) == {"stored"}
    # the same blocks again (same seq, same t_start): once from this store, and from two
    # other writers at the same time (ON CONFLICT on (machine, epoch, seq, t_start))
    assert set(statuses(store, first)) == {"duplicate"}
    others = [Store.open(db_url) for _ in range(2)]
    results: list[list[str]] = []
    retrans = first + [blk("crane-1", 10, JAN + 10 * SEC)]

    def write(s: Store) -> None:
        results.append(statuses(s, retrans))

    threads = [threading.Thread(target=write, args=(s,)) for s in others]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for s in others:
        s.close()
    assert sorted(r[-1] for r in results) == ["duplicate", "stored"]
    assert all(set(r[:-1]) == {"duplicate"} for r in results)
    with store.engine.connect() as c:
        n = c.execute(text("SELECT count(*) FROM sample_blocks")).scalar()
        distinct = c.execute(text("SELECT count(*) FROM (SELECT DISTINCT machine_pk, epoch, seq "
                                  "FROM sample_blocks) k")).scalar()
    assert n == distinct == 11
    if store.dialect == "postgresql":
        assert relkind(store.engine) == "p"


# --- partitions made on demand, ahead, and dropped by retention --------------------------------
@pytest.mark.postgres
def test_partitions_on_demand_and_ahead_with_the_recorded_interval(pg_url: str) -> None:
    s = Store.open(pg_url)
    s.add_machine("crane-1", 1, SECRET)
    assert partition_names(s.engine) == []
    assert statuses(s, [blk("crane-1", 0, JAN), blk("crane-1", 1, JUL)]) == ["stored"] * 2
    assert partition_names(s.engine) == ["sample_blocks_p20260101", "sample_blocks_p20260701"]
    # daily from now on: ahead from 30 Jun 12:00 makes 30 Jun (a day) and 1 Jul is covered by
    # July's month; 2 Aug gets a day of its own
    s.maintain_partitions((JUL - DAY_NS // 2) / SEC, ahead=1, interval="day")
    assert partition_names(s.engine) == ["sample_blocks_p20260101", "sample_blocks_p20260630",
                                         "sample_blocks_p20260701"]
    assert statuses(s, [blk("crane-1", 2, JUL + 32 * DAY_NS)]) == ["stored"]
    with s.engine.connect() as c:
        got = {p.name: (p.hi_ns - p.lo_ns) // DAY_NS for p in parts.list_partitions(c)}
        assert parts.get_interval(c) == "day"
    assert got == {"sample_blocks_p20260101": 31, "sample_blocks_p20260630": 1,
                   "sample_blocks_p20260701": 31, "sample_blocks_p20260802": 1}
    # a range read touches only the partitions that can hold a match
    with s.engine.connect() as c:
        plan = "\n".join(r[0] for r in c.execute(text(
            "EXPLAIN SELECT seq FROM sample_blocks WHERE machine_pk = 1 "
            f"AND t_start_ns <= {JAN + SEC} AND t_end_ns >= {JAN} "
            f"AND t_start_ns >= {JAN - blocks_mod.MAX_SPAN_NS}")))
    assert "sample_blocks_p20260101" in plan and "p20260701" not in plan, plan
    s.close()


@pytest.mark.postgres
def test_retention_drops_only_processed_partitions(pg_url: str) -> None:
    b = Backend.open(pg_url)
    s = b.store
    for m, w in (("crane-1", 1), ("crane-2", 2)):
        s.add_machine(m, w, SECRET)
    assert statuses(s, [blk("crane-1", 0, JAN), blk("crane-2", 0, JAN + SEC),
                        blk("crane-1", 1, MAR), blk("crane-1", 2, JUL)]) == ["stored"] * 4
    s.rollup()
    now = (JUL + 10 * DAY_NS) / SEC
    # nothing processed yet: January and March are past retention but kept
    res = s.maintain_partitions(now, keep_days=60)
    assert res.dropped == [] and [k for k, _ in res.kept] == ["sample_blocks_p20260101",
                                                            "sample_blocks_p20260301"]
    assert "no twin-worker progress" in res.kept[0][1]
    # crane-1 processed into May, crane-2 not at all: only March may go
    b.reset_progress(Progress.empty("crane-1", (MAR + 40 * DAY_NS) / SEC))
    res = s.maintain_partitions(now, keep_days=60, margin_s=5.0)
    assert res.dropped == ["sample_blocks_p20260301"]
    assert "crane-2" in res.kept[0][1]
    # crane-2 processed to just inside the replay margin of its block: still kept
    b.reset_progress(Progress.empty("crane-2", (JAN + SEC + 99 * PERIOD) / SEC + 4.0))
    assert s.maintain_partitions(now, keep_days=60, margin_s=5.0).dropped == []
    b.reset_progress(Progress.empty("crane-2", (JAN + 2 * DAY_NS) / SEC))
    # a minute waiting for the 1-min rollup keeps it too
    with s.engine.begin() as c:
        c.execute(text("INSERT INTO summary_dirty (machine_pk, minute_s, version) "
                       f"VALUES (1, {JAN // SEC // 60 * 60}, 1)"))
    assert "rollup" in s.maintain_partitions(now, keep_days=60, margin_s=5.0).kept[0][1]
    s.rollup()
    assert s.maintain_partitions(now, keep_days=60, margin_s=5.0).dropped == [
        "sample_blocks_p20260101"]
    assert partition_names(s.engine)[0] == "sample_blocks_p20260701"
    assert s.stats().blocks == 1
    # a writer whose cache still holds the dropped range makes the partition again
    other = Store.open(pg_url)
    assert statuses(other, [blk("crane-1", 3, JUL + SEC)]) == ["stored"]  # caches July
    with other.engine.begin() as c:  # July dropped behind its back (another process)
        c.execute(text("DROP TABLE sample_blocks_p20260701"))
    assert statuses(other, [blk("crane-1", 4, JUL + 2 * SEC)]) == ["stored"]
    assert "sample_blocks_p20260701" in partition_names(s.engine)
    other.close()
    b.close()


def test_sqlite_keeps_one_table_and_maintenance_is_a_no_op(sqlite_url: str) -> None:
    s = Store.open(sqlite_url)
    s.add_machine("crane-1", 1, SECRET)
    assert statuses(s, [blk("crane-1", 0, JAN), blk("crane-1", 1, JUL)]) == ["stored"] * 2
    res = s.maintain_partitions(JUL / SEC + 1e8, keep_days=1)
    assert res.dropped == [] and res.kept == [] and s.stats().blocks == 2
    with s.engine.connect() as c:
        assert c.execute(text("SELECT count(*) FROM sqlite_master WHERE type = 'table' "
                              "AND name LIKE 'sample_blocks%'")).scalar() == 1
    s.close()
