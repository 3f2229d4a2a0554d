"""The storage writer: durable JetStream consumers of the fleet bus writing into the database.

``cranetwin store-writer`` runs one :class:`StoreWriter`. For each partition it owns it binds
the durable consumer ``store-writer-<p>`` (created if missing: push to
``_cranetwin.deliver.<stream>.<p>`` in the queue group of the same name, explicit acks,
``ack_wait`` from :class:`~cranetwin.bus.subjects.BusConfig`, at most ``batch_max`` messages
unacknowledged, which bounds what a writer holds) and::

    delivered messages ─► batch (≤ batch_max, or what came within batch_wait_s of the oldest)
                          ─► decode ─► Store.write_batch (one transaction)
                                                          │ unavailable → retried with backoff,
                                                          │ messages kept in progress, none acked
                                                          ▼
                                        ack every message of the batch ─► live fan-out (optional)

A message is acked only after the transaction that holds its block has committed (stored, or
found already stored). Until it is answered, every message in hand is kept in progress
(``+WPI`` every ``ack_wait/4`` once it has been held that long), whatever it waits for: the
consumers of the other partitions being set up at start, its batch, a slow commit, a database
outage, the live fan-out of the batch before it. So a live writer's messages are not delivered
again, however slow it is (a redelivery would be written twice, the second time as a
``duplicate``). A writer killed at any point leaves its unacked messages to be delivered
again after ``ack_wait``; storage's (machine, epoch, seq) uniqueness turns the second write into
a ``duplicate``, so every block is stored exactly once. A block storage refuses (``overlap``,
``seq_reused``, …: its machine was already acknowledged by the daemon) is terminated on the bus
(never delivered again), counted by reason in ``refused`` and logged once per reason; a message
that is not a block (:class:`~cranetwin.bus.blockcodec.BlockCodecError`) likewise as
``bad_messages``. A block whose database shard is unavailable while the others are written
(:class:`~cranetwin.storage.shards.ShardedStore`, outcome ``unavailable``) is negatively acked
with a delay (``-NAK``, ``nak_delay_s``): delivered again, never lost, and the other shards'
blocks of the batch go on.

Prometheus metrics (:mod:`cranetwin.bus.metrics`, ``--metrics-bind``): consumed, committed,
redelivered and unavailable per partition, refusals by reason, and each partition's lag (its
messages not acked yet, read from JetStream every ``lag_interval_s``).

One writer per partition at a time: storage's overlap check assumes a single writer per machine
(:mod:`cranetwin.storage.writes`). Two writers bound to one consumer still never lose or double
a block (the queue group gives each message to one of them, and writes are idempotent), they
only lose the overlap check's guarantee.

Why push, not pull: nats-py's ``fetch`` spends about 160 µs of CPU per message (a task and a
timeout per message); a plain subscription on the deliver subject, acked with a plain publish
of ``+ACK`` to the message's reply subject, about 40 µs (measured on this machine).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from cranetwin.bus.blockcodec import BlockCodecError, decode_blocks
from cranetwin.bus.metrics import WriterMetrics
from cranetwin.bus.subjects import (
    BusConfig,
    deliver_subject,
    durable_name,
    ensure_stream,
    partition_filter,
)
from cranetwin.errors import StorageUnavailableError
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, WriteResult, dberrors
from cranetwin.storage.live import LiveBus
from cranetwin.storage.nats_loop import nats_module, redact

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WriterConfig:
    """Settings of one storage writer.

    Attributes:
        batch_max: Messages written per transaction at most; also the most messages each
            partition's consumer leaves unacknowledged with this writer.
        batch_wait_s: How long the oldest message in hand waits for others to share its
            transaction (unless ``batch_max`` are in hand sooner) [s]. A transaction's fixed
            client CPU (≈ 3 ms on PostgreSQL) dwarfs a small block's (≈ 0.1 ms), and the
            daemons' publishes arrive in bursts of a few blocks: without the wait a writer
            committed one transaction per 7 blocks where the direct daemon commits one per 17
            (docs/BUS.md). Delays storage (never a machine's ack) by at most this.
        fetch_wait_s: Longest wait for messages before the loop checks for a stop [s].
        retry_min_s, retry_max_s: First and longest wait between retries of a batch while the
            database is unavailable [s].
        rollup_interval_s: Period of the 1-min summary rollup [s].
        report_interval_s: Period of the counters log line [s].
        lag_interval_s: Period of the partitions' lag reading from JetStream [s]; 0: not read
            (``cranetwin store-writer`` without ``--metrics-bind``: no one could scrape it).
        nak_delay_s: Redelivery delay of a block held back by an unavailable shard [s].
    """

    batch_max: int = 1000
    batch_wait_s: float = 0.25
    fetch_wait_s: float = 1.0
    retry_min_s: float = 0.05
    retry_max_s: float = 5.0
    rollup_interval_s: float = 30.0
    report_interval_s: float = 10.0
    lag_interval_s: float = 5.0
    nak_delay_s: float = 1.0


@dataclass
class WriterCounters:
    """What a storage writer did since it started."""

    messages: int = 0
    batches: int = 0
    stored_blocks: int = 0
    stored_samples: int = 0
    duplicates: int = 0
    bad_messages: int = 0
    write_retries: int = 0
    unavailable: int = 0
    redelivered: int = 0
    refused: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"messages": self.messages, "batches": self.batches,
                "stored_blocks": self.stored_blocks, "stored_samples": self.stored_samples,
                "duplicates": self.duplicates, "bad_messages": self.bad_messages,
                "write_retries": self.write_retries, "unavailable": self.unavailable,
                "redelivered": self.redelivered, "refused": dict(self.refused)}


def _delivered(reply: str | None) -> int:
    """JetStream's delivery count from a message's ack subject: ``$JS.ACK.<stream>.<consumer>.
    <delivered>.…`` (9 tokens) or, with domain and account, ``$JS.ACK.<domain>.<account>.
    <stream>.<consumer>.<delivered>.…`` (12 or more); 1 when it is not one (a split is 4×
    cheaper than nats-py's ``Msg.metadata``)."""
    t = (reply or "").split(".")
    if len(t) < 9 or t[0] != "$JS" or t[1] != "ACK":
        return 1
    k = 4 if len(t) == 9 else 6
    return int(t[k]) if t[k].isdigit() else 1


SHUTDOWN_STEP_S = 3.0
"""Longest wait for each step of the writer's shutdown (unsubscribe, background tasks, close)
[s]: after :meth:`StoreWriter.stop` ``run`` returns within a few of these even when NATS does
not answer (what is not acked is delivered again to the next writer)."""


async def _within(aw: Awaitable[Any], timeout_s: float, what: str) -> None:
    """Await ``aw`` for at most ``timeout_s`` [s]; never raises. Unlike ``asyncio.wait_for`` it
    does not wait for a cancelled call to finish (one that swallows the cancellation would
    hold the caller forever)."""
    task = asyncio.ensure_future(aw)
    done, _ = await asyncio.wait({task}, timeout=timeout_s)
    if not done:
        task.cancel()
        log.warning("store-writer: %s did not finish within %.0f s on shutdown; left behind",
                    what, timeout_s)
    elif not task.cancelled() and task.exception() is not None:
        log.debug("store-writer: %s on shutdown: %s", what, task.exception())


class StoreWriter:
    """Consumes partitions of the fleet bus into ``store`` (see the module docstring).

    Args:
        store: The database (migrated).
        bus: The bus settings (the daemons' too).
        partitions: Partitions this writer owns (each in 0..bus.partitions − 1).
        live: Live fan-out of newly stored blocks (after commit), or None.
        config: Batching, retries, rollup.
    """

    def __init__(self, store: Store, bus: BusConfig, partitions: Sequence[int],
                 live: LiveBus | None = None, config: WriterConfig | None = None) -> None:
        bad = [p for p in partitions if not 0 <= p < bus.partitions]
        if bad or not partitions:
            raise ValueError(f"partitions {bad or '(none)'} outside 0..{bus.partitions - 1}")
        self.store = store
        self.bus = bus
        self.partitions = sorted(set(partitions))
        self.live = live
        self.config = config or WriterConfig()
        self.counters = WriterCounters()
        self.metrics = WriterMetrics()
        self.ready = asyncio.Event()
        self._logged: set[str] = set()
        self._stop = asyncio.Event()
        self._nats = nats_module()
        self._nc: Any = None
        self._pending: list[tuple[int, Any, float]] = []  # (partition, message, arrival [s])
        # every message in hand, pending or in the batch being handled, until it is answered:
        # id(message) → (message, arrival [s]); kept in progress by _heartbeat
        self._held: dict[int, tuple[Any, float]] = {}
        self._arrived = asyncio.Event()  # the first message is in hand
        self._full = asyncio.Event()  # batch_max messages are in hand
        self._closing = False  # the background loops end at their next turn

    def stop(self) -> None:
        """Ask :meth:`run` to finish the batch in hand and return (call on its loop)."""
        self._stop.set()

    def _log_once(self, kind: str, msg: str, *args: Any) -> None:
        if kind not in self._logged:
            self._logged.add(kind)
            log.error(msg + " (logged once; see the counters for repeats)", *args)

    # -- database side (worker thread) ----------------------------------------------------------
    def _write_db(self, blocks: list[SampleBlock]) -> WriteResult | None:
        """``store.write_batch(blocks)``, retried with backoff while the database is
        unavailable; None if stopped meanwhile (nothing acked)."""
        delay = self.config.retry_min_s
        outage_since: float | None = None
        while True:
            try:
                result = self.store.write_batch(blocks)
            except Exception as exc:
                if not dberrors.unavailable_in_chain(exc):
                    raise
                self.counters.write_retries += 1
                self.metrics.write_retries.inc()
                if outage_since is None:
                    outage_since = time.monotonic()
                    log.error("database unavailable: retrying with backoff, nothing acked on "
                              "the bus meanwhile: %s", " ".join(str(exc).split())[:300])
                if self._stop.is_set():
                    return None
                time.sleep(delay)
                delay = min(2 * delay, self.config.retry_max_s)
                continue
            if outage_since is not None:
                log.warning("database available again after %.1f s",
                            time.monotonic() - outage_since)
            return result

    def _rollup(self, force: bool = False) -> None:
        try:
            self.store.rollup(None if force else time.time() - 120)
        except Exception as exc:  # never fatal: queries stay exact, retried next time
            self._log_once("rollup", "summary rollup failed: %s", exc)

    # -- bus side (event loop) ------------------------------------------------------------------
    def _on_msg(self, partition: int) -> Callable[[Any], Awaitable[None]]:
        """The subscription callback of one partition."""

        pending, held, batch_max = self._pending, self._held, self.config.batch_max

        async def cb(msg: Any) -> None:
            now = time.monotonic()
            pending.append((partition, msg, now))
            held[id(msg)] = (msg, now)
            if len(pending) == 1:
                self._arrived.set()
            elif len(pending) >= batch_max:
                self._full.set()

        return cb

    async def _reply(self, msg: Any, what: bytes) -> None:
        """``+ACK``, ``+TERM`` or ``+WPI`` (in progress) to the message's reply subject."""
        if msg.reply:
            await self._nc.publish(msg.reply, what)

    async def _ack(self, msg: Any, what: bytes) -> None:
        """:meth:`_answer` after the commit; a reply lost to a reconnect is not an error (the
        message is delivered again and stored as a duplicate, then acked)."""
        try:
            await self._answer(msg, what)
        except Exception as exc:
            self._log_once("ack", "an ack was not sent (the message will be delivered again): "
                           "%s", exc)

    async def _answer(self, msg: Any, what: bytes) -> None:
        """The final :meth:`_reply` to a message (``+ACK``, ``-NAK``, ``+TERM``): it is no
        longer in hand, so :meth:`_heartbeat` sends it nothing more (a ``+WPI`` after a
        ``-NAK`` would push its redelivery from ``nak_delay_s`` out to ``ack_wait``)."""
        self._held.pop(id(msg), None)
        await self._reply(msg, what)

    async def _heartbeat(self) -> None:
        """Keep every message in hand in progress (``+WPI``) while it waits for its batch, is
        decoded, written (however long the commit or a database outage takes) or waits
        behind the live fan-out, so JetStream does not deliver it again after ``ack_wait``
        (its redelivery would be written a second time, as a ``duplicate``).

        Every ``ack_wait/4`` each message held at least that long is marked: its first mark
        goes out at most ``ack_wait/2`` after it arrived, the next ones every ``ack_wait/4``.
        Runs from before the first subscription (messages arrive while the other partitions'
        consumers are being set up) until the writer closes."""
        period = max(self.bus.ack_wait_s / 4, 0.05)
        held = self._held
        while not self._closing:
            await asyncio.sleep(period)
            old = time.monotonic() - period
            for key, (m, t) in list(held.items()):
                # checked again right before the publish, which queues the +WPI before
                # yielding: a message answered meanwhile gets nothing after its answer
                if t <= old and key in held:
                    with contextlib.suppress(Exception):
                        await self._reply(m, b"+WPI")

    def _count_delivery(self, items: list[tuple[int, Any]]) -> None:
        mt = self.metrics
        for p, m in items:
            mt.of(p)[0].inc()
            if _delivered(m.reply) > 1:
                self.counters.redelivered += 1
                mt.of(p)[2].inc()

    async def _handle(self, items: list[tuple[int, Any]]) -> None:
        c, mt = self.counters, self.metrics
        c.messages += len(items)
        self._count_delivery(items)
        msgs = [m for _, m in items]
        blocks: list[SampleBlock] = []
        kept: list[Any] = []
        parts: list[int] = []
        for (p, m), got in zip(items, decode_blocks([m.data for m in msgs]), strict=True):
            if isinstance(got, BlockCodecError):
                c.bad_messages += 1
                mt.refused.labels("bad_message").inc()
                self._log_once("bad_message", "message on %s is not a block, terminated: %s",
                               m.subject, got)
                with contextlib.suppress(Exception):
                    await self._answer(m, b"+TERM")
            else:
                blocks.append(got)
                kept.append(m)
                parts.append(p)
        if not blocks:
            return
        result = await asyncio.to_thread(self._write_db, blocks)
        if result is None:  # stopped during an outage: delivered again to the next writer
            return
        c.batches += 1
        new: list[SampleBlock] = []
        nak = b'-NAK {"delay": %d}' % round(self.config.nak_delay_s * 1e9)
        for p, m, (b, o) in zip(parts, kept, result, strict=True):
            if o.status == "unavailable":  # its shard is down: delivered again later
                c.unavailable += 1
                mt.of(p)[3].inc()
                self._log_once(f"unavailable:{p}", "blocks of partition %d held back, their "
                               "database shard is unavailable (delivered again): %s", p,
                               o.detail)
                with contextlib.suppress(Exception):
                    await self._answer(m, nak)
                continue
            if o.status == "refused":
                reason = o.reason or "unstorable"
                c.refused[reason] = c.refused.get(reason, 0) + 1
                mt.refused.labels(reason).inc()
                self._log_once(f"refused:{reason}", "block of %s (epoch %d, seq %d) refused by "
                               "storage after its machine was acknowledged (%s): %s",
                               b.machine_id, b.epoch, b.seq, reason, o.detail)
                await self._ack(m, b"+TERM")
                continue
            if o.status == "stored":
                new.append(b)
                c.stored_blocks += 1
                c.stored_samples += b.n
                mt.stored_samples.inc(b.n)
            else:
                c.duplicates += 1
            await self._ack(m, b"+ACK")
            mt.of(p)[1].inc()
        if self.live is not None and new:
            live = self.live
            try:
                await asyncio.to_thread(live.publish, new)
            except Exception as exc:  # fan-out is best effort; storage is the truth
                self._log_once("publish", "live fan-out failed: %s", exc)

    async def _gather(self) -> None:
        """Wait until ``batch_max`` messages are in hand or the oldest of them has waited
        ``batch_wait_s`` (one wake-up, not one per message)."""
        left = self._pending[0][2] + self.config.batch_wait_s - time.monotonic()
        if left <= 0 or len(self._pending) >= self.config.batch_max:
            return
        self._full.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._full.wait(), left)

    async def _report(self) -> None:
        last, t_last = 0, time.monotonic()
        while not self._closing:
            await asyncio.sleep(self.config.report_interval_s)
            now = time.monotonic()
            c = self.counters
            log.info("store-writer: %d messages, stored %d blocks / %d samples (%.0f samples/s), "
                     "%d duplicates, refused %s, retries %d", c.messages, c.stored_blocks,
                     c.stored_samples, (c.stored_samples - last) / max(now - t_last, 1e-9),
                     c.duplicates, c.refused, c.write_retries)
            last, t_last = c.stored_samples, now

    async def _lag(self, jsm: Any) -> None:
        """Every ``lag_interval_s``: each partition's messages not acked yet, from JetStream."""
        while not self._closing:
            for p in self.partitions:
                try:
                    info = await jsm.consumer_info(self.bus.stream, durable_name(self.bus, p))
                except Exception as exc:  # NATS reconnecting: the gauge keeps its last value
                    self._log_once("lag", "could not read the consumers' lag: %s", exc)
                    break
                self.metrics.lag.labels(str(p)).set(
                    int(info.num_pending or 0) + int(info.num_ack_pending or 0))
            await asyncio.sleep(self.config.lag_interval_s)

    async def _rollups(self) -> None:
        while not self._closing:
            await asyncio.sleep(self.config.rollup_interval_s)
            await asyncio.to_thread(self._rollup)

    async def run(self) -> dict[str, Any]:
        """Consume until :meth:`stop`; returns the counters.

        Raises:
            StorageUnavailableError: NATS unreachable at start.
        """
        nats = self._nats
        api = nats.js.api
        try:
            nc = await nats.connect(servers=[self.bus.url], name="cranetwin-store-writer",
                                    connect_timeout=5, allow_reconnect=True,
                                    max_reconnect_attempts=-1, reconnect_time_wait=0.25)
        except Exception as exc:
            raise StorageUnavailableError(
                f"NATS at {redact(self.bus.url)} unreachable: {exc}") from exc
        self._nc = nc
        tasks: list[asyncio.Task[None]] = []
        subs: list[Any] = []
        try:
            tasks.append(asyncio.create_task(self._heartbeat()))
            js = nc.jetstream(timeout=5)
            await ensure_stream(js, self.bus)
            jsm = nc.jsm(timeout=5)
            for p in self.partitions:
                name = durable_name(self.bus, p)
                try:
                    await jsm.consumer_info(self.bus.stream, name)
                except nats.js.errors.NotFoundError:
                    await jsm.add_consumer(self.bus.stream, api.ConsumerConfig(
                        durable_name=name, deliver_subject=deliver_subject(self.bus, p),
                        deliver_group=name, filter_subject=partition_filter(self.bus, p),
                        ack_policy=api.AckPolicy.EXPLICIT, ack_wait=self.bus.ack_wait_s,
                        deliver_policy=api.DeliverPolicy.ALL, max_deliver=-1,
                        max_ack_pending=self.config.batch_max))
                subs.append(await nc.subscribe(deliver_subject(self.bus, p), queue=name,
                                               cb=self._on_msg(p)))
            tasks.append(asyncio.create_task(self._report()))
            tasks.append(asyncio.create_task(self._rollups()))
            if self.config.lag_interval_s > 0:
                tasks.append(asyncio.create_task(self._lag(jsm)))
            self.ready.set()
            while not self._stop.is_set():
                for t in tasks:
                    if t.done() and not t.cancelled() and t.exception() is not None:
                        raise t.exception()  # type: ignore[misc]
                if not self._pending:
                    self._arrived.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(self._arrived.wait(), self.config.fetch_wait_s)
                    continue
                await self._gather()
                if self._stop.is_set():  # not acked: delivered again to the next writer
                    break
                batch = [(p, m) for p, m, _ in self._pending[:self.config.batch_max]]
                del self._pending[:self.config.batch_max]
                await self._handle(batch)
        finally:
            # Bounded whatever the connection does: nats-py swallows a cancellation inside some
            # of its calls while it reconnects, so nothing here waits on a cancelled call to
            # finish, and the loops also end by the flag.
            self._closing = True
            if subs:  # no more deliveries; what is not acked is delivered again
                await _within(asyncio.gather(*(s.unsubscribe() for s in subs),
                                             return_exceptions=True),
                              SHUTDOWN_STEP_S, "unsubscribe")
            for t in tasks:
                t.cancel()
            if tasks:
                _, left = await asyncio.wait(tasks, timeout=SHUTDOWN_STEP_S)
                if left:
                    log.warning("store-writer: %d background task(s) did not end on "
                                "shutdown; left behind", len(left))
            await _within(nc.close(), SHUTDOWN_STEP_S, "close")
        await asyncio.to_thread(self._rollup, True)
        return self.counters.as_dict()
