"""Service limits over HTTP: a token bucket per key, and heavy work off the request threads.

**Rate limit.** Every authenticated request takes tokens from its key's bucket: a cheap request
(machine list, history, events, …) 1, a heavy one (twin replay, analytics, report, export,
export.html: :data:`HEAVY_ROUTES`) ``rate_heavy_cost``. A bucket holds at most
``rate_<role>_burst`` tokens and gets ``rate_<role>_per_s`` back per second, per role
(viewer < fleet < admin). A request that finds too few tokens is answered 429 problem JSON
with ``Retry-After`` [whole seconds until enough tokens are back] and counted in
``cranetwin_http_refused_total{reason="rate_limit"}``. A key verified in the last seconds is
charged by :class:`RateLimitMiddleware` before any routing, so that refusing costs little, and
its refusal is sent after min(``Retry-After``, ``rate_limit_delay_s``) (a wait that costs no
CPU: a client hammering from N threads then gets at most about N refusals a second, instead of
hundreds that each cost the event loop its time, and other keys' requests with it); any other
by the routes' key dependency once the key is checked. The browser's sessions of a key
share the key's bucket (signing in again gives no fresh one). The web routes' in-process calls
to the API (scene, export.html) carry a per-process token and are not charged again: the outer
request paid.

Hand-written rather than the ``limits`` package: ``limits`` offers fixed, moving and sliding
windows (no token bucket, so no burst separate from the rate and no exact time to the next
token for ``Retry-After``), and its in-memory storage is per process, as this is; the bucket is
twenty lines.

**Heavy work.** Routes that replay or render run their work on the
:class:`~cranetwin.service.heavy.HeavyPool` (``heavy_workers`` threads, ``heavy_queue`` waiting)
instead of the thread pool that serves cheap requests, so a machine list never waits behind a
replay; a full pool answers 503 with ``Retry-After`` (``reason="busy"``).
"""

from __future__ import annotations

import asyncio
import math
import re
import secrets
import threading
import time
import weakref
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from starlette.requests import HTTPConnection
from starlette.types import ASGIApp, Receive, Scope, Send

from cranetwin.api.auth import ApiKey, Role
from cranetwin.api.errors import ApiError, problem
from cranetwin.service.errors import BusyError
from cranetwin.settings import Settings

if TYPE_CHECKING:
    from cranetwin.api.services import Services

T = TypeVar("T")

INTERNAL_HEADER = "x-cranetwin-internal"
"""Header of the web routes' in-process API calls (its value: :attr:`RateLimiter.internal_token`).
"""


@dataclass(frozen=True)
class Rate:
    """A token bucket's refill rate [tokens/s] and size [tokens]."""

    per_s: float
    burst: float


class TokenBucket:
    """``burst`` tokens at most, ``per_s`` back per second; starts full.

    Args:
        rate: Refill rate and size.
        now: The clock's time at creation [s].
    """

    def __init__(self, rate: Rate, now: float) -> None:
        self.rate = rate
        self.tokens = rate.burst
        self.updated = now

    def take(self, cost: float, now: float) -> float:
        """Take ``cost`` tokens (at most the bucket's size) if there are that many.

        Returns:
            0.0 when taken, else how long until there are enough [s] (nothing taken).
        """
        r = self.rate
        self.tokens = min(r.burst, self.tokens + (now - self.updated) * r.per_s)
        self.updated = now
        cost = min(cost, r.burst)
        if self.tokens >= cost:
            self.tokens -= cost
            return 0.0
        return (cost - self.tokens) / r.per_s


