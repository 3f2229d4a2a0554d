"""The application factory: ``create_app(settings)``."""

from __future__ import annotations

import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from cranetwin import __version__
from cranetwin.api import (
    routes_aemp,
    routes_alarms,
    routes_data,
    routes_docs,
    routes_live,
    routes_machines,
    routes_ops,
    routes_schedules,
    routes_session,
)
from cranetwin.api.errors import install_error_handlers
from cranetwin.api.limits import RateLimitMiddleware
from cranetwin.api.metrics import count_request
from cranetwin.api.services import Services
from cranetwin.settings import Settings, load_settings

log = logging.getLogger(__name__)

DESCRIPTION = """
Camera-less digital twin of hydraulic cranes: stored sensor samples, their replay through the
machine's physics (positions, cylinder forces, joint loads, payload), load history, events and
ISO 15143-3 fleet snapshots.

**Keys.** Every route except `/healthz` needs an API key (`cranetwin keys create --role viewer`)
in `X-API-Key`, as `Authorization: Bearer <key>`, or as `?key=` (API clients). Browsers sign in
once (`POST /api/v1/session`) and then carry only an HttpOnly session cookie.
Roles: viewer < fleet < admin. No key → 401, lower role → 403.

**Units.** SI throughout: time [s since the Unix epoch] (parameters `from`/`to` also accept
ISO 8601), lengths [m], angles [rad], forces [N], moments [N·m], pressures [Pa], masses [kg].

**Errors.** `application/problem+json` with `type`, `title`, `status`, `detail` (and `errors` for
validation). Bad input is always a 4xx.
"""


_KEY_PARAM = re.compile(r"(?i)([?&;](?:k|%6b)(?:e|%65)(?:y|%79)=)[^&;#\s\"]*")


def redact_keys(text: str) -> str:
    """``text`` with the value of every ``key=`` query parameter replaced by ``***`` (also when
    the name is percent-encoded, e.g. ``%6Bey=``)."""
    return _KEY_PARAM.sub(r"\1***", text)


class RedactKeysFilter(logging.Filter):
    """Rewrites log records so that API keys passed as ``?key=...`` never reach a log line.

    Installed on uvicorn's loggers (:data:`ACCESS_LOGGERS`) by :func:`install_log_redaction`;
    it rewrites the record's string arguments (uvicorn passes the request path with its query
    string as one) and its message, and never drops a record.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact_keys(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact_keys(a) if isinstance(a, str) else a
                                for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: redact_keys(v) if isinstance(v, str) else v
                           for k, v in record.args.items()}
        return True


ACCESS_LOGGERS = ("uvicorn.access", "uvicorn.error")
"""Loggers that see request paths with their query string: uvicorn's access log, and its error
log, where websocket connections are logged (``"WebSocket /api/v1/live?key=..." [accepted]``)."""


def install_log_redaction() -> None:
    """Add :class:`RedactKeysFilter` to the access loggers, once (idempotent). Logger filters
    survive uvicorn's logging configuration, which replaces handlers only."""
    for name in ACCESS_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactKeysFilter) for f in logger.filters):
            logger.addFilter(RedactKeysFilter())


def create_app(settings: Settings | None = None, *, bus: object = None) -> FastAPI:
    """Build the FastAPI app; the lifespan opens the store (and starts the twin worker when
    ``settings.worker_in_process``), and closes both on shutdown.

    Args:
        settings: The settings; read from the environment (``CRANETWIN_*``) when None.
        bus: The live bus of an ingest daemon running in the same process
            (``cranetwin.storage.live.InProcessBus``); None to use ``settings.live_bus_url``.
    """
    cfg = settings if settings is not None else load_settings(Settings)
    install_log_redaction()  # API keys in ?key= never reach the access log

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = Services.open(cfg, bus)
        app.state.services = services
        await services.start()
        log.info("cranetwin API serving %s", cfg.database_url)
        try:
            yield
        finally:
            await services.close()
            app.state.services = None

    # FastAPI's own /docs and /redoc load their assets from a CDN (blank without internet):
    # routes_docs serves Swagger UI from the installed swagger-ui-bundle package instead
    app = FastAPI(title="cranetwin", version=__version__, description=DESCRIPTION,
                  lifespan=lifespan, docs_url=None, redoc_url=None)
    app.state.settings = cfg
    app.state.services = None
    install_error_handlers(app)

    @app.middleware("http")
    async def _metrics(request, call_next):  # type: ignore[no-untyped-def]
        services = request.app.state.services
        if services is None:
            return await call_next(request)
        return await count_request(services.metrics, request, call_next)

    # outermost: a request over its key's rate is refused before anything else runs
    app.add_middleware(RateLimitMiddleware)

    for module in (routes_ops, routes_session, routes_machines, routes_data, routes_aemp,
                   routes_alarms, routes_live, routes_schedules):
        app.include_router(module.router)
    try:
        from cranetwin.api import routes_web
    except ImportError as exc:  # the web front end is optional
        log.warning("web routes not available: %s", exc)
    else:
        app.include_router(routes_web.router)
    app.include_router(routes_docs.router)
    app.include_router(routes_alarms.fleet_router)
    _register_problem_schema(app)
    return app


def _register_problem_schema(app: FastAPI) -> None:
    """Make sure ``#/components/schemas/Problem`` exists in the OpenAPI document."""
    from fastapi.openapi.utils import get_openapi

    from cranetwin.api.openapi import make_truthful
    from cranetwin.api.schemas import Problem

    def openapi() -> dict[str, object]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version, description=app.description,
                             routes=app.routes)
        comps = schema.setdefault("components", {}).setdefault("schemas", {})
        comps.setdefault("Problem", Problem.model_json_schema(ref_template=
                                                              "#/components/schemas/{model}"))
        make_truthful(schema, app.state.settings)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
