"""Live fan-out of newly stored sample blocks to the API's live view.

One small interface, :class:`LiveBus` (``publish`` from the ingest daemon after commit,
``subscribe`` from the API), with three transports chosen by URL in :func:`open_bus`:

* ``memory://`` — :class:`InProcessBus`, when daemon and API share a process (embedded default);
  subscribers get the :class:`~cranetwin.samples.SampleBlock` itself.
* ``postgresql://…`` — :class:`PostgresBus`, ``NOTIFY``/``LISTEN`` on the database server.
* ``redis://host:port`` — :class:`RedisBus`, Redis ``PUBLISH``/``SUBSCRIBE`` (tiny RESP client).

Across processes only a :class:`BlockNote` travels (machine, seq, time span, sample count); the
subscriber reads the samples from storage. A slow subscriber never slows ingest: its queue is
bounded and the oldest notes are dropped (counted in ``Subscription.dropped``).
"""

from __future__ import annotations

import contextlib
import json
import queue
import socket
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import urlsplit

from cranetwin.errors import StorageError
from cranetwin.samples import SampleBlock

CHANNEL = "cranetwin_blocks"


@dataclass(frozen=True)
class BlockNote:
    """A newly stored block.

    Attributes:
        machine_id: Machine identifier; seq: datagram sequence number.
        t0_ns, t_end_ns: First and last sample time [ns since the epoch, machine clock].
        n: Number of samples.
        block: The samples themselves (in-process bus only; None across processes).
    """

    machine_id: str
    seq: int
    t0_ns: int
    t_end_ns: int
    n: int
    block: SampleBlock | None = None

    @classmethod
    def of(cls, b: SampleBlock, with_block: bool = False) -> BlockNote:
        return cls(b.machine_id, b.seq, b.t0_ns, b.t_end_ns, b.n, b if with_block else None)

    def to_json(self) -> list[Any]:
        return [self.machine_id, self.seq, self.t0_ns, self.t_end_ns, self.n]


class Subscription(Protocol):
    """A subscriber's end: poll notes, then close."""

    dropped: int

    def get(self, timeout: float | None = None) -> BlockNote | None:
        """Next note, or None after ``timeout`` seconds without one."""

    def close(self) -> None:
        """Stop receiving."""


class LiveBus(Protocol):
    """Publish newly stored blocks; subscribe to them."""

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        """Announce blocks that were just committed (never raises on a subscriber's behalf)."""

    def subscribe(self) -> Subscription:
        """A new subscription receiving every block published from now on."""

    def close(self) -> None:
        """Release connections."""


class _QueueSubscription:
    def __init__(self, maxsize: int, on_close: Any = None) -> None:
        self._q: queue.Queue[BlockNote] = queue.Queue(maxsize)
        self._on_close = on_close
        self.dropped = 0

    def put(self, note: BlockNote) -> None:
        while True:
            try:
                self._q.put_nowait(note)
                return
            except queue.Full:
                try:
                    self._q.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def get(self, timeout: float | None = None) -> BlockNote | None:
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        if self._on_close is not None:
            self._on_close(self)


