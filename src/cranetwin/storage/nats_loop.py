"""A NATS connection for synchronous code: nats-py on a private event loop in its own thread.

nats-py is asyncio only. The ingest daemon's writer and the API's live view are threads, so
:class:`NatsLoop` runs one event loop in a daemon thread and bridges each call with
:func:`asyncio.run_coroutine_threadsafe` (the future's result is awaited with a deadline). The
connection is made lazily, on the first call, and reconnects by itself afterwards (nats-py's
reconnect loop); while it is down, calls time out and raise
:class:`~cranetwin.errors.StorageUnavailableError`, so callers retry as they do for a database
outage.

Used by :class:`cranetwin.storage.live_nats.NatsBus` (live fan-out) and by the fleet bus
(:mod:`cranetwin.bus`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar
from urllib.parse import urlsplit, urlunsplit

from cranetwin.errors import MissingExtraError, StorageUnavailableError

log = logging.getLogger(__name__)
T = TypeVar("T")


def redact(url: str) -> str:
    """``url`` without a password or token (for logs and messages)."""
    u = urlsplit(url)
    if u.password is None and not u.username:
        return url
    host = u.hostname or ""
    netloc = f"***@{host}" + (f":{u.port}" if u.port else "")
    return urlunsplit((u.scheme, netloc, u.path, u.query, u.fragment))


def nats_module() -> Any:
    """The ``nats`` package (nats-py), or MissingExtraError naming the ``nats`` extra."""
    try:
        import nats
    except ImportError as exc:
        raise MissingExtraError("nats", "the NATS bus") from exc
    return nats


class NatsLoop:
    """One NATS connection served by a private event loop thread.

    Args:
        url: ``nats://host:port`` (credentials in the URL are never logged).
        name: Client name shown by the server (``nats server report connections``).
        connect_timeout_s: Longest wait for the first connection [s].

    Raises:
        MissingExtraError: nats-py is not installed (``cranetwin[nats]``).
    """

    def __init__(self, url: str, name: str = "cranetwin",
                 connect_timeout_s: float = 2.0) -> None:
        self._nats = nats_module()
        self.url = url
        self.name = name
        self.connect_timeout_s = connect_timeout_s
        self.nc: Any = None
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name=f"nats-{name}",
                                        daemon=True)
        self._thread.start()
        self._closed = False

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The private loop (schedule coroutines on it with :meth:`run` or :meth:`submit`)."""
        return self._loop

    async def _connect(self) -> Any:
        if self.nc is not None and not self.nc.is_closed:
            return self.nc

        async def on_error(exc: Exception) -> None:
            log.debug("nats %s: %s", redact(self.url), exc)

        async def on_disconnect() -> None:
            log.warning("nats %s: disconnected; reconnecting", redact(self.url))

        async def on_reconnect() -> None:
            log.warning("nats %s: reconnected", redact(self.url))

        try:
            self.nc = await self._nats.connect(
                servers=[self.url], name=self.name, connect_timeout=self.connect_timeout_s,
                allow_reconnect=True, max_reconnect_attempts=-1, reconnect_time_wait=0.25,
                error_cb=on_error, disconnected_cb=on_disconnect, reconnected_cb=on_reconnect)
        except Exception as exc:
            raise StorageUnavailableError(
                f"NATS at {redact(self.url)} unreachable: {type(exc).__name__}: {exc}") from exc
        return self.nc

    def run(self, fn: Callable[[Any], Awaitable[T]], timeout_s: float) -> T:
        """``await fn(connection)`` on the private loop, from another thread.

        Args:
            fn: Coroutine function of the connected ``nats.aio.client.Client``.
            timeout_s: Deadline of the whole call, connecting included [s].

        Raises:
            StorageUnavailableError: Not connected, the deadline passed, or the connection failed
                (everything nats-py raises that means "the bus is not there now").
            Exception: What ``fn`` raised otherwise (e.g. a JetStream API error).
        """
        if self._closed:
            raise StorageUnavailableError("the NATS connection is closed")

        async def call() -> T:
            nc = await self._connect()
            return await fn(nc)

        fut = asyncio.run_coroutine_threadsafe(call(), self._loop)
        try:
            return fut.result(timeout_s)
        except concurrent.futures.TimeoutError as exc:
            fut.cancel()
            raise StorageUnavailableError(
                f"NATS at {redact(self.url)} did not answer within {timeout_s:.1f} s") from exc
        except StorageUnavailableError:
            raise
        except Exception as exc:
            if is_unavailable(exc, self._nats):
                raise StorageUnavailableError(
                    f"NATS at {redact(self.url)} unavailable: {type(exc).__name__}: "
                    f"{exc}") from exc
            raise

    def submit(self, coro: Awaitable[T]) -> concurrent.futures.Future[T]:
        """Schedule ``coro`` on the private loop without waiting (fire and forget)."""
        async def wrap() -> T:
            return await coro

        return asyncio.run_coroutine_threadsafe(wrap(), self._loop)

    def close(self, timeout_s: float = 2.0) -> None:
        """Drain and close the connection, then stop the loop thread (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        nc = self.nc

        async def shutdown() -> None:
            if nc is not None and not nc.is_closed:
                await nc.close()
            me = asyncio.current_task()
            rest = [t for t in asyncio.all_tasks() if t is not me]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        fut = asyncio.run_coroutine_threadsafe(shutdown(), self._loop)
        try:
            fut.result(timeout_s)
        except Exception as exc:  # closing a broken connection: nothing left to save
            log.debug("nats close: %s", exc)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self._loop.close()


def run_bounded(main: Coroutine[Any, Any, T], cleanup_s: float = 3.0) -> T:
    """``asyncio.run(main)``, except that the tasks ``main`` leaves behind get ``cleanup_s`` [s]
    to end after their cancellation instead of forever: nats-py swallows a cancellation in
    some of its calls while it reconnects, and ``asyncio.run`` would then never return (a
    process that was asked to stop would hang)."""
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    try:
        return loop.run_until_complete(main)
    finally:
        try:
            rest = asyncio.all_tasks(loop)
            for t in rest:
                t.cancel()
            if rest:
                _, left = loop.run_until_complete(asyncio.wait(rest, timeout=cleanup_s))
                if left:
                    log.warning("%d task(s) did not end within %.0f s of their cancellation; "
                                "left behind", len(left), cleanup_s)
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.run_until_complete(loop.shutdown_default_executor())
        finally:
            asyncio.set_event_loop(None)
            loop.close()


def is_unavailable(exc: BaseException, nats: Any) -> bool:
    """Whether a nats-py error means the server is not reachable now (retry later)."""
    errors = nats.errors
    js_errors = nats.js.errors
    transient = (errors.ConnectionClosedError, errors.TimeoutError, errors.NoServersError,
                 errors.ConnectionReconnectingError, errors.StaleConnectionError,
                 errors.OutboundBufferLimitError, errors.NoRespondersError,
                 js_errors.NoStreamResponseError, js_errors.ServiceUnavailableError,
                 asyncio.TimeoutError, ConnectionError, OSError)
    return isinstance(exc, transient)
