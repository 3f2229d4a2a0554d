"""Fleet bus on NATS JetStream: block messages, subjects, the daemon's sink (PubAck → outcome),
the storage writer (ack after commit), and the NATS live bus — against the real NATS server
(127.0.0.1:4222, JetStream). Each test uses its own stream and subject prefix and deletes the
stream afterwards."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import uuid
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import SECRET
from cranetwin.bus.blockcodec import BlockCodecError, decode_block, decode_blocks, encode_blocks
from cranetwin.bus.consumer import StoreWriter, WriterConfig
from cranetwin.bus.sink import JetStreamStore
from cranetwin.bus.subjects import (
    BusConfig,
    msg_id_of,
    subject_of,
    subject_token,
)
from cranetwin.errors import StorageUnavailableError
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store
from cranetwin.storage.nats_loop import run_bounded
from cranetwin.storage.sharding import partition_of

pytestmark = pytest.mark.timeout(120)
NATS_URL = "nats://127.0.0.1:4222"
CHANNELS = ("p_a", "p_b", "s")
RES = (1000.0, 1000.0, 1e-4)


def nats_unreachable_reason(url: str = NATS_URL) -> str | None:
    """None if a NATS server with JetStream answers at ``url``, else why not."""
    try:
        import nats
    except ImportError:
        return "nats-py is not installed (cranetwin[nats])"

    async def probe() -> None:
        nc = await nats.connect(url, connect_timeout=2, allow_reconnect=False)
        try:
            await nc.jetstream().account_info()
        finally:
            await nc.close()

    try:
        asyncio.run(probe())
    except Exception as exc:
        return f"no NATS server with JetStream at {url}: {exc}"
    return None


def fresh_bus(url: str = NATS_URL, **kw: Any) -> BusConfig:
    tag = uuid.uuid4().hex[:10]
    return BusConfig(url=url, stream=f"T_{tag}", prefix=f"t{tag}.blocks", **kw)


def delete_stream(cfg: BusConfig) -> None:
    import nats

    async def run() -> None:
        nc = await nats.connect(cfg.url, connect_timeout=2, allow_reconnect=False)
        try:
            await nc.jetstream().delete_stream(cfg.stream)
        except nats.js.errors.NotFoundError:
            pass
        finally:
            await nc.close()

    asyncio.run(run())


@pytest.fixture
def bus() -> Iterator[BusConfig]:
    """A fresh stream name and subject prefix on the local server (stream deleted after)."""
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    cfg = fresh_bus(partitions=4, ack_wait_s=1.0)
    yield cfg
    delete_stream(cfg)


def block(machine: str, seq: int, n: int = 20, seed: int = 0, *, epoch: int = 7,
          t0_ns: int | None = None, nan: bool = False) -> SampleBlock:
    rng = np.random.default_rng(seed + seq)
    k = rng.integers(-5000, 5000, size=(n, len(CHANNELS))).astype(np.int64)
    values = k * np.asarray(RES)
    if nan:
        values[::3, 1] = np.nan
        k[::3, 1] = 0
    t0 = 1_700_000_000_000_000_000 + seq * n * 10_000_000 if t0_ns is None else t0_ns
    return SampleBlock(machine, seq, t0, 10_000_000, CHANNELS, RES, values, epoch=epoch, steps=k)


def same(a: SampleBlock, b: SampleBlock) -> bool:
    return ((a.machine_id, a.epoch, a.seq, a.t0_ns, a.period_ns, a.channels, a.resolution)
            == (b.machine_id, b.epoch, b.seq, b.t0_ns, b.period_ns, b.channels, b.resolution)
            and np.array_equal(a.values, b.values, equal_nan=True))


# --- messages and subjects (no server) ----------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(machine=st.text(min_size=1, max_size=40), seq=st.integers(0, 2**63 - 1),
       epoch=st.integers(0, 2**63 - 1), n=st.integers(1, 300), nan=st.booleans(),
       with_steps=st.booleans())
def test_block_message_round_trips_exactly(machine: str, seq: int, epoch: int, n: int,
                                           nan: bool, with_steps: bool) -> None:
    b = block(machine, seq % 1000, n, epoch=epoch, nan=nan)
    b = SampleBlock(b.machine_id, seq, b.t0_ns, b.period_ns, b.channels, b.resolution,
                    b.values, b.epoch, b.steps if with_steps else None)
    (body,) = encode_blocks([b])
    assert isinstance(body, bytes)
    got = decode_block(body)
    assert same(got, b)
    assert got.steps is not None and np.array_equal(got.steps, b.steps if with_steps else
                                                    np.rint(np.nan_to_num(b.values)
                                                            / np.asarray(RES)))


@settings(max_examples=30, deadline=None)
@given(shapes=st.lists(st.tuples(st.integers(1, 40), st.booleans()), min_size=1, max_size=12),
       corrupt=st.integers(0, 20))
def test_messages_decoded_together_equal_each_decoded_alone(
        shapes: list[tuple[int, bool]], corrupt: int) -> None:
    blocks = [block(f"m-{i % 3}", i, n, nan=nan) for i, (n, nan) in enumerate(shapes)]
    bodies = [b for b in encode_blocks(blocks) if isinstance(b, bytes)]
    if corrupt < len(bodies):  # one broken message fails alone
        bodies[corrupt] = bodies[corrupt][:-3]
    got = decode_blocks(bodies)
    for i, (body, g) in enumerate(zip(bodies, got, strict=True)):
        if i == corrupt:
            assert isinstance(g, BlockCodecError)
            continue
        assert isinstance(g, SampleBlock) and same(g, decode_block(body)) and same(g, blocks[i])


def test_block_message_that_is_cut_or_foreign_is_refused() -> None:
    (body,) = encode_blocks([block("crane-1", 1)])
    assert isinstance(body, bytes)
    for bad in (body[:10], body[:-5], b"XX" + body[2:], b"", b"hello world"):
        with pytest.raises(BlockCodecError):
            decode_block(bad)


def test_infinite_values_are_reported_not_encoded() -> None:
    b = block("crane-1", 1)
    v = b.values.copy()
    v[3, 0] = np.inf
    bad = SampleBlock(b.machine_id, 1, b.t0_ns, b.period_ns, b.channels, b.resolution, v, 7)
    out = encode_blocks([bad, block("crane-1", 2)])
    assert isinstance(out[0], str) and isinstance(out[1], bytes)


def test_partition_is_stable_and_subjects_are_single_tokens() -> None:
    cfg = BusConfig(partitions=16)
    # CRC-32 of the UTF-8 id: golden values, so a change of the hash (which would move every
    # machine to another partition) fails here
    assert [partition_of(m, 16) for m in ("crane-1", "crane-2", "bobcat-17")] == [15, 5, 11]
    assert [partition_of(m, 1000) for m in ("crane-1", "crane-2", "bobcat-17")] == [247, 909, 515]
    for m in ("crane.1", "a b", "x*>", "ü-7", "plain_ID-9"):
        tok = subject_token(m)
        assert not set(tok) & set(". *>\t") and tok
        assert subject_of(cfg, m).split(".")[-1] == tok
    assert subject_token("crane.1") != subject_token("crane-1")
    assert msg_id_of("crane-1", 7, 42) == "crane-1/7/42"


# --- the daemon's sink ----------------------------------------------------------------------------
def _store(sqlite_url: str, cfg: BusConfig, machines: int = 3) -> JetStreamStore:
    store = JetStreamStore.open_bus(sqlite_url, cfg)
    for w in range(1, machines + 1):
        store.add_machine(f"crane-{w}", w, SECRET)
    return store


def test_sink_reports_new_blocks_stored_and_retransmissions_duplicate(
        bus: BusConfig, sqlite_url: str) -> None:
    store = _store(sqlite_url, bus)
    try:
        first = [block("crane-1", s) for s in range(5)] + [block("crane-2", 0)]
        r1 = store.write_batch(first)
        assert [o.status for o in r1.outcomes] == ["stored"] * 6
        # a retransmission of two of them, the same datagram twice in a batch, and a new one
        r2 = store.write_batch([first[1], first[2], block("crane-1", 5), block("crane-1", 5)])
        assert [o.status for o in r2.outcomes] == ["duplicate", "duplicate", "stored",
                                                  "duplicate"]
        # nothing went to the database; storage's refusals are checked before publishing
        assert store.stats().blocks == 0
        bad = block("crane-3", 0, t0_ns=-5)
        r3 = store.write_batch([bad, block("crane-3", 1)])
        assert [(o.status, o.reason) for o in r3.outcomes] == [("refused", "unstorable"),
                                                              ("stored", None)]
        assert store.rollup() == 0
    finally:
        store.close()


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_sink_without_a_server_raises_unavailable(sqlite_url: str) -> None:
    cfg = fresh_bus(f"nats://127.0.0.1:{_closed_port()}", publish_timeout_s=0.5)
    store = _store(sqlite_url, cfg, machines=1)
    try:
        with pytest.raises(StorageUnavailableError, match="NATS"):
            store.write_batch([block("crane-1", 0)])
        # status reports and keys still come from the database
        assert set(store.machine_keys()) == {1}
    finally:
        store.close()


# --- the storage writer, in process ---------------------------------------------------------------
class Crash(Exception):
    """Stands for a kill -9 between the database commit and the acks."""


class CrashingStore(Store):
    """Commits like a Store, then dies after ``crash_after`` batches."""

    crash_after: int | None = None
    writes = 0

    def write_batch(self, blocks: Any) -> Any:
        result = super().write_batch(blocks)
        self.writes += 1
        if self.crash_after is not None and self.writes >= self.crash_after:
            raise Crash()
        return result


def run_writer(store: Store, cfg: BusConfig, until: Any, timeout_s: float = 30.0,
               batch_max: int = 50, batch_wait_s: float = 0.05,
               on_ready: Any = None, live: Any = None) -> dict[str, Any] | BaseException:
    """A StoreWriter over every partition (live fan-out ``live``) until ``until()`` holds;
    returns its counters, or the exception it died of. ``on_ready()`` runs in a thread once it
    consumes."""
    writer = StoreWriter(store, cfg, range(cfg.partitions), live,
                         WriterConfig(batch_max=batch_max, batch_wait_s=batch_wait_s,
                                      fetch_wait_s=0.2))
    out: list[Any] = []

    async def main() -> None:
        task = asyncio.create_task(writer.run())
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        if on_ready is not None:
            await asyncio.wait_for(writer.ready.wait(), timeout_s)
            await asyncio.to_thread(on_ready)
        while not task.done() and loop.time() < end and not until():
            await asyncio.sleep(0.05)
        writer.stop()
        try:
            out.append(await task)
        except BaseException as exc:  # the crash under test
            out.append(exc)

    t = threading.Thread(target=lambda: run_bounded(main()))
    t.start()
    t.join(timeout_s + 20)
    assert not t.is_alive()
    return out[0]  # type: ignore[no-any-return]


def stored_keys(store: Store, machines: list[str]) -> list[tuple[str, int, int]]:
    from sqlalchemy import select

    from cranetwin.storage.blocks import BlockRow
    from cranetwin.storage.machines import MachineRow

    with store.engine.connect() as c:
        rows = c.execute(select(MachineRow.machine_id, BlockRow.epoch, BlockRow.seq)
                         .join(MachineRow, MachineRow.id == BlockRow.machine_pk)).all()
    return sorted((str(m), int(e), int(s)) for m, e, s in rows if m in machines)


@settings(max_examples=8, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_acked_blocks_are_stored_exactly_once_through_writer_crashes(
        bus: BusConfig, tmp_path_factory: pytest.TempPathFactory, data: st.DataObject) -> None:
    """Property: whatever the daemon re-publishes (retransmissions, the same batch again) and
    wherever the storage writer dies between commit and ack, every block the bus acknowledged
    (PubAck) ends up stored exactly once, with its samples."""
    cfg = fresh_bus(partitions=3, ack_wait_s=0.5)
    url = f"sqlite:///{tmp_path_factory.mktemp('db') / 'c.db'}"
    machines = ["crane-1", "crane-2", "crane-3"]
    n_blocks = data.draw(st.integers(1, 40), label="blocks")
    owners = data.draw(st.lists(st.sampled_from(machines), min_size=n_blocks,
                                max_size=n_blocks), label="machines")
    per: dict[str, int] = {}
    all_blocks = []
    for m in owners:
        per[m] = per.get(m, 0) + 1
        all_blocks.append(block(m, per[m]))
    batches = data.draw(st.lists(st.lists(st.sampled_from(range(n_blocks)), min_size=1,
                                          max_size=12), min_size=1, max_size=6), label="batches")
    crashes = data.draw(st.lists(st.integers(1, 3), max_size=2), label="crash after")
    sink = _store(url, cfg)
    acked: set[tuple[str, int, int]] = set()
    try:
        for idx in [*batches, list(range(n_blocks))]:
            res = sink.write_batch([all_blocks[i] for i in idx])
            acked.update((b.machine_id, b.epoch, b.seq) for b, o in res if o.durable)
        store = CrashingStore.open(url)
        for k in crashes:  # a writer that dies after k commits, before acking that batch
            store.crash_after, store.writes = k, 0
            got = run_writer(store, cfg, until=lambda: False, timeout_s=10, batch_max=5)
            assert isinstance(got, Crash) or isinstance(got, dict)
        store.crash_after = None
        run_writer(store, cfg, until=lambda: len(stored_keys(store, machines)) >= len(acked),
                   timeout_s=30, batch_max=5)
        keys = stored_keys(store, machines)
        assert len(keys) == len(set(keys)), "a block stored twice"
        assert set(keys) == acked, "an acked block is missing (or an unacked one stored)"
        for b in all_blocks:
            got = store.read_samples(b.machine_id, b.t0_ns / 1e9 - 1e-6, b.t_end_ns / 1e9 + 1e-3)
            assert np.array_equal(got.values, b.values)
        store.close()
    finally:
        sink.close()
        delete_stream(cfg)


# --- live fan-out over core NATS ------------------------------------------------------------------
def test_nats_live_bus_delivers_every_note_to_every_subscriber() -> None:
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    from cranetwin.storage.live import open_bus
    from cranetwin.storage.live_nats import NatsBus

    subject = f"t{uuid.uuid4().hex[:10]}.live"
    pub, sub_bus = NatsBus(NATS_URL, subject), NatsBus(NATS_URL, subject)
    a, b = sub_bus.subscribe(), pub.subscribe()
    try:
        sent = [block("crane-1", s) for s in range(300)]
        pub.publish(sent)
        for sub in (a, b):
            got = []
            while len(got) < 300 and (note := sub.get(timeout=5)) is not None:
                got.append(note)
            assert [(n.machine_id, n.seq, n.t0_ns, n.t_end_ns, n.n) for n in got] == [
                (x.machine_id, x.seq, x.t0_ns, x.t_end_ns, x.n) for x in sent]
        a.close()
        pub.publish(sent[:1])
        assert b.get(timeout=5) is not None and a.get(timeout=0.3) is None
    finally:
        b.close()
        pub.close()
        sub_bus.close()
    assert isinstance(open_bus(NATS_URL), NatsBus)


def test_nats_live_bus_without_a_server_raises_unavailable() -> None:
    pytest.importorskip("nats")
    from cranetwin.storage.live_nats import NatsBus

    bus = NatsBus(f"nats://127.0.0.1:{_closed_port()}")
    try:
        with pytest.raises(StorageUnavailableError):
            bus.publish([block("crane-1", 0)])
        with pytest.raises(StorageUnavailableError):
            bus.subscribe()
    finally:
        bus.close()


def test_writer_commits_blocks_arriving_within_its_batch_wait_together(
        bus: BusConfig, sqlite_url: str) -> None:
    """Blocks published one by one (as a daemon's small batches arrive) share one transaction
    when they reach the writer within ``batch_wait_s`` of the first, and the first is not held
    much longer than that."""
    import time

    sink = _store(sqlite_url, bus)
    machines = ["crane-1", "crane-2", "crane-3"]
    first_acked: list[float] = []

    def publish() -> None:
        for s in range(6):
            assert sink.write_batch([block(machines[s % 3], s)]).outcomes[0].status == "stored"
            if not first_acked:
                first_acked.append(time.monotonic())
            time.sleep(0.05)

    store = Store.open(sqlite_url)
    try:
        counters = run_writer(store, bus, until=lambda: len(stored_keys(store, machines)) >= 6,
                              batch_wait_s=2.5, on_ready=publish)
        done = time.monotonic()
        assert isinstance(counters, dict)
        assert counters["stored_blocks"] == 6 and counters["batches"] == 1, counters
        assert done - first_acked[0] < 2.5 + 3.0  # the wait, the write and the poll
    finally:
        store.close()
        sink.close()


# --- faults the storage writer and the stream absorb ----------------------------------------------
class FlakyStore(Store):
    """The database is unavailable until ``until`` (monotonic time)."""

    until = 0.0
    attempts = 0

    def write_batch(self, blocks: Any) -> Any:
        import time

        self.attempts += 1
        if time.monotonic() < self.until:
            raise StorageUnavailableError("database down (test)")
        return super().write_batch(blocks)


def test_writer_holds_messages_through_a_database_outage_without_redelivery(
        bus: BusConfig, sqlite_url: str) -> None:
    """Database down for 3 × ack_wait: nothing stored or acked meanwhile, the messages are kept
    in progress (not delivered again: no duplicate writes), all stored once afterwards."""
    import time

    sink = _store(sqlite_url, bus)
    sent = [block(f"crane-{1 + s % 3}", s) for s in range(60)]
    try:
        assert all(o.status == "stored" for o in sink.write_batch(sent).outcomes)
    finally:
        sink.close()
    store = FlakyStore.open(sqlite_url)
    store.until = time.monotonic() + 3 * bus.ack_wait_s
    try:
        counters = run_writer(store, bus, until=lambda: len(stored_keys(
            store, ["crane-1", "crane-2", "crane-3"])) >= 60, timeout_s=30)
        assert isinstance(counters, dict)
        assert store.attempts > 2 and counters["write_retries"] > 0  # the outage was hit
        assert counters["stored_blocks"] == 60 and counters["duplicates"] == 0
        keys = stored_keys(store, ["crane-1", "crane-2", "crane-3"])
        assert len(keys) == len(set(keys)) == 60
    finally:
        store.close()


class SlowStore(Store):
    """The first ``write_batch`` takes ``slow_s`` [s] longer (a slow commit)."""

    slow_s = 0.0

    def write_batch(self, blocks: Any) -> Any:
        import time

        delay, self.slow_s = self.slow_s, 0.0
        time.sleep(delay)
        return super().write_batch(blocks)


class SlowLive:
    """A live fan-out whose first ``publish`` takes ``slow_s`` [s] (a stalled live bus)."""

    def __init__(self, slow_s: float) -> None:
        self.slow_s = slow_s
        self.published = 0

    def publish(self, blocks: Any) -> None:
        import time

        delay, self.slow_s = self.slow_s, 0.0
        time.sleep(delay)
        self.published += len(blocks)

    def subscribe(self) -> Any:
        raise NotImplementedError

    def close(self) -> None:
        pass


@pytest.mark.parametrize("slow", ["commit", "fan-out", "setup"])
def test_writer_keeps_messages_in_progress_however_slow_it_is(
        bus: BusConfig, sqlite_url: str, slow: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """One phase of the writer takes 2 × ack_wait: the first commit, the live fan-out of the
    first batch (the later messages wait behind it), or the consumers' set-up at start (one
    partition's messages arrive while the next partitions' consumers are created). Every
    message in hand is kept in progress meanwhile: none is delivered again (no redelivery, no
    duplicate write), every block stored once. Before, the last two redelivered."""
    import time

    import nats.js.manager

    sink = _store(sqlite_url, bus)
    sent = [block(f"crane-{1 + s % 3}", s) for s in range(30)]
    try:
        assert all(o.status == "stored" for o in sink.write_batch(sent).outcomes)
    finally:
        sink.close()
    stall_s = 2 * bus.ack_wait_s
    store = SlowStore.open(sqlite_url)
    live = SlowLive(stall_s if slow == "fan-out" else 0.0)
    if slow == "commit":
        store.slow_s = stall_s
    if slow == "setup":  # the 4 partitions' set-up takes 4 × 0.5 × stall_s in all
        add = nats.js.manager.JetStreamManager.add_consumer

        async def slow_add(self: Any, *a: Any, **k: Any) -> Any:
            await asyncio.sleep(stall_s / 2)
            return await add(self, *a, **k)

        monkeypatch.setattr(nats.js.manager.JetStreamManager, "add_consumer", slow_add)
    done_at: list[float] = []

    def until() -> bool:  # every block stored, then 2 × ack_wait more for any redelivery
        if not done_at and len(stored_keys(store, ["crane-1", "crane-2", "crane-3"])) >= 30:
            done_at.append(time.monotonic())
        return bool(done_at) and time.monotonic() > done_at[0] + 2 * bus.ack_wait_s
    try:
        counters = run_writer(store, bus, until=until, timeout_s=40, batch_max=10, live=live)
        assert isinstance(counters, dict), counters
        assert done_at, counters
        assert (counters["redelivered"], counters["duplicates"]) == (0, 0), counters
        assert counters["messages"] == counters["stored_blocks"] == live.published == 30
        keys = stored_keys(store, ["crane-1", "crane-2", "crane-3"])
        assert len(keys) == len(set(keys)) == 30
    finally:
        store.close()


def test_full_stream_refuses_publishing_until_a_writer_drains_it(sqlite_url: str) -> None:
    """``max_msgs`` reached: the sink raises unavailable (the daemon stops acknowledging)
    instead of the stream dropping anything; once the writer has drained it, publishing
    works again and every block acknowledged is stored. (With ``max_bytes`` instead, nats-server
    2.9.10 dropped old acknowledged messages here: 147 acknowledged, 77 kept.)"""
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    cfg = fresh_bus(partitions=2, max_msgs=60, ack_wait_s=1.0)
    sink = _store(sqlite_url, cfg)
    acked: list[SampleBlock] = []
    try:
        with pytest.raises(StorageUnavailableError, match="maximum messages"):
            for s in range(200):
                b = block(f"crane-{1 + s % 3}", s, n=50)
                sink.write_batch([b])
                acked.append(b)
        assert len(acked) == 60
        store = Store.open(sqlite_url)
        try:
            counters = run_writer(store, cfg, until=lambda: store.stats().blocks >= len(acked))
            assert store.stats().blocks == len(acked), counters
            nxt = block("crane-1", 1000, n=50)
            assert sink.write_batch([nxt]).outcomes[0].status == "stored"
        finally:
            store.close()
    finally:
        sink.close()
        delete_stream(cfg)


def test_writer_stops_in_bounded_time_when_nats_calls_hang(bus: BusConfig,
                                                           sqlite_url: str) -> None:
    """Fault: after the writer is up, every NATS call its shutdown makes (unsubscribe, the lag
    poll, close) hangs and swallows its cancellation, as nats-py's calls can while it
    reconnects. ``stop()`` still ends ``run`` within a few shutdown steps (it hung before)."""
    import time
    import types

    import nats

    from cranetwin.bus.consumer import SHUTDOWN_STEP_S

    stuck = threading.Event()

    async def stubborn(*_a: Any, **_k: Any) -> None:
        while True:  # a call that ignores cancellation
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                continue

    async def connect(*a: Any, **k: Any) -> Any:
        nc = await nats.connect(*a, **k)
        real_sub, real_jsm, real_close = nc.subscribe, nc.jsm, nc.close

        async def subscribe(*sa: Any, **sk: Any) -> Any:
            sub = await real_sub(*sa, **sk)
            real_unsub = sub.unsubscribe

            async def unsubscribe(*ua: Any, **uk: Any) -> Any:
                return await (stubborn() if stuck.is_set() else real_unsub(*ua, **uk))

            sub.unsubscribe = unsubscribe
            return sub

        def jsm(*ja: Any, **jk: Any) -> Any:
            m = real_jsm(*ja, **jk)
            real_info = m.consumer_info

            async def consumer_info(*ca: Any, **ck: Any) -> Any:
                return await (stubborn() if stuck.is_set() else real_info(*ca, **ck))

            m.consumer_info = consumer_info
            return m

        async def close() -> None:
            await stubborn()

        nc.subscribe, nc.jsm, nc.close = subscribe, jsm, close
        nc._cranetwin_real_close = real_close  # closed for real at the end of the test
        return nc

    store = Store.open(sqlite_url)
    writer = StoreWriter(store, bus, range(bus.partitions), None,
                         WriterConfig(fetch_wait_s=0.1, lag_interval_s=0.05))
    writer._nats = types.SimpleNamespace(js=nats.js, connect=connect)
    took: list[float] = []

    async def main() -> None:
        task = asyncio.create_task(writer.run())
        await asyncio.wait_for(writer.ready.wait(), 20)
        await asyncio.sleep(0.3)  # the lag poll runs (for real)
        stuck.set()
        await asyncio.sleep(0.3)  # ... and now hangs
        t0 = time.monotonic()
        writer.stop()
        await task
        took.append(time.monotonic() - t0)
        with contextlib.suppress(Exception):
            await writer._nc._cranetwin_real_close()

    t = threading.Thread(target=lambda: run_bounded(main()), daemon=True)
    t.start()
    t.join(60)
    store.close()
    assert not t.is_alive(), "run() (or the loop's cleanup) did not return after stop()"
    assert took and took[0] < 3 * SHUTDOWN_STEP_S + 2.0