class RateLimiter:
    """Token buckets per key (see module docstring).

    Args:
        rates: Rate of each role.
        heavy_cost: Tokens of a heavy request (a cheap one costs 1).
        clock: Monotonic time [s].
        max_keys: Buckets kept; beyond, the fullest-by-now (longest unused) are dropped.
    """

    def __init__(self, rates: dict[Role, Rate], heavy_cost: float,
                 clock: Callable[[], float] = time.monotonic, max_keys: int = 100_000) -> None:
        self.rates = rates
        self.heavy_cost = heavy_cost
        self.internal_token = secrets.token_urlsafe(24)
        self._clock = clock
        self._max_keys = max_keys
        self._buckets: dict[str, TokenBucket] = {}
        self._lock = threading.Lock()

    @classmethod
    def from_settings(cls, s: Settings) -> RateLimiter:
        """The limiter of the ``rate_*`` settings."""
        return cls({"viewer": Rate(s.rate_viewer_per_s, s.rate_viewer_burst),
                    "fleet": Rate(s.rate_fleet_per_s, s.rate_fleet_burst),
                    "admin": Rate(s.rate_admin_per_s, s.rate_admin_burst)}, s.rate_heavy_cost)

    def take(self, key_id: str, role: Role, heavy: bool) -> float:
        """Charge one request of key ``key_id``: 0.0 if admitted, else seconds to wait."""
        now = self._clock()
        with self._lock:
            bucket = self._buckets.get(key_id)
            if bucket is None or bucket.rate != self.rates[role]:
                if len(self._buckets) >= self._max_keys:
                    oldest = sorted(self._buckets, key=lambda k: self._buckets[k].updated)
                    for k in oldest[: self._max_keys // 10 + 1]:
                        del self._buckets[k]
                bucket = self._buckets[key_id] = TokenBucket(self.rates[role], now)
            return bucket.take(self.heavy_cost if heavy else 1.0, now)


HEAVY_ROUTES = re.compile(r"^/api/v1/machines/[^/]+/(twin|analytics|report|export|export\.html)$")
"""Paths of the heavy requests (replays, reports, exports): they cost ``rate_heavy_cost``."""

_CHARGED = "cranetwin.charged"
"""Scope entry marking a request the middleware has charged already."""


def is_heavy(path: str) -> bool:
    """Whether a request of ``path`` is heavy (:data:`HEAVY_ROUTES`)."""
    return HEAVY_ROUTES.match(path) is not None


def admit(services: Services, conn: HTTPConnection, key: ApiKey) -> None:
    """Charge ``key`` for this request (once: not again after :class:`RateLimitMiddleware`).

    Raises:
        ApiError: 429 with ``Retry-After`` when its bucket holds too few tokens.
    """
    limiter = services.limiter
    if limiter is None or conn.scope.get(_CHARGED) or \
            conn.headers.get(INTERNAL_HEADER) == limiter.internal_token:
        return
    conn.scope[_CHARGED] = True
    heavy = is_heavy(conn.url.path)
    wait_s = limiter.take(key.key_id, key.role, heavy)
    if wait_s > 0:
        services.metrics.refused.labels("rate_limit", key.role).inc()
        retry = max(1, math.ceil(wait_s))
        raise ApiError(429, "Too many requests",
                       f"this key's {key.role} rate limit is used up; retry in {retry} s "
                       f"({'a heavy' if heavy else 'a'} request costs "
                       f"{limiter.heavy_cost if heavy else 1:g} of its "
                       f"{limiter.rates[key.role].burst:g} tokens, "
                       f"{limiter.rates[key.role].per_s:g} come back per second)",
                       headers={"Retry-After": str(retry)})


class RateLimitMiddleware:
    """Charges requests of keys verified recently (:meth:`KeyVerifier.peek`) before any routing,
    and answers a refused one at once: a client ignoring ``Retry-After`` costs the server
    little more than parsing its request. Requests of keys not verified recently are charged by
    the routes' key dependency (:func:`admit`) after their key is checked."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            services = getattr(scope["app"].state, "services", None)
            if services is not None and services.limiter is not None:
                conn = HTTPConnection(scope)
                key = services.keys.peek(conn)
                if key is not None:
                    try:
                        admit(services, conn, key)
                    except ApiError as exc:
                        retry = float((exc.headers or {}).get("Retry-After", "1"))
                        await asyncio.sleep(min(retry, services.settings.rate_limit_delay_s))
                        await problem(exc.status, exc.title, exc.detail,
                                      headers=exc.headers)(scope, receive, send)
                        return
        await self.app(scope, receive, send)


def _busy(services: Services, key: ApiKey | None, exc: BusyError) -> BusyError:
    services.metrics.refused.labels("busy", key.role if key is not None else "-").inc()
    return exc


async def run_heavy(services: Services, key: ApiKey | None, fn: Callable[..., T],
                    *args: Any, process_fn: Callable[..., T] | None = None) -> T:
    """``fn(*args)`` run on the heavy pool (``process_fn(*args)`` in a worker process when the
    pool has them), awaited (``key``: the caller, for the metric).

    Raises:
        BusyError: The pool is full (HTTP 503 with ``Retry-After``).
    """
    try:
        fut = services.heavy.submit(fn, *args, process_fn=process_fn)
    except BusyError as exc:
        raise _busy(services, key, exc) from None
    return await asyncio.wrap_future(fut)


async def stream_heavy(services: Services, key: ApiKey, start: Callable[[], T],
                       body: Callable[[T], Iterator[bytes]]) -> tuple[T, AsyncIterator[bytes]]:
    """A streamed result made on the heavy pool under one admission: ``start()`` (checks and
    opens the result) and then each chunk of ``body(result)``, each on a heavy thread.

    Returns:
        ``start()``'s result and the chunks as an async iterator (the admission is given back
        when it ends, fails or is closed).

    Raises:
        BusyError: The pool is full (HTTP 503 with ``Retry-After``).
    """
    try:
        lease = services.heavy.lease()
    except BusyError as exc:
        raise _busy(services, key, exc) from None
    try:
        result = await asyncio.wrap_future(lease.submit(start))
    except BaseException:
        lease.release()
        raise
    chunks = body(result)

    async def stream() -> AsyncIterator[bytes]:
        try:
            while True:
                chunk = await asyncio.wrap_future(lease.submit(next, chunks, None))
                if chunk is None:
                    return
                yield chunk
        finally:
            lease.release()

    gen = stream()
    weakref.finalize(gen, lease.release)  # a stream never started gives its admission back too
    return result, gen
