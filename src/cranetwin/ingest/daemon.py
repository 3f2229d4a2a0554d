"""The UDP ingest daemon: datagrams in, durable blocks out, acks after commit.

Shape (after uvicorn's ``serve()`` and the sans-IO split of h11/aioquic)::

    socket ─► _IngestProtocol.datagram_received (event loop: bytes, address, receive time)
                 │
                 ▼
          bounded queue.Queue ── full → dropped["queue_full"] (the sender retransmits)
                 │
                 ▼  decoder thread, batches of ≤ batch_max datagrams or batch_wait_s:
          Receiver.receive (HMAC, replay window, decode) ── bad → dropped[reason] += 1
                 ▼  queue of 2 decoded batches (back-pressure)
          writer thread: Store.store_blocks (one transaction, durable on return)
                 ▼
          Receiver.mark_durable, one ack per (machine, address) ─► socket;  LiveBus.publish

The event loop only moves bytes into the queue, so the socket is drained even while a batch is
being decoded and written (a slow loop overflows the kernel buffer and turns into loss).
Decoding the next batch overlaps the database round trip of the current one. The protocol
state (:class:`~cranetwin.protocol.Receiver`) is shared by the two threads under one lock.

Nothing is acknowledged before it is committed, and storage ignores a (machine, seq) it already
holds, so a sender that retransmits until acknowledged gets every sample stored exactly once,
whatever the link loses, duplicates or reorders, and across a crash of the daemon.
``serve()`` owns the lifecycle: SIGTERM/SIGINT stop the socket, the queue is drained and
written, the last acks go out, the 1-min rollup runs, and the metrics file is written last.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import queue
import signal
import socket
import threading
import time
import tomllib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cranetwin.errors import CraneTwinError
from cranetwin.model import builtin_machines, load_machine, machine_from_dict
from cranetwin.protocol import (
    TYPE_ACK,
    DatagramError,
    Layout,
    MachineKey,
    Receiver,
    ReplayedError,
    datagram_seq,
    peek_header,
)
from cranetwin.protocol.status import StatusReport
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store
from cranetwin.storage.live import LiveBus

log = logging.getLogger(__name__)

Addr = tuple[Any, ...]
Item = SampleBlock | StatusReport
_STOP = object()


@dataclass
class DaemonConfig:
    """Settings of one daemon.

    Attributes:
        host, port: UDP address to bind (port 0 picks a free one; see ``IngestDaemon.address``).
        queue_max: Accepted datagrams waiting for the writer; beyond it they are dropped
            (counted as ``queue_full``) and the sender retransmits.
        batch_max: Blocks written per transaction at most.
        batch_wait_s: How long the writer gathers a batch after its first item [s].
        rcvbuf_bytes: Requested SO_RCVBUF (the kernel caps it at net.core.rmem_max).
        metrics_path: JSON file rewritten every ``metrics_interval_s`` (None: not written).
        metrics_interval_s: Period of the metrics log line and file [s].
        rollup_interval_s: Period of the 1-min summary rollup [s].
        key_refresh_s: Least time between reloads of machine keys after an unknown wire id [s].
    """

    host: str = "127.0.0.1"
    port: int = 5005
    queue_max: int = 50_000
    batch_max: int = 1000
    batch_wait_s: float = 0.05
    rcvbuf_bytes: int = 8 * 1024 * 1024
    metrics_path: Path | None = None
    metrics_interval_s: float = 10.0
    rollup_interval_s: float = 30.0
    key_refresh_s: float = 2.0


@dataclass
class Metrics:
    """Counters of one daemon run (written by the loop and the writer thread; ints only)."""

    received: int = 0
    received_bytes: int = 0
    accepted: int = 0
    stored_blocks: int = 0
    stored_samples: int = 0
    duplicates: int = 0
    status_reports: int = 0
    acks_sent: int = 0
    batches: int = 0
    write_errors: int = 0
    write_seconds: float = 0.0
    dropped: Counter[str] = field(default_factory=Counter)

    def snapshot(self, queue_depth: int, queue_max: int, started: float) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "dropped"}
        d["dropped"] = dict(self.dropped)
        d["dropped_total"] = sum(self.dropped.values())
        d["queue_depth"] = queue_depth
        d["queue_max"] = queue_max
        d["uptime_s"] = round(time.monotonic() - started, 3)
        d["time_unix_s"] = time.time()
        return d


def layout_of(model: str) -> Layout:
    """Channel layout of a machine model: a built-in name or machine-description TOML text.

    Raises:
        ModelError: The model does not load.
    """
    if model in builtin_machines():
        machine = load_machine(model)
    else:
        machine = machine_from_dict(tomllib.loads(model), source="<stored model>")
    return Layout.from_channels(machine.channels)


class _IngestProtocol(asyncio.DatagramProtocol):
    def __init__(self, daemon: IngestDaemon) -> None:
        self.daemon = daemon

    def datagram_received(self, data: bytes, addr: Addr) -> None:
        self.daemon._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP errors of sent acks
        self.daemon.metrics.dropped["socket_error"] += 1


class IngestDaemon:
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
        self.ready = threading.Event()
        self._clock = clock_ns
        self._keys: dict[int, MachineKey] = {}
        self._layouts: dict[str, Layout] = {}
        self._keys_loaded = 0.0
        self._receiver = Receiver(self._lookup)
        self._queue: queue.Queue[Any] = queue.Queue(self.config.queue_max)
        self._decoded: queue.Queue[Any] = queue.Queue(2)
        self._rx_lock = threading.Lock()  # the Receiver is shared by decoder and writer
        self._stopping = False
        self._transport: asyncio.DatagramTransport | None = None
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = time.monotonic()
        self._last_rollup = time.monotonic()

    # -- keys -----------------------------------------------------------------------------
    def reload_keys(self) -> None:
        """Read machine keys from storage (new registrations become valid)."""
        keys: dict[int, MachineKey] = {}
        models = {m.machine_id: m.model for m in self.store.machines()}
        for wire_id, (machine_id, secret) in self.store.machine_keys().items():
            model = models[machine_id]
            try:
                layout = self._layouts.get(model) or layout_of(model)
            except CraneTwinError as exc:
                log.error("machine %s: model does not load, its datagrams are dropped: %s",
                          machine_id, exc)
                continue
            self._layouts[model] = layout
            keys[wire_id] = MachineKey(wire_id, machine_id, secret, layout)
        self._keys = keys
        self._keys_loaded = time.monotonic()

    def _lookup(self, wire_id: int) -> MachineKey | None:
        key = self._keys.get(wire_id)
        if key is None and time.monotonic() - self._keys_loaded > self.config.key_refresh_s:
            self._keys_loaded = time.monotonic()  # rate limit even if the reload fails
            try:
                self.reload_keys()
            except CraneTwinError as exc:
                log.error("could not reload machine keys: %s", exc)
            key = self._keys.get(wire_id)
        return key

    # -- event loop side ------------------------------------------------------------------
    def _on_datagram(self, data: bytes, addr: Addr) -> None:
        m = self.metrics
        m.received += 1
        m.received_bytes += len(data)
        if self._stopping:  # arrived after shutdown began: not acked, so the sender retries
            m.dropped["shutdown"] += 1
            return
        try:
            self._queue.put_nowait((data, addr, self._clock()))
        except queue.Full:
            m.dropped["queue_full"] += 1

    def _decode(self, raw: list[tuple[bytes, Addr, int]]) -> list[tuple[Item, Addr]]:
        """Writer thread: authenticate and decode; bad datagrams are counted and dropped.

        Retransmissions are recognised before the (costly) decode from the header's wire id and
        seq: a copy of a datagram already in this batch, or below the machine's durable floor,
        is counted as ``replayed`` and answered with one ack per address and batch. Under
        overload this keeps retransmissions from eating the capacity that would clear them.
        """
        m = self.metrics
        items: list[tuple[Item, Addr]] = []
        seen: set[tuple[int, int]] = set()
        reack: dict[tuple[str, Addr], None] = {}
        for data, addr, now in raw:
            try:
                head = peek_header(data)
                key = self._keys.get(head.wire_id)
                ws = (head.wire_id, -1)
                if key is not None and head.type != TYPE_ACK:
                    ws = (head.wire_id, datagram_seq(data))
                    if ws in seen:  # a copy of one accepted (authentic) earlier in this batch
                        m.dropped["replayed"] += 1
                        continue
                    with self._rx_lock:
                        floor = self._receiver.floor(key.machine_id)
                    if ws[1] < floor:
                        m.dropped["replayed"] += 1
                        reack[(key.machine_id, addr)] = None
                        continue
                with self._rx_lock:
                    item = self._receiver.receive(data, now)
                items.append((item, addr))
                seen.add(ws)
            except ReplayedError as exc:
                m.dropped[exc.reason] += 1
                rk = self._keys.get(exc.wire_id) if exc.wire_id is not None else None
                if rk is not None:
                    reack[(rk.machine_id, addr)] = None  # its ack was probably lost
            except DatagramError as exc:
                m.dropped[exc.reason] += 1
            except Exception:  # a bug must not stop ingest: count, log once, go on
                m.dropped["internal_error"] += 1
                if m.dropped["internal_error"] == 1:
                    log.exception("unexpected error decoding a datagram (counted, dropped)")
        now_ns = self._clock()
        for machine_id, addr in reack:
            with contextlib.suppress(KeyError), self._rx_lock:
                ack = self._receiver.ack(machine_id, now_ns)
            self._sendto(ack, addr)
        m.accepted += len(items)
        return items

    def _sendto(self, data: bytes, addr: Addr) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(data, addr)
            self.metrics.acks_sent += 1
        except OSError:  # full buffer or unreachable: the sender retransmits and is acked then
            self.metrics.dropped["ack_send_error"] += 1

    def _after_commit(self, items: list[tuple[Item, Addr]]) -> None:
        """Writer thread, after commit: mark durable, then one ack per (machine, address)."""
        dest: dict[tuple[str, Addr], None] = {}
        acks: list[tuple[bytes, Addr]] = []
        with self._rx_lock:
            for item, addr in items:
                self._receiver.mark_durable(item.machine_id, item.seq)
                dest[(item.machine_id, addr)] = None
            now = self._clock()
            for machine_id, addr in dest:
                acks.append((self._receiver.ack(machine_id, now), addr))
        for ack, addr in acks:
            self._sendto(ack, addr)

    # -- writer thread --------------------------------------------------------------------
    def _decoder(self) -> None:
        """Decoder thread: raw datagrams → decoded batches (overlaps the writer's database
        round trips, which release the GIL)."""
        cfg = self.config
        done = False
        while not done:
            try:
                first = self._queue.get(timeout=0.5)
            except queue.Empty:
                continue
            if first is _STOP:
                break
            items = [first]
            deadline = time.monotonic() + cfg.batch_wait_s
            while len(items) < cfg.batch_max:
                try:
                    nxt = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    break
                if nxt is _STOP:
                    done = True
                    # drain whatever is left: shutdown flushes everything accepted
                    while True:
                        try:
                            rest = self._queue.get_nowait()
                        except queue.Empty:
                            break
                        if rest is not _STOP:
                            items.append(rest)
                    break
                items.append(nxt)
            batch = self._decode(items)
            if batch:
                self._decoded.put(batch)  # blocks when the writer is behind: back-pressure
        self._decoded.put(_STOP)

    def _writer(self) -> None:
        """Writer thread: decoded batches → one transaction each (merging any that queued up
        meanwhile) → acks."""
        while True:
            try:
                first = self._decoded.get(timeout=0.5)
            except queue.Empty:
                self._maybe_rollup()
                continue
            if first is _STOP:
                return
            items = list(first)
            stop = False
            while len(items) < self.config.batch_max:
                try:
                    more = self._decoded.get_nowait()
                except queue.Empty:
                    break
                if more is _STOP:
                    stop = True
                    break
                items.extend(more)
            self._write(items)
            self._maybe_rollup()
            if stop:
                return

    def _write(self, items: list[tuple[Item, Addr]]) -> None:
        if not items:
            return
        m = self.metrics
        t = time.perf_counter()
        blocks = [i for i, _ in items if isinstance(i, SampleBlock)]
        try:
            new = self.store.store_blocks(blocks)
            for item, _ in items:
                if isinstance(item, StatusReport):
                    self._write_status(item)
        except CraneTwinError as exc:
            m.write_errors += 1
            log.error("write of %d item(s) failed, not acknowledged (senders retransmit): %s",
                      len(items), exc)
            return
        except Exception:  # a bug must not kill the writer: nothing is acked, senders retry
            m.write_errors += 1
            log.exception("unexpected error writing %d item(s); not acknowledged", len(items))
            return
        m.write_seconds += time.perf_counter() - t
        m.batches += 1
        m.stored_blocks += len(new)
        m.stored_samples += sum(b.n for b in new)
        m.duplicates += len(blocks) - len(new)
        self._after_commit(items)
        if self.bus is not None and new:
            try:
                self.bus.publish(new)
            except Exception as exc:  # fan-out is best effort; storage is the truth
                m.dropped["publish_error"] += 1
                log.warning("live fan-out failed: %s", exc)

    def _write_status(self, r: StatusReport) -> None:
        def val(x: float) -> float | None:
            return None if x != x else x  # NaN → not reported

        self.store.update_status(r.machine_id, r.t_ns / 1e9, latitude_deg=val(r.latitude_deg),
                                 longitude_deg=val(r.longitude_deg),
                                 altitude_m=val(r.altitude_m),
                                 operating_hours=val(r.operating_hours))
        self.metrics.status_reports += 1

    def _maybe_rollup(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_rollup < self.config.rollup_interval_s:
            return
        self._last_rollup = now
        try:
            # minutes that ended a while ago (machine clocks may lag), or everything at shutdown
            self.store.rollup(None if force else time.time() - 120)
        except CraneTwinError as exc:
            log.warning("summary rollup failed (queries stay exact): %s", exc)

    # -- metrics --------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """Counters, queue depth and uptime as a JSON-ready dict."""
        return self.metrics.snapshot(self._queue.qsize(), self.config.queue_max, self._started)

    def write_metrics(self) -> None:
        """Write the snapshot to ``config.metrics_path`` atomically (rename)."""
        path = self.config.metrics_path
        if path is None:
            return
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.snapshot(), indent=1))
        os.replace(tmp, path)

    async def _report(self) -> None:
        last_samples, last_t = 0, time.monotonic()
        while True:
            await asyncio.sleep(self.config.metrics_interval_s)
            s = self.snapshot()
            now = time.monotonic()
            rate = (s["stored_samples"] - last_samples) / max(now - last_t, 1e-9)
            last_samples, last_t = s["stored_samples"], now
            log.info("ingest: received %d, stored %d blocks / %d samples (%.0f samples/s), "
                     "duplicates %d, dropped %s, queue %d/%d", s["received"], s["stored_blocks"],
                     s["stored_samples"], rate, s["duplicates"], s["dropped"], s["queue_depth"],
                     s["queue_max"])
            try:
                self.write_metrics()
            except OSError as exc:
                log.warning("could not write metrics file: %s", exc)

    # -- lifecycle ------------------------------------------------------------------------
    def _socket(self) -> socket.socket:
        cfg = self.config
        fam = socket.AF_INET6 if ":" in cfg.host else socket.AF_INET
        sock = socket.socket(fam, socket.SOCK_DGRAM)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, cfg.rcvbuf_bytes)
        sock.bind((cfg.host, cfg.port))
        sock.setblocking(False)
        return sock

    def stop(self) -> None:
        """Ask a running :meth:`serve` to shut down gracefully (thread-safe)."""
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._stop.set)

    async def serve(self, install_signal_handlers: bool = True) -> None:
        """Run until :meth:`stop`, SIGTERM or SIGINT; then stop receiving, write everything
        accepted, send the last acks, roll up summaries and write the metrics file."""
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self.reload_keys()
        sock = self._socket()
        self._sock = sock
        transport, _ = await self._loop.create_datagram_endpoint(
            lambda: _IngestProtocol(self), sock=sock)
        self._transport = transport
        host, port = sock.getsockname()[:2]
        self.address = (host, port)
        if install_signal_handlers:
            for sig in (signal.SIGTERM, signal.SIGINT):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    self._loop.add_signal_handler(sig, self._stop.set)
        decoder = threading.Thread(target=self._decoder, name="ingest-decoder", daemon=True)
        writer = threading.Thread(target=self._writer, name="ingest-writer", daemon=True)
        decoder.start()
        writer.start()
        reporter = asyncio.create_task(self._report())
        log.info("ingest listening on udp %s:%d, %d machine(s), rcvbuf %d bytes", host, port,
                 len(self._keys), sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        self.ready.set()
        try:
            await self._stop.wait()
        finally:
            log.info("ingest shutting down: flushing %d queued datagram(s)", self._queue.qsize())
            self._stopping = True
            sock_stop = getattr(transport, "pause_reading", None)  # not every loop has it
            if sock_stop is not None:
                sock_stop()
            self._queue.put(_STOP)
            await asyncio.to_thread(decoder.join)
            await asyncio.to_thread(writer.join)  # last batch written and acknowledged
            reporter.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reporter
            transport.close()
            await asyncio.to_thread(self._maybe_rollup, True)
            with contextlib.suppress(OSError):
                self.write_metrics()
            log.info("ingest stopped: %s", json.dumps(self.snapshot()))


def new_event_loop() -> asyncio.AbstractEventLoop:
    """uvloop's loop when installed (it receives ≈ 3× more datagrams/s), else asyncio's."""
    try:
        import uvloop
    except ImportError:  # pragma: no cover - uvloop is a dependency
        return asyncio.new_event_loop()
    loop: asyncio.AbstractEventLoop = uvloop.new_event_loop()
    return loop


def serve(db_url: str, config: DaemonConfig | None = None, bus: LiveBus | None = None) -> None:
    """Open the store at ``db_url`` and run the daemon until SIGTERM/SIGINT (blocking)."""
    store = Store.open(db_url)
    try:
        daemon = IngestDaemon(store, config, bus)
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            runner.run(daemon.serve())
    finally:
        if bus is not None:
            bus.close()
        store.close()
