"""The UDP ingest daemon: datagrams in, durable blocks out, acks after commit; it never stops.

Shape (after uvicorn's ``serve()`` and the sans-IO split of h11/aioquic)::

    socket ─► _IngestProtocol.datagram_received (event loop: bytes, address, receive time)
                 │
                 ▼
          gathered into batches of ≤ batch_max datagrams, handed over batch_wait_s after
          the first (one queue put and one decoder wake-up per batch); more than queue_max
          accepted and not yet decoded ── dropped["queue_full"] (the sender retransmits)
                 │
                 ▼  decoder thread (blocks on the queue, no polling):
          Receiver.receive (HMAC first, then replay check, validation, decode)
                 │   replayed → ack;  refused → refusal;  anything else bad → counted, silent
                 ▼  queue of 2 decoded batches (back-pressure)
          writer thread: per-block outcomes of one batch write (stored / duplicate / refused)
                 │   storage unavailable → the batch is retried with backoff, nothing acked
                 ▼
          Receiver.mark_durable, one ack per (machine, epoch, address) ─► socket; LiveBus.publish

The event loop only moves bytes into batches, so the socket is drained even while a batch is
being decoded and written (a slow loop overflows the kernel buffer and turns into loss).
Decoding the next batch overlaps the database round trip of the current one. The protocol
state (:class:`~cranetwin.protocol.Receiver`) is shared by the two threads under one lock.

Nothing is acknowledged before it is committed, and storage ignores a block it already holds, so
a sender that retransmits until acknowledged gets every sample stored exactly once, whatever the
link loses, duplicates or reorders, and across a crash of the daemon.

Faults never stop the daemon:

* every exception in the decoder and writer loops (storage, protocol, rollup, live fan-out, a
  bug) is caught, counted and logged once per kind, and the loop goes on; a thread that dies
  anyway is restarted by a supervisor (``writer_restarts``, ``decoder_restarts``);
* a block that storage refuses fails alone: its machine gets a refusal, the rest of the batch is
  acknowledged (isolation between machines);
* while storage is unavailable the batch is retried with exponential backoff (``retry_min_s``
  … ``retry_max_s``) and nothing is acknowledged; ingest resumes when the database is back;
* a machine registered with a model that does not load is logged once and its datagrams are
  dropped as ``bad_model``; the other machines are served.

Modules: the datagram path (decoding through the Receiver, acks and refusals) in
:mod:`~cranetwin.ingest.datagrams`, the decoder and writer threads and their supervisor in
:mod:`~cranetwin.ingest.pipeline`, the database side (retries through outages, block-by-block
fallback, status, rollup) in :mod:`~cranetwin.ingest.writer`, configuration in
:mod:`~cranetwin.ingest.config`, counters in :mod:`~cranetwin.ingest.metrics`, binding sockets in
:mod:`~cranetwin.ingest.sockets`, machine keys in :mod:`~cranetwin.ingest.keys`; this module is the
daemon's lifecycle (socket, threads started, metrics served, shutdown).

``serve()`` owns the lifecycle: SIGTERM/SIGINT stop the socket, the queue is drained and
written, the last acks go out and the 1-min rollup runs, in bounded time: during a database
outage (or a database call stuck longer than ``stall_timeout_s``) the unwritten batches are
given up — they were never acknowledged, so their senders retransmit them to the next run. A
second signal gives up at once. Counters are served as Prometheus text on HTTP ``/metrics``
(``metrics_host``/``metrics_port``) and by :meth:`IngestDaemon.snapshot`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from prometheus_client import CollectorRegistry, Histogram, start_http_server

from cranetwin.ingest.config import DaemonConfig, IngestConfigError, check_model, layout_of
from cranetwin.ingest.datagrams import Addr, Item, Raw
from cranetwin.ingest.keys import MachineKeys
from cranetwin.ingest.metrics import COUNTERS, Metrics, SnapshotCollector
from cranetwin.ingest.pipeline import Pipeline, drain
from cranetwin.ingest.sockets import _bind, _bind_message, new_event_loop
from cranetwin.ingest.writer import StorageWriter, is_unavailable
from cranetwin.protocol import Receiver
from cranetwin.storage import Store, StoreSpec, open_store
from cranetwin.storage.live import LiveBus

__all__ = ["COUNTERS", "DaemonConfig", "IngestConfigError", "IngestDaemon", "Metrics",
           "check_model", "is_unavailable", "layout_of", "new_event_loop", "serve",
           "serve_store"]

log = logging.getLogger(__name__)


# --- the daemon ---------------------------------------------------------------------------------
class _IngestProtocol(asyncio.DatagramProtocol):
    def __init__(self, daemon: IngestDaemon) -> None:
        self.daemon = daemon

    def datagram_received(self, data: bytes, addr: Addr) -> None:
        self.daemon._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP errors of sent acks
        self.daemon.metrics.drop("socket_error")


class IngestDaemon(Pipeline):
    """UDP ingest into a :class:`~cranetwin.storage.Store`.

    Args:
        store: Where blocks go (migrated already).
        config: Settings.
        bus: Live fan-out of newly stored blocks (None: no fan-out).
        clock_ns: Server clock [ns since the epoch] (injectable for tests).
    """

    def __init__(self, store: Store, config: DaemonConfig | None = None,
                 bus: LiveBus | None = None, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.store = store
        self.config = config or DaemonConfig()
        self.bus = bus
        self.metrics = Metrics()
        self.address: tuple[str, int] | None = None
        self.metrics_address: tuple[str, int] | None = None
        self.ready = threading.Event()
        self.db = StorageWriter(self.store, self.config, self.metrics, self._log_once)
        self.registry = CollectorRegistry()
        self.registry.register(SnapshotCollector(self))
        self.write_latency = Histogram(
            "cranetwin_ingest_write_seconds", "duration of one committed batch write [s]",
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10))
        self._clock = clock_ns
        self.keys = MachineKeys(store, self.config.key_refresh_s, self._log_once)
        self._receiver = Receiver(self.keys.lookup, limits=self.config.limits)
        # batches gathered by the event loop (bounded by queue_max datagrams in _on_datagram);
        # None wakes the decoder at shutdown
        self._queue: queue.Queue[list[Raw] | None] = queue.Queue()
        self._gathering: list[Raw] = []
        self._hand_over_at: asyncio.TimerHandle | None = None
        self._accepted_in = 0                # datagrams accepted (event loop thread only)
        self._taken_out = 0                  # datagrams taken by the decoder (its thread only)
        self._decoded: queue.Queue[list[tuple[Item, Addr]] | None] = queue.Queue(2)
        self._rx_lock = threading.Lock()  # the Receiver is shared by decoder and writer
        self._stopping = False
        self._draining = threading.Event()   # shutdown: finish what is queued, then return
        self._abandon = self.db.abandon      # shutdown: give up unwritten batches now
        self._decoder_done = threading.Event()
        self._threads: dict[str, threading.Thread] = {}
        self._finished: set[str] = set()
        self._died: set[str] = set()         # threads that died, not yet restarted
        self._in_hand = 0                    # items of the batch the writer is writing
        self._logged: set[str] = set()
        self._log_lock = threading.Lock()
        self._transport: asyncio.DatagramTransport | None = None
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._signals = 0
        self._http: Any = None
        self._started = time.monotonic()

    @property
    def storage_outage(self) -> bool:
        """True while storage is unavailable (from the first failed write of an outage until a
        write succeeds)."""
        return self.db.outage

    # -- keys ---------------------------------------------------------------------------------
    def reload_keys(self) -> None:
        """Read machine keys from storage now (:meth:`MachineKeys.reload`).

        Raises:
            Exception: storage could not be read (the previous keys stay in use).
        """
        self.keys.reload()

    # -- metrics --------------------------------------------------------------------------------
    @property
    def metrics_url(self) -> str | None:
        """``http://HOST:PORT/metrics`` of the Prometheus endpoint once serving, else None."""
        if self.metrics_address is None:
            return None
        host, port = self.metrics_address
        return f"http://{host if ':' not in host else f'[{host}]'}:{port}/metrics"

    def snapshot(self) -> dict[str, Any]:
        """Counters, queue depth and uptime as a JSON-ready dict."""
        return self.metrics.snapshot(self._queue_depth(), self.config.queue_max, self._started)

    async def _report(self) -> None:
        last_samples, last_t = 0, time.monotonic()
        while True:
            await asyncio.sleep(self.config.metrics_interval_s)
            s = self.snapshot()
            now = time.monotonic()
            rate = (s["stored_samples"] - last_samples) / max(now - last_t, 1e-9)
            last_samples, last_t = s["stored_samples"], now
            log.info("ingest: received %d, stored %d blocks / %d samples (%.0f samples/s), "
                     "duplicates %d, dropped %s, queue %d/%d, write errors %d%s",
                     s["received"], s["stored_blocks"], s["stored_samples"], rate,
                     s["duplicates"], s["dropped"], s["queue_depth"], s["queue_max"],
                     s["write_errors"], ", STORAGE UNAVAILABLE" if self.db.outage else "")

    # -- lifecycle ------------------------------------------------------------------------------
    def _socket(self) -> socket.socket:
        """The bound UDP socket.

        Raises:
            IngestConfigError: the host does not resolve, the address is not local, the port is
                in use or needs privileges.
        """
        cfg = self.config
        if cfg.socket_fd is not None:  # a member of the parent's SO_REUSEPORT group
            sock = socket.socket(fileno=cfg.socket_fd)
        else:
            sock = _bind(cfg.host, cfg.port, socket.SOCK_DGRAM, "UDP", "--bind")
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, cfg.rcvbuf_bytes)
        sock.setblocking(False)
        return sock

    def _start_metrics_server(self) -> None:
        cfg = self.config
        if cfg.metrics_host is None:
            return
        # resolve and check first: start_http_server's own errors are less clear
        _bind(cfg.metrics_host, cfg.metrics_port, socket.SOCK_STREAM, "TCP",
              "--metrics-bind").close()
        try:
            server, _ = start_http_server(cfg.metrics_port, cfg.metrics_host,
                                          registry=self.registry)
        except OSError as exc:
            raise IngestConfigError(_bind_message(exc, cfg.metrics_host, cfg.metrics_port, "TCP",
                                                  "--metrics-bind")) from None
        self._http = server
        host, port = server.server_address[:2]
        self.metrics_address = (str(host), int(port))

    def stop(self) -> None:
        """Ask a running :meth:`serve` to shut down gracefully (thread-safe, idempotent)."""
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._stop.set)

    def _on_signal(self) -> None:
        """SIGTERM/SIGINT: the first stops gracefully, a second gives up unwritten batches."""
        self._signals += 1
        if self._stop is not None:
            self._stop.set()
        if self._signals > 1:
            log.warning("second stop signal: giving up unwritten batches now")
            self._abandon.set()

    async def serve(self, install_signal_handlers: bool = True,
                    on_ready: Callable[[IngestDaemon], None] | None = None) -> None:
        """Run until :meth:`stop`, SIGTERM or SIGINT; then stop receiving, write everything
        accepted, send the last acks and roll up summaries — in bounded time.

        Args:
            install_signal_handlers: Handle SIGTERM/SIGINT (main thread only).
            on_ready: Called once listening (``address`` and ``metrics_url`` are set).

        Raises:
            IngestConfigError: the UDP or metrics address cannot be bound.
            Exception: the machine keys could not be read from storage at start.
        """
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self.reload_keys()
        sock = self._socket()
        try:
            self._start_metrics_server()
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        transport, _ = await self._loop.create_datagram_endpoint(
            lambda: _IngestProtocol(self), sock=sock)
        self._transport = transport
        host, port = sock.getsockname()[:2]
        self.address = (host, port)
        if install_signal_handlers:
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    self._loop.add_signal_handler(sig, self._on_signal)
        self._start_thread("decoder")
        self._start_thread("writer")
        tasks = [asyncio.create_task(self._report()), asyncio.create_task(self._supervise())]
        log.info("ingest listening on udp %s:%d, %d machine(s), rcvbuf %d bytes, metrics %s",
                 host, port, len(self.keys), sock.getsockopt(socket.SOL_SOCKET,
                                                             socket.SO_RCVBUF),
                 self.metrics_url or "not served")
        self.ready.set()
        try:
            if on_ready is not None:
                on_ready(self)
            await self._stop.wait()
        finally:
            await self._shutdown(transport, tasks)

    async def _shutdown(self, transport: asyncio.DatagramTransport,
                        tasks: list[asyncio.Task[None]]) -> None:
        cfg = self.config
        t0 = time.monotonic()
        log.info("ingest shutting down: flushing %d queued datagram(s)", self._queue_depth())
        self._stopping = True
        pause = getattr(transport, "pause_reading", None)  # not every loop has it
        if pause is not None:
            pause()
        self._draining.set()
        self._wake_decoder()
        writer = self._threads.get("writer")
        while writer is not None and not self._abandon.is_set():
            writer = self._threads.get("writer")  # the supervisor may have replaced it
            if writer is None or (not writer.is_alive() and "writer" in self._finished):
                break
            now = time.monotonic()
            if self.db.outage:
                log.warning("storage unavailable at shutdown: giving up %d queued datagram(s) "
                            "and the batch in hand (never acknowledged: their senders "
                            "retransmit)", self._queue_depth())
                self._abandon.set()
            elif not self.db.idle and now - self.db.progress > cfg.stall_timeout_s:
                log.warning("a database call has not returned for %.1f s: giving up the "
                            "unwritten batches (never acknowledged)", now - self.db.progress)
                self._abandon.set()
            elif now - t0 > cfg.shutdown_timeout_s:
                log.warning("flush not done after %.0f s: giving up the rest (never "
                            "acknowledged)", cfg.shutdown_timeout_s)
                self._abandon.set()
            await asyncio.sleep(0.02)
        clean = not self._abandon.is_set()
        if not clean:  # the writer leaves its backoff at once; a call stuck in C is not waited
            await self._wait_threads(1.0)
            dropped = self._queue_depth() + sum(len(b) for b in drain(self._decoded))
            writer = self._threads.get("writer")
            if writer is not None and writer.is_alive():  # stuck in a database call
                dropped += self._in_hand
            if dropped:
                self.metrics.drop("unwritten_at_shutdown", dropped)
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        transport.close()
        if clean:
            await self._bounded(lambda: self.db.maybe_rollup(True), cfg.stall_timeout_s,
                                "final summary rollup")
        if self._http is not None:
            self._http.shutdown()
            self._http.server_close()
        log.info("ingest stopped in %.2f s: %s", time.monotonic() - t0,
                 json.dumps(self.snapshot()))

    async def _wait_threads(self, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and any(t.is_alive() for t in self._threads.values()):
            await asyncio.sleep(0.02)

    @staticmethod
    async def _bounded(fn: Callable[[], None], timeout_s: float, what: str) -> None:
        """Run ``fn`` in a daemon thread and wait for it at most ``timeout_s`` (a database call
        stuck in C cannot be interrupted; never use the loop's executor for it, whose threads
        are joined at exit)."""
        done = threading.Event()

        def run() -> None:
            try:
                fn()
            finally:
                done.set()

        threading.Thread(target=run, name="ingest-final", daemon=True).start()
        end = time.monotonic() + timeout_s
        while not done.is_set():
            if time.monotonic() > end:
                log.warning("%s did not finish in %.1f s: not waited for", what, timeout_s)
                return
            await asyncio.sleep(0.02)


def serve(db_url: str | StoreSpec, config: DaemonConfig | None = None, bus: LiveBus | None = None,
          on_ready: Callable[[IngestDaemon], None] | None = None,
          busy_timeout_s: float = 3.0) -> dict[str, Any]:
    """Open the store at ``db_url`` (a URL or a :class:`~cranetwin.storage.StoreSpec`, e.g.
    shards: :func:`cranetwin.storage.open_store`) and run the daemon until SIGTERM/SIGINT
    (blocking).

    Args:
        on_ready: Called once the daemon listens (``address``, ``metrics_url`` set).
        busy_timeout_s: SQLite only: how long a write waits for another process's lock before
            storage reports itself unavailable (then the batch is retried with backoff) [s];
            shorter than ``stall_timeout_s`` so that a locked database is an outage, not a
            stuck call.

    Returns:
        The final :meth:`IngestDaemon.snapshot` (counters after the shutdown flush).

    Raises:
        IngestConfigError: an address cannot be bound.
        StorageError: the database cannot be opened.
    """
    return serve_store(open_store(db_url, busy_timeout_s=busy_timeout_s), config, bus, on_ready)


def serve_store(store: Store, config: DaemonConfig | None = None, bus: LiveBus | None = None,
                on_ready: Callable[[IngestDaemon], None] | None = None) -> dict[str, Any]:
    """Run the daemon on an opened ``store`` until SIGTERM/SIGINT (blocking), then close the
    store and ``bus`` (whatever happens). :func:`serve` and
    :func:`cranetwin.ingest.bus_serve.serve_to_bus` differ only in the store they pass.

    Returns:
        The final :meth:`IngestDaemon.snapshot`.

    Raises:
        IngestConfigError: an address cannot be bound.
    """
    try:
        daemon = IngestDaemon(store, config, bus)
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            runner.run(daemon.serve(on_ready=on_ready))
        return daemon.snapshot()
    finally:
        if bus is not None:
            bus.close()
        store.close()
