"""Live fan-out of newly stored sample blocks to the API's live view.

One small interface, :class:`LiveBus` (``publish`` from the ingest daemon after commit,
``subscribe`` from the API), with three transports chosen by URL in :func:`open_bus`:

* ``memory://`` — :class:`InProcessBus`, when daemon and API share a process (embedded default);
  subscribers get the :class:`~cranetwin.samples.SampleBlock` itself.
* ``postgresql://…`` — :class:`PostgresBus`, ``NOTIFY``/``LISTEN`` on the database server.
* ``redis://host:port`` — :class:`RedisBus`, Redis ``PUBLISH``/``SUBSCRIBE`` (redis-py, the
  ``redis`` extra).
* ``nats://host:port`` — :class:`~cranetwin.storage.live_nats.NatsBus`, core NATS subjects
  (nats-py, the ``nats`` extra).

Across processes only a :class:`BlockNote` travels (machine, seq, time span, sample count); the
subscriber reads the samples from storage. A slow subscriber never slows ingest: its queue is
bounded and the oldest notes are dropped (counted in ``Subscription.dropped``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import urlsplit

from cranetwin.errors import MissingExtraError, StorageError, StorageUnavailableError
from cranetwin.samples import SampleBlock

CHANNEL = "cranetwin_blocks"
log = logging.getLogger(__name__)


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
        _psycopg()  # fail at open_bus, not at the first publish
        self._conninfo = url.replace("postgresql+psycopg://", "postgresql://", 1)
        self._channel = channel
        self._maxsize = maxsize
        self._pub: Any = None
        self._lock = threading.Lock()

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        psycopg = _psycopg()
        with self._lock:
            if self._pub is None or self._pub.closed:
                self._pub = psycopg.connect(self._conninfo, autocommit=True)
            for p in _payloads(blocks):
                self._pub.execute("SELECT pg_notify(%s, %s)", (self._channel, p))

    def subscribe(self) -> Subscription:
        conn = _psycopg().connect(self._conninfo, autocommit=True)
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


def _psycopg() -> Any:
    """The psycopg module, or MissingExtraError naming the ``postgres`` extra."""
    try:
        import psycopg
    except ImportError as exc:
        raise MissingExtraError("postgres", "the PostgreSQL live bus") from exc
    return psycopg


class RedisBus:
    """Redis ``PUBLISH``/``SUBSCRIBE`` through redis-py (daemon and API in separate processes).

    Publishing uses redis-py's connection pool (it reconnects after a lost connection); each
    subscription has its own pub/sub connection read by a background thread.

    Args:
        host, port: Redis server (127.0.0.1:6379 by default).
        channel: Pub/sub channel name.
        maxsize: Notes buffered per subscriber before the oldest are dropped.

    Raises:
        MissingExtraError: redis-py is not installed (``cranetwin[redis]``).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 6379, channel: str = CHANNEL,
                 maxsize: int = 10_000) -> None:
        try:
            import redis
        except ImportError as exc:
            raise MissingExtraError("redis", "the Redis live bus") from exc
        self._redis = redis
        self._client = redis.Redis(host=host, port=port, socket_timeout=5,
                                   socket_connect_timeout=5)
        self._channel = channel
        self._maxsize = maxsize
        self._readers: list[tuple[_ThreadSubscription, threading.Thread]] = []

    def publish(self, blocks: Sequence[SampleBlock]) -> None:
        """Publish notes of ``blocks`` (one pipelined round trip).

        Raises:
            StorageUnavailableError: Redis cannot be reached.
            StorageError: Redis refused a command.
        """
        pipe = self._client.pipeline(transaction=False)
        for p in _payloads(blocks, limit=64_000):
            pipe.publish(self._channel, p)
        with self._translated():
            pipe.execute()

    def subscribe(self) -> Subscription:
        """A subscription that receives every note published after this call returns.

        Raises:
            StorageUnavailableError: Redis cannot be reached.
        """
        pubsub = self._client.pubsub()
        with self._translated():
            pubsub.subscribe(self._channel)
            confirmed = pubsub.get_message(timeout=5)  # the server has registered us
        if not confirmed or confirmed["type"] != "subscribe":
            pubsub.close()
            raise StorageUnavailableError(f"redis did not confirm SUBSCRIBE: {confirmed!r}")
        sub = _ThreadSubscription(self._maxsize)

        def run() -> None:
            try:
                while not sub._stop.is_set():
                    msg = pubsub.get_message(timeout=0.2)
                    if msg is not None and msg["type"] == "message":
                        for note in _notes(msg["data"]):
                            sub.put(note)
            except (self._redis.RedisError, OSError) as exc:
                log.warning("redis subscription ended: %s", exc)
            finally:
                pubsub.close()

        reader = threading.Thread(target=run, name="redis-sub", daemon=True)
        reader.start()
        self._readers.append((sub, reader))
        return sub

    @contextlib.contextmanager
    def _translated(self) -> Iterator[None]:
        """redis-py's errors as storage errors (connection problems: unavailable)."""
        try:
            yield
        except (self._redis.ConnectionError, self._redis.TimeoutError) as exc:
            raise StorageUnavailableError(f"redis unreachable: {exc}") from exc
        except self._redis.RedisError as exc:
            raise StorageError(f"redis error: {exc}") from exc

    def close(self) -> None:
        """End every subscription's reader, then release the connections."""
        for sub, reader in self._readers:
            sub.close()
            reader.join(timeout=2.0)
        self._readers.clear()
        self._client.close()


def open_bus(url: str = "memory://") -> LiveBus:
    """The bus for ``url``: ``memory://``, ``postgresql[+psycopg]://…``, ``redis://host:port``
    or ``nats://host:port``.

    Raises:
        StorageError: Unknown scheme.
        MissingExtraError: The transport's optional dependency is not installed.
    """
    scheme = urlsplit(url).scheme
    if scheme == "memory":
        return InProcessBus()
    if scheme.startswith("postgresql"):
        return PostgresBus(url)
    if scheme == "redis":
        u = urlsplit(url)
        return RedisBus(u.hostname or "127.0.0.1", u.port or 6379)
    if scheme == "nats":
        from cranetwin.storage.live_nats import NatsBus

        return NatsBus(url)
    raise StorageError(f"unknown live bus {url!r}; expected memory://, postgresql://…, "
                       "redis://host:port or nats://host:port")
