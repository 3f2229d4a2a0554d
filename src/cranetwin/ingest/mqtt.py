"""The MQTT ingest adapter: Sparkplug B ``DDATA`` from a broker into storage, acked after commit.

``cranetwin mqtt-ingest`` runs one :class:`MqttIngest` (docs/INGEST.md, "MQTT / Sparkplug B"):
the paho network thread queues each delivered message; the adapter thread takes batches,
learns metric aliases from ``DBIRTH``, decodes and checks each ``DDATA`` against the machine
description (:mod:`~cranetwin.ingest.sparkplug`; an unknown alias is held unacked and a rebirth
asked for), writes the blocks with :class:`~cranetwin.ingest.writer.StorageWriter`
(``Store.write_batch``, idempotent on (machine, epoch, seq), retried while the database is
unavailable) and only after the commit sends the PUBACK of every message of the batch.

The subscription is QoS 1 in a persistent session with manual acks: the broker keeps what is
not acked and sends it again after a reconnect, so a crash before a commit means redelivery,
which storage turns into a ``duplicate``. An ack only goes over the connection that delivered
the message (packet ids of a former connection may name other messages by now).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from cranetwin.errors import MissingExtraError, StorageUnavailableError
from cranetwin.ingest.config import DaemonConfig, layout_of
from cranetwin.ingest.metrics import Metrics
from cranetwin.ingest.sparkplug import (
    DData,
    SparkplugError,
    Topic,
    birth_aliases,
    encode_rebirth,
    limits_problems,
    on_grid,
    parse_ddata,
    parse_topic,
    pb,
)
from cranetwin.ingest.writer import Abandoned, StorageWriter
from cranetwin.protocol import Layout, Limits
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store
from cranetwin.storage.live import LiveBus

log = logging.getLogger(__name__)


def paho() -> Any:
    """``paho.mqtt.client``, or MissingExtraError naming the ``mqtt`` extra."""
    try:
        import paho.mqtt.client as client
    except ImportError as exc:
        raise MissingExtraError("mqtt", "the MQTT ingest adapter") from exc
    return client


@dataclass(frozen=True)
class MqttConfig:
    """Settings of one adapter.

    Attributes:
        host, port: The broker (Mosquitto, or NATS's MQTT listener).
        group: Sparkplug group id whose ``DDATA``/``DBIRTH`` are consumed.
        client_id: MQTT client id: the name of the persistent session (one adapter per id).
        username, password: Broker credentials (``password`` never logged nor in ``repr``).
        tls: Connect with TLS (``mqtts://``).
        protocol: ``"5"`` (MQTT 5: session expiry, Receive Maximum) or ``"3.1.1"`` (a
            persistent ``clean_session=False`` session; for NATS's MQTT listener, which speaks
            3.1.1 only; the broker's own settings bound the unacked messages then).
        session_expiry_s: How long the broker keeps the session, and with it every message
            not yet acked, while the adapter is away [s].
        receive_maximum: Unacked messages the broker may send at once (MQTT 5 Receive
            Maximum); bounds what the adapter holds.
        batch_max, batch_wait_s: Messages per transaction at most; time a batch is gathered [s].
        keepalive_s: MQTT keep-alive [s].
        rebirth_interval_s: Least time between two rebirth requests to one edge node [s].
        limits: Edge validation as the UDP daemon's (time window, range margin).
        writer: Retry backoff and rollup period of the database writer.
    """

    host: str = "127.0.0.1"
    port: int = 1883
    group: str = "cranetwin"
    client_id: str = "cranetwin-mqtt-ingest"
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    tls: bool = False
    protocol: str = "5"
    session_expiry_s: int = 7 * 86400
    receive_maximum: int = 1000
    batch_max: int = 1000
    batch_wait_s: float = 0.05
    keepalive_s: int = 30
    rebirth_interval_s: float = 5.0
    limits: Limits = field(default_factory=Limits)
    writer: DaemonConfig = field(default_factory=DaemonConfig)


class Msg(NamedTuple):
    """One delivered message, with the connection (generation) that delivered it."""

    topic: str
    payload: bytes
    mid: int
    qos: int
    conn: int


class MqttIngest:
    """Consumes Sparkplug B blocks from a broker into ``store`` (see the module docstring).

    Args:
        store: The database (migrated; machines registered with ``cranetwin machines add``).
        config: Broker, session, batching, limits.
        live: Live fan-out of newly stored blocks (after commit), or None.
    """

    def __init__(self, store: Store, config: MqttConfig, live: LiveBus | None = None) -> None:
        self.store = store
        self.config = config
        self.live = live
        self.metrics = Metrics()
        self.ready = threading.Event()
        self._stop = threading.Event()
        self._logged: set[str] = set()
        self._db = StorageWriter(store, config.writer, self.metrics, self._log_once)
        self._queue: queue.Queue[Msg] = queue.Queue()
        self._conn = 0  # generation of the current connection (0: none yet)
        self._in_hand: set[tuple[int, int]] = set()  # (connection, mid) delivered, not acked
        self._aliases: dict[tuple[str, str], dict[int, str]] = {}
        self._held: dict[tuple[str, str], list[Msg]] = {}
        self._rebirth_asked: dict[str, float] = {}
        self._layouts: dict[str, Layout] = {}
        self._models: dict[str, str] = {}
        self._models_loaded = 0.0
        self._started = time.monotonic()
        self._mqtt = paho()
        pb()  # fail at start, not on the first message, without the extra
        self._client: Any = None

    # -- bookkeeping ----------------------------------------------------------------------------
    def _log_once(self, kind: str, exc: BaseException | None, msg: str, *args: Any) -> None:
        if kind not in self._logged:
            self._logged.add(kind)
            log.error(msg + " (logged once; see the counters for repeats)", *args)

    def snapshot(self) -> dict[str, Any]:
        """The counters (:class:`~cranetwin.ingest.metrics.Metrics`; ``received`` = messages,
        ``accepted`` = blocks decoded and valid, ``acks_sent`` = PUBACKs, ``dropped`` = refused
        messages by reason) and the messages held for a rebirth."""
        d = self.metrics.snapshot(self._queue.qsize(), self.config.receive_maximum,
                                  self._started)
        d["held"] = sum(len(v) for v in self._held.values())
        return d

    def stop(self) -> None:
        """Ask :meth:`run` to finish the batch in hand, disconnect and return (any thread)."""
        self._stop.set()
        self._db.abandon.set()

    # -- paho callbacks (network thread) --------------------------------------------------------
    def _on_connect(self, client: Any, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if reason.is_failure:
            self._log_once(f"connect:{reason}", None, "broker refused the connection: %s",
                           reason)
            return
        self._conn += 1
        g = self.config.group
        client.subscribe([(f"spBv1.0/{g}/DBIRTH/+/+", 1), (f"spBv1.0/{g}/DDATA/+/+", 1)])
        log.info("connected to %s:%d (session %s, present: %s), subscribed to group %s",
                 self.config.host, self.config.port, self.config.client_id,
                 getattr(_f, "session_present", "?"), g)

    def _on_subscribe(self, _c: Any, _u: Any, _mid: int, codes: Any, _p: Any) -> None:
        bad = [c for c in codes if c.is_failure]
        if bad:
            self._log_once("subscribe", None, "subscription refused by the broker: %s", bad)
        else:
            self.ready.set()

    def _on_message(self, _c: Any, _u: Any, m: Any) -> None:
        key = (self._conn, m.mid)
        if m.qos and key in self._in_hand:  # sent again before we acked it (NATS's ack_wait)
            self.metrics.drop("redelivered_in_hand")
            return
        if m.qos:
            self._in_hand.add(key)
        self._queue.put(Msg(m.topic, m.payload, m.mid, m.qos, self._conn))

    # -- machines -------------------------------------------------------------------------------
    def _layout(self, machine_id: str) -> Layout | None:
        """The registered machine's channel layout; None if not registered (the registry is
        read again, at most every 2 s, when an unknown machine appears)."""
        model = self._models.get(machine_id)
        if model is None and time.monotonic() - self._models_loaded > 2.0:
            self._models = self._db.retry("machines", lambda: {
                m.machine_id: m.model for m in self.store.machines()})
            self._models_loaded = time.monotonic()
            model = self._models.get(machine_id)
        if model is None:
            return None
        layout = self._layouts.get(model)
        if layout is None:
            layout = self._layouts[model] = layout_of(model)
        return layout

    # -- one batch ------------------------------------------------------------------------------
    def _parse(self, msg: Msg, topic: Topic) -> tuple[DData, Layout]:
        """The identity and values of a DDATA message and its machine's layout.

        Raises:
            SparkplugError: refused (or ``unknown_alias``: to be held).
        """
        try:
            layout = self._layout(topic.device)
        except Exception as exc:  # a model that does not load: as the daemon's bad_model
            raise SparkplugError("bad_model", f"machine {topic.device!r}: {exc}") from exc
        if layout is None:
            raise SparkplugError("unknown_machine", f"no machine {topic.device!r} registered")
        return parse_ddata(msg.payload, topic.device, layout,
                           self._aliases.get((topic.edge_node, topic.device))), layout

    def _refuse(self, msg: Msg, exc: SparkplugError) -> None:
        self.metrics.drop(exc.reason)
        self._log_once(f"refused:{exc.reason}", exc, "message on %s refused (%s): %s",
                       msg.topic, exc.reason, exc)

    def _blocks(self, msgs: list[Msg]) -> tuple[list[tuple[Msg, SampleBlock]], list[Msg]]:
        """The valid blocks of a batch with their messages, and the messages to ack whatever
        the write does (DBIRTHs, refused). Births and parsing first, in arrival order; then
        the values of each layout's blocks are put on the grid and checked in one pass."""
        m = self.metrics
        todo: deque[Msg] = deque(msgs)
        parsed: dict[Layout, list[tuple[Msg, DData]]] = {}
        done: list[Msg] = []
        while todo:
            msg = todo.popleft()
            m.add("received")
            m.add("received_bytes", len(msg.payload))
            try:
                topic = parse_topic(msg.topic)
                if topic.kind == "DBIRTH":
                    key = (topic.edge_node, topic.device)
                    self._aliases[key] = birth_aliases(msg.payload)
                    todo.extend(self._held.pop(key, []))
                    done.append(msg)
                    continue
                d, layout = self._parse(msg, topic)
                parsed.setdefault(layout, []).append((msg, d))
            except SparkplugError as exc:
                if exc.reason == "unknown_alias" and self._hold(msg, topic):
                    continue
                self._refuse(msg, exc)
                done.append(msg)
        good: list[tuple[Msg, SampleBlock]] = []
        now = time.time_ns()
        for layout, items in parsed.items():
            gridded: list[tuple[Msg, SampleBlock]] = []
            for (msg, _), b in zip(items, on_grid([d for _, d in items], layout), strict=True):
                if isinstance(b, SparkplugError):
                    self._refuse(msg, b)
                    done.append(msg)
                else:
                    gridded.append((msg, b))
            problems = limits_problems([b for _, b in gridded], layout, self.config.limits, now)
            for (msg, b), problem in zip(gridded, problems, strict=True):
                if problem is None:
                    good.append((msg, b))
                    m.add("accepted")
                else:
                    self._refuse(msg, problem)
                    done.append(msg)
        return good, done

    def _hold(self, msg: Msg, topic: Topic) -> bool:
        """Keep ``msg`` unacked until its device's DBIRTH arrives; ask the edge node for one.
        False when too many are held already (then it is refused)."""
        if sum(len(v) for v in self._held.values()) >= self.config.receive_maximum // 2:
            return False
        self._held.setdefault((topic.edge_node, topic.device), []).append(msg)
        now = time.monotonic()
        if now - self._rebirth_asked.get(topic.edge_node, -1e9) >= self.config.rebirth_interval_s:
            self._rebirth_asked[topic.edge_node] = now
            self._client.publish(str(Topic(topic.group, "NCMD", topic.edge_node)),
                                 encode_rebirth(time.time_ns() // 1_000_000), qos=0)
            log.info("asked edge node %s for a rebirth (unknown metric alias)", topic.edge_node)
        return True

    def _handle(self, msgs: list[Msg]) -> None:
        """Decode, write and ack one batch (acks only after the commit)."""
        m = self.metrics
        good, done = self._blocks(msgs)
        blocks = [b for _, b in good]
        outcomes = self._db.write_blocks(blocks)  # raises Abandoned: nothing acked
        new: list[SampleBlock] = []
        for (msg, b), (kind, reason) in zip(good, outcomes, strict=True):
            if kind == "stored":
                new.append(b)
            elif kind == "duplicate":
                m.add("duplicates")
            elif kind == "refused":
                m.drop(reason)
            else:  # not stored for an unexplained reason: not acked, delivered again later
                m.drop(reason)
                continue
            done.append(msg)
        if blocks:
            m.add("batches")
        m.add("stored_blocks", len(new))
        m.add("stored_samples", sum(b.n for b in new))
        self._ack(done)
        if self.live is not None and new:
            try:
                self.live.publish(new)
            except Exception as exc:  # fan-out is best effort; storage is the truth
                m.drop("publish_error")
                self._log_once("publish", exc, "live fan-out failed: %s", exc)

    def _ack(self, msgs: list[Msg]) -> None:
        for msg in msgs:
            if msg.qos == 0:
                continue
            self._in_hand.discard((msg.conn, msg.mid))
            if msg.conn != self._conn:  # its connection is gone: the broker sends it again
                self.metrics.drop("ack_after_reconnect")
                continue
            self._client.ack(msg.mid, msg.qos)
            self.metrics.add("acks_sent")

    def _batch(self) -> list[Msg]:
        try:
            first = self._queue.get(timeout=0.1)
        except queue.Empty:
            return []
        out = [first]
        deadline = time.monotonic() + self.config.batch_wait_s
        while len(out) < self.config.batch_max:
            try:
                out.append(self._queue.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                break
        return out

    # -- lifecycle ------------------------------------------------------------------------------
    def _connect(self) -> Any:
        mqtt = self._mqtt
        try:
            from paho.mqtt.packettypes import PacketTypes
            from paho.mqtt.properties import Properties
        except ImportError as exc:
            raise MissingExtraError("mqtt", "the MQTT ingest adapter") from exc
        new_properties: Any = Properties  # untyped in paho
        cfg = self.config
        v5 = cfg.protocol != "3.1.1"
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=cfg.client_id,
                        protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
                        clean_session=None if v5 else False, manual_ack=True)
        if cfg.username is not None:
            c.username_pw_set(cfg.username, cfg.password)
        if cfg.tls:
            c.tls_set()
        c.on_connect, c.on_subscribe, c.on_message = (self._on_connect, self._on_subscribe,
                                                      self._on_message)
        c.reconnect_delay_set(0.25, 5)
        try:
            if v5:
                props = new_properties(PacketTypes.CONNECT)
                props.SessionExpiryInterval = cfg.session_expiry_s
                props.ReceiveMaximum = cfg.receive_maximum
                c.connect(cfg.host, cfg.port, cfg.keepalive_s, clean_start=False,
                          properties=props)
            else:
                c.connect(cfg.host, cfg.port, cfg.keepalive_s)
        except OSError as exc:
            raise StorageUnavailableError(
                f"MQTT broker {cfg.host}:{cfg.port} unreachable: {exc}") from exc
        return c

    def run(self) -> dict[str, Any]:
        """Consume until :meth:`stop`; returns the counters.

        Raises:
            StorageUnavailableError: the broker is unreachable at start.
        """
        self._client = self._connect()
        self._client.loop_start()
        try:
            while not self._stop.is_set():
                msgs = self._batch()
                try:
                    if msgs:
                        self._handle(msgs)
                except Abandoned:
                    break
                except Exception as exc:  # a bug must not stop ingest: nothing of it acked
                    self.metrics.add("write_errors")
                    self._log_once("handle", exc, "unexpected error on %d message(s); not "
                                   "acknowledged (delivered again after a reconnect): %s",
                                   len(msgs), exc)
                self._db.maybe_rollup()
        finally:
            self._client.disconnect()  # the session (and every unacked message) stays
            self._client.loop_stop()
            self._db.maybe_rollup(force=True)
        return self.snapshot()