class InProcessBus:
    """Fan-out inside one process; subscribers receive the blocks themselves.

    Args:
        maxsize: Notes buffered per subscriber before the oldest are dropped.
    """

    def __init__(self, maxsize: int = 10_000) -> None:
        self._subs: list[_QueueSubscription] = []
        self._lock = threading.Lock()
        self._maxsize = maxsize

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        with self._lock:
            subs = list(self._subs)
        for b in blocks:
            note = BlockNote.of(b, with_block=True)
            for s in subs:
                s.put(note)

    def subscribe(self) -> Subscription:
        sub = _QueueSubscription(self._maxsize, self._unsubscribe)
        with self._lock:
            self._subs.append(sub)
        return sub

    def _unsubscribe(self, sub: _QueueSubscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def close(self) -> None:
        with self._lock:
            self._subs.clear()


def _payloads(blocks: Sequence[SampleBlock], limit: int = 7000) -> list[str]:
    """JSON arrays of notes, each below ``limit`` bytes (PostgreSQL's NOTIFY caps at 8000)."""
    out: list[str] = []
    cur: list[str] = []
    size = 2
    for b in blocks:
        item = json.dumps(BlockNote.of(b).to_json(), separators=(",", ":"))
        if cur and size + len(item) + 1 > limit:
            out.append("[" + ",".join(cur) + "]")
            cur, size = [], 2
        cur.append(item)
        size += len(item) + 1
    if cur:
        out.append("[" + ",".join(cur) + "]")
    return out


def _notes(payload: str | bytes) -> list[BlockNote]:
    return [BlockNote(str(m), int(s), int(a), int(b), int(n))
            for m, s, a, b, n in json.loads(payload)]


class _ThreadSubscription(_QueueSubscription):
    """Queue filled by a background reader thread."""

    def __init__(self, maxsize: int) -> None:
        super().__init__(maxsize)
        self._stop = threading.Event()

    def close(self) -> None:
        self._stop.set()


class PostgresBus:
    """``NOTIFY``/``LISTEN`` on a PostgreSQL server (daemon and API in separate processes).

    Args:
        url: ``postgresql[+psycopg]://user@host:port/db``.
        channel: Notification channel name.
    """

    def __init__(self, url: str, channel: str = CHANNEL, maxsize: int = 10_000) -> None:
        self._conninfo = url.replace("postgresql+psycopg://", "postgresql://", 1)
        self._channel = channel
        self._maxsize = maxsize
        self._pub: Any = None
        self._lock = threading.Lock()

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        import psycopg

        with self._lock:
            if self._pub is None or self._pub.closed:
                self._pub = psycopg.connect(self._conninfo, autocommit=True)
            for p in _payloads(blocks):
                self._pub.execute("SELECT pg_notify(%s, %s)", (self._channel, p))

    def subscribe(self) -> Subscription:
        import psycopg

        conn = psycopg.connect(self._conninfo, autocommit=True)
        conn.execute(f'LISTEN "{self._channel}"')
        sub = _ThreadSubscription(self._maxsize)

        def run() -> None:
            try:
                while not sub._stop.is_set():
                    for n in conn.notifies(timeout=0.2, stop_after=1):
                        for note in _notes(n.payload):
                            sub.put(note)
            finally:
                conn.close()

        threading.Thread(target=run, name="pg-listen", daemon=True).start()
        return sub

    def close(self) -> None:
        with self._lock:
            if self._pub is not None:
                self._pub.close()
                self._pub = None


def _resp(*parts: bytes) -> bytes:
    out = b"*%d\r\n" % len(parts)
    for p in parts:
        out += b"$%d\r\n%s\r\n" % (len(p), p)
    return out


class _RespReader:
    """Minimal RESP2 reader (integers, bulk strings, arrays, simple strings, errors)."""

    def __init__(self, sock: socket.socket) -> None:
        self._f = sock.makefile("rb")

    def read(self) -> Any:
        line = self._f.readline()
        if not line:
            raise ConnectionError("redis closed the connection")
        kind, rest = line[:1], line[1:-2]
        if kind == b"+":
            return rest
        if kind == b"-":
            raise StorageError(f"redis error: {rest.decode(errors='replace')}")
        if kind == b":":
            return int(rest)
        if kind == b"$":
            n = int(rest)
            return None if n < 0 else self._f.read(n + 2)[:-2]
        if kind == b"*":
            return [self.read() for _ in range(int(rest))]
        raise StorageError(f"unexpected redis reply {line!r}")


class RedisBus:
    """Redis ``PUBLISH``/``SUBSCRIBE`` (daemon and API in separate processes).

    Args:
        host, port: Redis server (127.0.0.1:6379 by default).
        channel: Pub/sub channel name.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 6379, channel: str = CHANNEL,
                 maxsize: int = 10_000) -> None:
        self._addr = (host, port)
        self._channel = channel.encode()
        self._maxsize = maxsize
        self._pub: socket.socket | None = None
        self._reader: _RespReader | None = None
        self._lock = threading.Lock()

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        with self._lock:
            if self._pub is None:
                self._pub = socket.create_connection(self._addr, timeout=5)
                self._reader = _RespReader(self._pub)
            assert self._reader is not None
            payloads = _payloads(blocks, limit=64_000)
            self._pub.sendall(b"".join(_resp(b"PUBLISH", self._channel, p.encode())
                                       for p in payloads))
            for _ in payloads:
                self._reader.read()

    def subscribe(self) -> Subscription:
        sock = socket.create_connection(self._addr, timeout=5)
        sock.sendall(_resp(b"SUBSCRIBE", self._channel))
        reader = _RespReader(sock)
        reader.read()  # subscribe confirmation
        sock.settimeout(None)  # blocking reads; close() shuts the socket down to end them
        sub = _ThreadSubscription(self._maxsize)

        def stop() -> None:
            sub._stop.set()
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

        sub.close = stop  # type: ignore[method-assign]

        def run() -> None:
            try:
                while not sub._stop.is_set():
                    msg = reader.read()
                    if isinstance(msg, list) and msg and msg[0] == b"message":
                        for note in _notes(msg[2]):
                            sub.put(note)
            except (OSError, ConnectionError):
                pass
            finally:
                sock.close()

        threading.Thread(target=run, name="redis-sub", daemon=True).start()
        return sub

    def close(self) -> None:
        with self._lock:
            if self._pub is not None:
                self._pub.close()
                self._pub = None


def open_bus(url: str = "memory://") -> LiveBus:
    """The bus for ``url``: ``memory://``, ``postgresql[+psycopg]://…`` or ``redis://host:port``.

    Raises:
        StorageError: Unknown scheme.
    """
    scheme = urlsplit(url).scheme
    if scheme == "memory":
        return InProcessBus()
    if scheme.startswith("postgresql"):
        return PostgresBus(url)
    if scheme == "redis":
        u = urlsplit(url)
        return RedisBus(u.hostname or "127.0.0.1", u.port or 6379)
    raise StorageError(f"unknown live bus {url!r}; expected memory://, postgresql://… or "
                       "redis://host:port")
