"""The daemon's two worker threads and their supervisor: the decoder (raw datagrams → decoded
batches, back-pressured by a queue of two) and the writer (one batch write each, then the acks),
restarted by a supervisor on the event loop when one dies.

:class:`Pipeline` sits between :class:`~cranetwin.ingest.datagrams.DatagramPath` (decoding, acks)
and :class:`~cranetwin.ingest.daemon.IngestDaemon` (lifecycle); the database side itself is
:class:`~cranetwin.ingest.writer.StorageWriter`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from functools import partial

from prometheus_client import Histogram

from cranetwin.ingest.datagrams import Addr, DatagramPath, Item
from cranetwin.ingest.writer import Abandoned, StorageWriter
from cranetwin.protocol.status import StatusReport
from cranetwin.samples import SampleBlock
from cranetwin.storage.live import LiveBus

__all__ = ["Pipeline", "drain"]

log = logging.getLogger("cranetwin.ingest.daemon")  # one logger for the daemon's messages


class Pipeline(DatagramPath):
    """Decoder and writer threads and their supervisor (base of the daemon; its state is set by
    the daemon's ``__init__``)."""

    bus: LiveBus | None
    db: StorageWriter
    write_latency: Histogram
    _decoded: queue.Queue[list[tuple[Item, Addr]] | None]
    _draining: threading.Event
    _abandon: threading.Event
    _decoder_done: threading.Event
    _threads: dict[str, threading.Thread]
    _finished: set[str]
    _died: set[str]
    _in_hand: int

    # -- decoder thread -------------------------------------------------------------------------
    def _decoder(self) -> None:
        """Decoder thread: batches of raw datagrams (gathered by the event loop) → decoded
        batches (overlaps the writer's round trips, which release the GIL). It blocks until a
        batch comes (no polling); returns at the wake-up that shutdown queues after the last
        batch (:meth:`_wake_decoder`)."""
        while True:
            raw = self._queue.get()
            if raw is None:
                if self._draining.is_set():
                    self._decoder_done.set()
                    self._put_decoded(None)  # wakes the writer: nothing more comes
                    return
                continue
            self._taken_out += len(raw)
            try:
                batch = self._decode(raw)
                if batch:
                    self._put_decoded(batch)
            except Exception as exc:
                self.metrics.drop("internal_error")
                self._log_once("decoder", exc, "unexpected error in the decoder loop "
                               "(the loop goes on): %s", exc)

    def _put_decoded(self, batch: list[tuple[Item, Addr]] | None) -> None:
        """Hand a decoded batch (None: the decoder is done) to the writer; blocks while the
        writer is behind (back-pressure), gives the batch up once shutdown abandons."""
        while True:
            if self._abandon.is_set():
                if batch:
                    self.metrics.drop("unwritten_at_shutdown", len(batch))
                return
            try:
                self._decoded.put(batch, timeout=0.2)
                return
            except queue.Full:
                continue

    def _wake_decoder(self) -> None:
        """Shutdown (event loop, after ``_stopping`` and ``_draining`` are set): the batch
        being gathered goes to the decoder, then the wake-up that ends it."""
        self._hand_over()
        self._queue.put_nowait(None)

    # -- writer thread --------------------------------------------------------------------------
    def _writer(self) -> None:
        """Writer thread: decoded batches → one batch write each (merging any that queued up
        meanwhile) → acks. It blocks until a batch comes or the next rollup is due (no
        polling; during shutdown it checks every 0.1 s whether to give up); returns once the
        decoder is done and everything decoded is written (or abandoned)."""
        while True:
            self.db.progress = time.monotonic()
            if self._abandon.is_set():
                self._discard_decoded()
                return
            if self._draining.is_set() and self._decoder_done.is_set() and self._decoded.empty():
                return
            wait_s = 0.1 if self._draining.is_set() else self.db.rollup_due_in()
            self.db.idle = True
            try:
                first = self._decoded.get(timeout=wait_s)
            except queue.Empty:
                self.db.maybe_rollup()
                continue
            finally:
                self.db.idle = False
            if first is None:  # the decoder is done (shutdown)
                continue
            items = list(first)
            while len(items) < self.config.batch_max:
                try:
                    more = self._decoded.get_nowait()
                except queue.Empty:
                    break
                if more is not None:
                    items.extend(more)
            self._in_hand = len(items)
            try:
                self._write(items)
            except Abandoned:
                self.metrics.drop("unwritten_at_shutdown", len(items))
            except Exception as exc:  # a bug must not kill the writer: nothing acked, retried
                self.metrics.add("write_errors")
                self._log_once("write", exc, "unexpected error writing %d item(s); not "
                               "acknowledged (senders retransmit): %s", len(items), exc)
            self._in_hand = 0
            if not self._draining.is_set():
                self.db.maybe_rollup()

    def _discard_decoded(self) -> None:
        for batch in drain(self._decoded):
            self.metrics.drop("unwritten_at_shutdown", len(batch))

    def _write(self, items: list[tuple[Item, Addr]]) -> None:
        """Write one batch; ack what is durable, refuse what storage refused.

        Raises:
            Abandoned: shutdown gave up while storage was unavailable (nothing acked).
        """
        if not items:
            return
        m = self.metrics
        t = time.perf_counter()
        block_items = [(i, a) for i, a in items if isinstance(i, SampleBlock)]
        blocks = [i for i, _ in block_items]
        outcomes = self.db.write_blocks(blocks)
        durable: list[tuple[Item, Addr]] = []
        refused: list[tuple[Item, Addr, str]] = []
        new: list[SampleBlock] = []
        for (b, addr), (kind, reason) in zip(block_items, outcomes, strict=True):
            if kind == "stored":
                new.append(b)
                durable.append((b, addr))
            elif kind == "duplicate":
                m.add("duplicates")
                durable.append((b, addr))
            elif kind == "refused":
                refused.append((b, addr, reason))
            else:
                m.drop(reason)
        for item, addr in items:
            if isinstance(item, StatusReport):
                try:
                    self.db.retry("status", partial(self.db.write_status, item))
                except Abandoned:
                    raise
                except Exception as exc:
                    m.drop("write_error")
                    self._log_once("write_status", exc, "status report of %s could not be "
                                   "written (not acknowledged): %s", item.machine_id, exc)
                    continue
                durable.append((item, addr))
        dt = time.perf_counter() - t
        m.write_seconds += dt
        self.write_latency.observe(dt)
        m.add("batches")
        m.add("stored_blocks", len(new))
        m.add("stored_samples", sum(b.n for b in new))
        self._after_commit(durable, refused)
        if self.bus is not None and new:
            try:
                self.bus.publish(new)
            except Exception as exc:  # fan-out is best effort; storage is the truth
                m.drop("publish_error")
                self._log_once("publish", exc, "live fan-out failed: %s", exc)

    # -- threads and supervision ----------------------------------------------------------------
    def _run_thread(self, name: str, target: Callable[[], None]) -> None:
        try:
            target()
        except BaseException as exc:  # noqa: BLE001 - reported; the supervisor restarts it
            log.critical("ingest %s thread died (restarted by the supervisor): %r", name, exc,
                         exc_info=exc)
            self._died.add(name)  # (still alive for a moment: is_alive() cannot tell yet)
            loop = self._loop
            if loop is not None:  # restart now, not at the supervisor's next periodic check
                with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
                    loop.call_soon_threadsafe(self._supervise_once)
            return
        self._finished.add(name)

    def _start_thread(self, name: str) -> None:
        target = {"decoder": self._decoder, "writer": self._writer}[name]
        t = threading.Thread(target=self._run_thread, args=(name, target),
                             name=f"ingest-{name}", daemon=True)
        self._threads[name] = t
        t.start()

    def _supervise_once(self) -> None:
        """Restart a decoder or writer thread that died (counted). Called by a dying thread
        through the event loop, and every ``supervise_interval_s`` as a backstop."""
        if self._abandon.is_set():
            return
        for name, t in list(self._threads.items()):
            if name in self._died or (not t.is_alive() and name not in self._finished):
                self._died.discard(name)
                self.metrics.add(f"{name}_restarts")
                log.error("restarting the ingest %s thread", name)
                self._start_thread(name)

    async def _supervise(self) -> None:
        while True:
            await asyncio.sleep(self.config.supervise_interval_s)
            try:
                self._supervise_once()
            except Exception as exc:  # pragma: no cover - thread start failing
                self._log_once("supervise", exc, "supervisor failed: %s", exc)


def drain(q: queue.Queue[list[tuple[Item, Addr]] | None]) -> list[list[tuple[Item, Addr]]]:
    """Every batch in ``q`` now, without waiting (the decoder's end marker left out)."""
    out: list[list[tuple[Item, Addr]]] = []
    while True:
        try:
            batch = q.get_nowait()
        except queue.Empty:
            return out
        if batch is not None:
            out.append(batch)

