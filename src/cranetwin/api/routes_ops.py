"""Service routes: health (no key) and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response

from cranetwin import __version__
from cranetwin.api.deps import CurrentKey, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.api.schemas import Health

router = APIRouter(tags=["service"])


@router.get("/healthz", response_model=Health, summary="Liveness (no key needed)")
def healthz() -> Health:
    """``{"status": "ok", "version": ...}`` while the service runs."""
    return Health(status="ok", version=__version__)


@router.get("/metrics", summary="Prometheus metrics",
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus text exposition format 0.0.4"},
                       **{k: v for k, v in PROBLEM_RESPONSES.items() if k in (401, 403)}},
            response_class=Response)
def metrics(key: CurrentKey, services: ServicesDep) -> Response:
    """Request counts and latencies per route, live clients, replay cache and worker lag."""
    services.refresh_gauges()
    return Response(services.metrics.render(),
                    media_type="text/plain; version=0.0.4; charset=utf-8")
