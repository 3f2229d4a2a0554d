"""Machines sharded across databases by a partition map (:mod:`cranetwin.storage.shards`), on
the real PostgreSQL server: two databases ``h_shards_a_*`` and ``h_shards_b_*`` stand for two
servers. A shard "goes down" by refusing connections (``ALLOW_CONNECTIONS false`` and its
sessions terminated): every new connection fails as it would with the server gone.

Also the storage writer's Prometheus ``/metrics``, scraped from the ``cranetwin store-writer``
command writing to the shards.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import PG_URL, SECRET, _pg_conninfo, pg_unreachable_reason, running_daemon
from cranetwin.errors import StorageError, StorageUnavailableError
from cranetwin.settings import Settings
from cranetwin.storage import ShardedStore, Store, StoreSpec, open_store, store_spec
from cranetwin.storage.sharding import partition_of
from cranetwin.storage.shardmap import ShardMap, ShardMapError
from test_bus import block, delete_stream, fresh_bus, nats_unreachable_reason, stored_keys
from test_ingest_daemon import drive, grid_values, make_sender

P = 4
MAP = {"0-1": "a", "2-3": "b"}  # URLs filled in by the fixture


def _machines_on(shard_parts: range, prefix: str = "crane-", count: int = 2) -> list[int]:
    """Wire ids w whose machine ``crane-w`` falls in ``shard_parts``."""
    out = [w for w in range(1, 200) if partition_of(f"{prefix}{w}", P) in shard_parts]
    return out[:count]


A_WIRES = _machines_on(range(0, 2))
B_WIRES = _machines_on(range(2, 4))


def _psql(sql: str) -> None:
    import psycopg

    with psycopg.connect(_pg_conninfo(), autocommit=True) as c:
        c.execute(sql)


def _db_url(name: str) -> str:
    base = PG_URL.rsplit("/", 1)[0]
    return f"{base}/{name}"


class Shards:
    """Two fresh databases standing for two servers, and the means to take one down."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:8]
        self.names = (f"h_shards_a_{tag}", f"h_shards_b_{tag}")
        for n in self.names:
            _psql(f'CREATE DATABASE "{n}"')
        self.urls = tuple(_db_url(n) for n in self.names)
        self.map = {"0-1": self.urls[0], "2-3": self.urls[1]}

    def spec(self) -> StoreSpec:
        return StoreSpec.of(PG_URL, self.map, P)

    def down(self, i: int) -> None:
        n = self.names[i]
        _psql(f'ALTER DATABASE "{n}" ALLOW_CONNECTIONS false')
        _psql(f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{n}'")

    def up(self, i: int) -> None:
        _psql(f'ALTER DATABASE "{self.names[i]}" ALLOW_CONNECTIONS true')

    def drop(self) -> None:
        for n in self.names:
            _psql(f'DROP DATABASE IF EXISTS "{n}" WITH (FORCE)')


@pytest.fixture
def shards() -> Iterator[Shards]:
    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    s = Shards()
    try:
        yield s
    finally:
        s.drop()


@pytest.fixture
def sharded(shards: Shards) -> Iterator[ShardedStore]:
    st = open_store(shards.spec())
    assert isinstance(st, ShardedStore)
    for w in A_WIRES + B_WIRES:
        st.add_machine(f"crane-{w}", w, SECRET)
    try:
        yield st
    finally:
        st.close()


def _direct(url: str) -> Store:
    return Store.open(url)


# --- the map (no database) ----------------------------------------------------------------------
@pytest.mark.timeout(10)
def test_shard_map_covers_every_partition_once_and_hides_passwords() -> None:
    m = ShardMap.parse({"0-1": "postgresql://u:pw1@a/x", "2": "postgresql://u:pw2@b/x",
                        "3": "postgresql://u:pw1@a/x"}, 4)
    assert m.urls == ("postgresql://u:pw1@a/x", "postgresql://u:pw2@b/x")
    assert m.owner == (0, 0, 1, 0)
    assert [m.shard_of(f"m{i}") for i in range(50)] == \
        [m.owner[partition_of(f"m{i}", 4)] for i in range(50)]
    text = " ".join(m.describe())
    assert "pw1" not in text and "pw2" not in text and "0-1,3" in text
    with pytest.raises(ShardMapError, match="two ranges"):
        ShardMap.parse({"0-2": "sqlite://", "2-3": "sqlite://"}, 4)
    with pytest.raises(ShardMapError, match="3 of 0..3 have no shard"):
        ShardMap.parse({"0-2": "postgresql://u:secret@a/x"}, 4)
    with pytest.raises(ShardMapError, match="partitions are 0..3") as e:
        ShardMap.parse({"0-7": "postgresql://u:secret@a/x"}, 4)
    assert "secret" not in str(e.value)
    spec = StoreSpec.of("sqlite://", {"0-1": "postgresql://u:secret@a/x", "2-3": "sqlite://"}, 4)
    assert StoreSpec.from_json(json.loads(json.dumps(spec.to_json()))) == spec
    assert "secret" not in spec.display()


@pytest.mark.timeout(10)
def test_settings_read_the_shard_map_from_the_environment(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    monkeypatch.setenv("CRANETWIN_STORAGE_SHARDS", json.dumps({"0-7": "sqlite:///a.db",
                                                               "8-15": "sqlite:///b.db"}))
    spec = store_spec(Settings())
    m = spec.shard_map()
    assert m is not None and m.partitions == 16 and m.urls == ("sqlite:///a.db", "sqlite:///b.db")
    monkeypatch.setenv("CRANETWIN_STORAGE_SHARD_PARTITIONS", "8")
    with pytest.raises(ShardMapError):
        store_spec(Settings())


# --- routing and merging ------------------------------------------------------------------------
@pytest.mark.postgres
@pytest.mark.timeout(120)
def test_writes_land_on_their_shard_only_and_reads_and_lists_merge(
        shards: Shards, sharded: ShardedStore) -> None:
    assert A_WIRES and B_WIRES
    blocks = [block(f"crane-{w}", s) for w in A_WIRES + B_WIRES for s in range(3)]
    res = sharded.write_batch(blocks)
    assert [o.status for o in res.outcomes] == ["stored"] * len(blocks)
    a, b = _direct(shards.urls[0]), _direct(shards.urls[1])
    try:
        for st, wires, other in ((a, A_WIRES, B_WIRES), (b, B_WIRES, A_WIRES)):
            assert sorted(m.machine_id for m in st.machines()) == \
                sorted(f"crane-{w}" for w in wires)
            assert set(stored_keys(st, [f"crane-{w}" for w in wires + other])) == \
                {(f"crane-{w}", 7, s) for w in wires for s in range(3)}
            assert st.stats().blocks == 3 * len(wires)
    finally:
        a.close()
        b.close()
    # fleet-wide reads merge every shard; per-machine reads go to the machine's shard
    ids = sorted(f"crane-{w}" for w in A_WIRES + B_WIRES)
    assert [m.machine_id for m in sharded.machines()] == ids
    assert set(sharded.machine_keys()) == set(A_WIRES + B_WIRES)
    assert sharded.stats().blocks == len(blocks)
    for bl in blocks:
        got = sharded.read_samples(bl.machine_id, bl.t0_ns / 1e9 - 1e-6, bl.t_end_ns / 1e9 + 1e-3)
        assert np.array_equal(got.values, bl.values)
    assert sharded.get_machine(f"crane-{B_WIRES[0]}").wire_id == B_WIRES[0]
    # a wire id is unique across shards
    with pytest.raises(StorageError, match="already"):
        sharded.add_machine(f"crane-new-{uuid.uuid4().hex[:4]}", B_WIRES[0], SECRET)
    # the retransmission of every block is stored once: all duplicates, nothing added
    again = sharded.write_batch(blocks)
    assert [o.status for o in again.outcomes] == ["duplicate"] * len(blocks)
    assert sharded.stats().blocks == len(blocks)
    assert sharded.rollup() >= 0


@pytest.mark.postgres
@pytest.mark.timeout(120)
def test_one_shard_down_holds_back_only_its_machines(shards: Shards,
                                                     sharded: ShardedStore) -> None:
    ma, mb = f"crane-{A_WIRES[0]}", f"crane-{B_WIRES[0]}"
    shards.down(1)
    try:
        res = sharded.write_batch([block(ma, 0), block(mb, 0), block(ma, 1)])
        assert [o.status for o in res.outcomes] == ["stored", "unavailable", "stored"]
        assert res.outcomes[1].reason == "shard_unavailable" and not res.outcomes[1].durable
        assert res.refused == [] and len(res.unavailable) == 1
        # the paused shard is skipped without a new connection attempt; A goes on
        res = sharded.write_batch([block(mb, 1), block(ma, 2)])
        assert [o.status for o in res.outcomes] == ["unavailable", "stored"]
        # the keys of the down shard's machines stay known (last read)
        assert set(sharded.machine_keys()) == set(A_WIRES + B_WIRES)
    finally:
        shards.up(1)
    deadline = time.monotonic() + 20
    while True:  # back after the pause
        res = sharded.write_batch([block(mb, 0), block(mb, 1)])
        if res.outcomes[0].status != "unavailable" or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert [o.status for o in res.outcomes] == ["stored", "stored"]
    assert sharded.stats(mb).blocks == 2 and sharded.stats(ma).blocks == 3


@pytest.mark.postgres
@pytest.mark.timeout(180)
def test_daemon_round_trip_stores_on_the_right_shard_and_acks_none_of_a_down_shard(
        shards: Shards, sharded: ShardedStore) -> None:
    """Through the UDP ingest path: with shard b down, crane A's samples are stored and
    acknowledged, crane B's are neither acknowledged nor refused; once b is back the sender's
    retransmissions store them, each sample once, on b only."""
    from test_ingest_daemon import LAYOUT

    wa, wb = A_WIRES[0], B_WIRES[0]
    vals = {w: grid_values(600, w) for w in (wa, wb)}
    # the daemon's checks use the patu655 layout: register the senders' machines that way
    sa, sb = make_sender(wa, vals[wa]), make_sender(wb, vals[wb])
    assert sa.key.layout == LAYOUT
    shards.down(1)
    try:
        with running_daemon(sharded) as d:
            assert drive([sa, sb], d.address, 60, until=lambda: sa.idle), "A not acked"
            drive([sb], d.address, 1.5)  # a few retransmissions of B meet the down shard
            assert not sb.idle and sb.refused == 0
            snap = d.snapshot()
            assert snap["dropped"].get("shard_unavailable", 0) > 0
            shards.up(1)
            assert drive([sb], d.address, 60), "B not acked after its shard came back"
    finally:
        shards.up(1)
    for w, url, other in ((wa, shards.urls[0], shards.urls[1]),
                          (wb, shards.urls[1], shards.urls[0])):
        got = sharded.read_samples(f"crane-{w}", 0, 4e9)
        assert np.array_equal(got.values, vals[w])
        with _direct(url) as own, _direct(other) as foreign:
            assert own.stats(f"crane-{w}").samples == 600
            assert all(k[0] != f"crane-{w}" for k in stored_keys(foreign, [f"crane-{w}"]))


# --- the storage writer on the shards, and its /metrics ------------------------------------------
def _scrape(url: str) -> dict[str, float]:
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.rpartition(" ")
            out[name] = float(value)
    return out


@pytest.mark.postgres
@pytest.mark.timeout(180)
def test_store_writer_stores_on_the_shards_and_serves_metrics(shards: Shards, tmp_path: Path
                                                              ) -> None:
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    from cranetwin.bus.sink import JetStreamStore, ShardedJetStreamStore

    cfg = fresh_bus(partitions=P, ack_wait_s=2.0)
    sink = JetStreamStore.open_bus(shards.spec(), cfg)
    assert isinstance(sink, ShardedJetStreamStore)
    proc: subprocess.Popen[str] | None = None
    try:
        for w in A_WIRES + B_WIRES:
            sink.add_machine(f"crane-{w}", w, SECRET)
        sent = [block(f"crane-{w}", s) for w in A_WIRES + B_WIRES for s in range(4)]
        assert all(o.status == "stored" for o in sink.write_batch(sent).outcomes)
        env = {**os.environ, "CRANETWIN_STORAGE_SHARDS": json.dumps(shards.map),
               "CRANETWIN_STORAGE_SHARD_PARTITIONS": str(P), "CRANETWIN_BUS_URL": cfg.url,
               "CRANETWIN_BUS_STREAM": cfg.stream, "CRANETWIN_BUS_PREFIX": cfg.prefix,
               "CRANETWIN_BUS_PARTITIONS": str(P), "CRANETWIN_BUS_ACK_WAIT_S": "2"}
        proc = subprocess.Popen([sys.executable, "-c", "from cranetwin.cli import main; main()",
                                 "store-writer",
                                 "--metrics-bind", "127.0.0.1:0", "--log-level", "WARNING"],
                                stdout=subprocess.PIPE, text=True, env=env)
        assert proc.stdout is not None
        ready = json.loads(proc.stdout.readline())
        assert ready["event"] == "ready" and ready["metrics"].startswith("http://127.0.0.1:")
        assert "h_shards_a_" in ready["store"] and "h_shards_b_" in ready["store"]
        ids = [f"crane-{w}" for w in A_WIRES + B_WIRES]
        deadline = time.monotonic() + 60
        while sink.stats().blocks < len(sent) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert sink.stats().blocks == len(sent)
        for url, wires in ((shards.urls[0], A_WIRES), (shards.urls[1], B_WIRES)):
            with _direct(url) as st:
                assert {k[0] for k in stored_keys(st, ids)} == {f"crane-{w}" for w in wires}
        m: dict[str, Any] = {}
        while time.monotonic() < deadline:  # the lag is read every few seconds
            m = _scrape(ready["metrics"])
            lag = [m.get(f'cranetwin_store_writer_lag_messages{{partition="{p}"}}') for p in
                   range(P)]
            if all(x == 0 for x in lag):
                break
            time.sleep(0.5)
        per = {p: sum(1 for b in sent if partition_of(b.machine_id, P) == p) for p in range(P)}
        for p, n in per.items():
            key = f'{{partition="{p}"}}'
            assert m.get(f"cranetwin_store_writer_consumed_total{key}", 0) == n
            assert m.get(f"cranetwin_store_writer_committed_total{key}", 0) == n
            assert m.get(f"cranetwin_store_writer_lag_messages{key}") == 0
        assert m["cranetwin_store_writer_stored_samples_total"] == sum(b.n for b in sent)
        assert not any(k.startswith("cranetwin_store_writer_redelivered_total") and v
                       for k, v in m.items())
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(30)
        sink.close()
        delete_stream(cfg)


@pytest.mark.postgres
@pytest.mark.timeout(180)
def test_store_writer_naks_a_down_shards_blocks_and_stores_them_once_it_is_back(
        shards: Shards, sharded: ShardedStore) -> None:
    """Shard b down: the writer stores a's blocks and acks them; b's are negatively acked and
    delivered again (counted as redelivered), then stored once b is back."""
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    import asyncio
    import threading

    from cranetwin.bus.consumer import StoreWriter, WriterConfig
    from cranetwin.bus.sink import JetStreamStore

    cfg = fresh_bus(partitions=P, ack_wait_s=2.0)
    sink = JetStreamStore.open_bus(shards.spec(), cfg)
    ids = [f"crane-{w}" for w in A_WIRES + B_WIRES]
    sent = [block(m, s) for m in ids for s in range(3)]
    writer = StoreWriter(sharded, cfg, range(P), None,
                         WriterConfig(batch_max=50, fetch_wait_s=0.2, nak_delay_s=0.3,
                                      lag_interval_s=0.5))
    done: list[Any] = []

    def run() -> None:
        done.append(asyncio.run(writer.run()))

    shards.down(1)
    t = threading.Thread(target=run)
    try:
        assert all(o.status == "stored" for o in sink.write_batch(sent).outcomes)
        t.start()
        a_ids = [f"crane-{w}" for w in A_WIRES]
        deadline = time.monotonic() + 60
        while writer.counters.redelivered < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        with _direct(shards.urls[0]) as a:
            assert len(stored_keys(a, ids)) == 3 * len(A_WIRES)
            assert {k[0] for k in stored_keys(a, ids)} == set(a_ids)
        assert writer.counters.unavailable >= 3 * len(B_WIRES)
        assert writer.counters.redelivered >= 2
        shards.up(1)

        def stored() -> int:
            try:
                return sharded.stats().blocks
            except StorageUnavailableError:  # still pausing after the outage
                return -1

        while stored() < len(sent) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert stored() == len(sent)
        text = writer.metrics.render().decode()
        assert "cranetwin_store_writer_unavailable_total" in text
    finally:
        shards.up(1)
        if t.is_alive():
            loop_stop = writer.stop
            # stop() sets an asyncio.Event; from another thread it is observed at the next wake
            loop_stop()
            t.join(30)
        sink.close()
        delete_stream(cfg)
    assert done and done[0]["stored_blocks"] == len(sent) and done[0]["duplicates"] == 0


@pytest.mark.timeout(60)
def test_db_upgrade_migrates_every_shard_and_hides_passwords(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    import sqlite3

    from typer.testing import CliRunner

    from cranetwin.cli import app

    a, b = tmp_path / "a.db", tmp_path / "b.db"
    monkeypatch.setenv("CRANETWIN_STORAGE_SHARDS", json.dumps(
        {"0-9": f"sqlite:///{a}", "10-15": f"sqlite:///{b}"}))
    got = CliRunner().invoke(app, ["db", "upgrade"])
    assert got.exit_code == 0, got.output
    assert got.output.count("at the newest revision") == 2
    for f in (a, b):
        with sqlite3.connect(f) as c:
            tables = {r[0] for r in c.execute("SELECT name FROM sqlite_master")}
        assert {"machines", "sample_blocks", "alembic_version"} <= tables
    # a shard that cannot be migrated fails the command, with its password hidden
    monkeypatch.setenv("CRANETWIN_STORAGE_SHARDS", json.dumps(
        {"0-9": f"sqlite:///{a}",
         "10-15": "postgresql+psycopg://u:hunter2@127.0.0.1:1/x?connect_timeout=1"}))
    got = CliRunner().invoke(app, ["db", "upgrade"])
    assert got.exit_code != 0
    assert "hunter2" not in got.output and "***" in got.output


@pytest.mark.postgres
@pytest.mark.timeout(120)
def test_alarms_are_listed_from_every_shard_and_acted_on_in_their_own(
        sharded: ShardedStore) -> None:
    """Event ids are per database: the alarm list merges both shards newest first with ids that
    name their shard, an acknowledgement goes to that shard, new events of both are notified."""
    from cranetwin.service.alarms import AlarmService
    from cranetwin.service.backend import Backend
    from cranetwin.storage import Event

    ma, mb = f"crane-{A_WIRES[0]}", f"crane-{B_WIRES[0]}"
    backend = Backend(sharded)
    svc = AlarmService(backend, offline_s=60.0, gap_s=10.0)
    offered: list[dict[str, Any]] = []

    class Notifier:  # the outbox's interface: named cursors, queued with them
        def __init__(self) -> None:
            self.cursors: dict[str, int] = {}

        def cursor(self, name: str = "events") -> int | None:
            return self.cursors.get(name)

        def offer_many(self, alarms: list[dict[str, Any]], cursor: int | None = None,
                       cursors: dict[str, int] | None = None) -> None:
            offered.extend(alarms)
            for name, value in (cursors or {}).items():
                self.cursors[name] = max(value, self.cursors.get(name, 0))

    svc.set_notifier(Notifier(), "warning")
    evs = [Event(ma, 100.0, "overload", "critical", {}), Event(mb, 200.0, "overload",
                                                              "critical", {}),
           Event(mb, 300.0, "data_gap", "info", {}), Event(ma, 400.0, "machine_offline",
                                                           "warning", {})]
    assert sharded.add_events(evs) == 4
    page = svc.list(state="all", limit=10)
    assert page["total"] == 4 and page["kinds"] == ["data_gap", "machine_offline", "overload"]
    assert [(a["machine_id"], a["t"]) for a in page["items"]] == \
        [(ma, 400.0), (mb, 300.0), (mb, 200.0), (ma, 100.0)]
    ids = [a["id"] for a in page["items"]]
    assert len(set(ids)) == 4  # the two shards' row ids collide; these do not
    two = svc.list(state="all", limit=2, offset=1)
    assert [a["id"] for a in two["items"]] == ids[1:3] and two["total"] == 4
    b_alarm = page["items"][2]
    done = svc.act(b_alarm["id"], "clear", "tester")
    assert done["id"] == b_alarm["id"] and done["machine_id"] == mb
    assert done["cleared"]["by"] == "tester"
    active = svc.list(state="active", limit=10)
    assert b_alarm["id"] not in [a["id"] for a in active["items"]] and active["total"] == 3
    assert svc.list(machine_ids=[ma], state="all")["total"] == 2
    # the webhook is offered the new warnings and criticals of both shards, once
    assert svc.notify_new() == 3 and svc.notify_new() == 0
    assert sorted((a["machine_id"], a["t"]) for a in offered) == \
        sorted([(ma, 100.0), (ma, 400.0), (mb, 200.0)])


@pytest.mark.timeout(10)
def test_delivery_count_read_from_the_ack_subject_as_nats_py_reads_it() -> None:
    from nats.aio.msg import Msg

    from cranetwin.bus.consumer import _delivered

    for reply in ("$JS.ACK.S.c.3.5.5.1700000000000000000.0",
                  "$JS.ACK.dom.acc.S.c.4.5.5.1700000000000000000.0.tok",
                  "$JS.ACK.S.c.1.9.9.1700000000000000000.2"):
        assert _delivered(reply) == Msg(None, subject="x", reply=reply).metadata.num_delivered
    assert _delivered(None) == _delivered("_INBOX.abc") == 1


def test_late_data_version_is_raised_on_the_machines_shard_only(sharded: ShardedStore) -> None:
    """The replay cache's late-data version (storage.late_version) through the sharded store:
    read with the machine from its shard, raised by a block stored behind its newest one in
    a batch split by shard, not by blocks in time order, not for the other shard's machine."""
    ma, mb = f"crane-{A_WIRES[0]}", f"crane-{B_WIRES[0]}"
    assert len(sharded.write_batch([block(ma, 0), block(mb, 0), block(ma, 2),
                                    block(mb, 1)]).new) == 4
    before = {m: sharded.get_machine(m).late_version for m in (ma, mb)}
    assert before == {ma: 1, mb: 1}  # their rows made by the first write
    assert len(sharded.write_batch([block(mb, 2), block(ma, 3)]).new) == 2  # time order
    assert {m: sharded.get_machine(m).late_version for m in (ma, mb)} == before
    assert len(sharded.write_batch([block(ma, 1), block(mb, 3)]).new) == 2  # ma's 1: late
    assert {m: sharded.get_machine(m).late_version for m in (ma, mb)} == {ma: 2, mb: 1}
