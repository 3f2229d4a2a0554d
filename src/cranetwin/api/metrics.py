"""Request counting of the HTTP API into the service's Prometheus metrics."""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable

from fastapi import Request, Response

from cranetwin.service.metrics import Metrics


async def count_request(metrics: Metrics, request: Request,
                        call_next: Callable[[Request], Awaitable[Response]]) -> Response:
    """Count requests and their latency per route template (not per raw path)."""
    start = time.perf_counter()
    response = await call_next(request)
    matched = request.scope.get("route")
    route = str(getattr(matched, "path", "unmatched"))
    metrics.requests.labels(request.method, route, str(response.status_code)).inc()
    metrics.latency.labels(route).observe(time.perf_counter() - start)
    return response
