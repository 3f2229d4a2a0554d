"""Problem JSON (RFC 9457) errors: the one place where failures become HTTP responses.

Every error response of the API has media type ``application/problem+json`` and a body
``{type, title, status, detail}`` (plus ``errors`` for validation failures, one entry per bad
field). Bad input is always a 4xx: request validation → 422 (malformed JSON body → 400), unknown
machine → 404, unusable range → 422, missing key → 401, wrong role → 403, rate limit used up
→ 429 and a full heavy-work queue → 503 (both with ``Retry-After``), an undeclared method → 405
with ``Allow`` listing every method served at the path. cranetwin errors raised
below the API are translated here once: the service's
(:mod:`cranetwin.service.errors`) :class:`~cranetwin.service.errors.NotFoundError` → 404,
:class:`~cranetwin.service.errors.ConflictError` → 409,
:class:`~cranetwin.service.errors.InvalidRequestError` → 422; a
:class:`~cranetwin.errors.TwinError` (too few samples to replay) → 422, a
:class:`~cranetwin.errors.StorageError` → 503.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from cranetwin.api.schemas import Problem
from cranetwin.errors import (
    AnalyticsError,
    CraneTwinError,
    MissingExtraError,
    ModelError,
    PhysicsError,
    ReportError,
    SignalError,
    StorageError,
    TwinError,
)
from cranetwin.service.errors import BusyError, ConflictError, NotFoundError, ServiceError

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"


class ApiError(CraneTwinError):
    """An HTTP-level failure with its status, short title and a detail saying what was expected.

    Attributes:
        status: HTTP status code (4xx for bad input).
        title: Short summary (``"Unknown machine"``).
        detail: What was wrong and what was expected.
        headers: Extra response headers (``WWW-Authenticate`` for 401).
    """

    def __init__(self, status: int, title: str, detail: str,
                 headers: dict[str, str] | None = None) -> None:
        self.status = status
        self.title = title
        self.detail = detail
        self.headers = headers
        super().__init__(f"{status} {title}: {detail}")


def problem(status: int, title: str, detail: str, errors: list[dict[str, Any]] | None = None,
            headers: dict[str, str] | None = None) -> JSONResponse:
    """A problem JSON response."""
    body: dict[str, Any] = {"type": "about:blank", "title": title, "status": status,
                            "detail": detail}
    if errors is not None:
        body["errors"] = errors
    return JSONResponse(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def _clean(err: Any) -> dict[str, Any]:
    loc = [str(x) for x in err.get("loc", ())]
    return {"loc": loc, "msg": str(err.get("msg", "")), "type": str(err.get("type", ""))}


async def _validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError | WebSocketRequestValidationError)
    errors = [_clean(e) for e in exc.errors()]
    if any(e["type"] == "json_invalid" for e in errors):
        return problem(400, "Malformed JSON", "the request body is not valid JSON: "
                       + "; ".join(e["msg"] for e in errors), errors)
    detail = "; ".join(f"{'.'.join(e['loc'])}: {e['msg']}" for e in errors)
    return problem(422, "Invalid request", detail, errors)


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app serves at the request's path (the ``Allow`` of a 405:
    the router names only the first route matching the path, and ``GET`` and ``POST`` of one
    path are two routes)."""
    from fastapi.routing import iter_route_contexts
    from starlette.routing import Match

    methods: set[str] = set()
    for ctx in iter_route_contexts(request.app.routes):
        route_methods = ctx.methods
        if not route_methods:
            continue
        try:
            match, _ = ctx.matches(request.scope)
        except (AttributeError, TypeError, KeyError):
            continue
        if match != Match.NONE:
            methods |= set(route_methods)
    return sorted(methods)


async def _http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    title = {404: "Not found", 405: "Method not allowed"}.get(exc.status_code, "HTTP error")
    headers = dict(exc.headers) if exc.headers else None
    detail = str(exc.detail)
    if exc.status_code == 405:
        allow = allowed_methods(request) or [m.strip() for m in (headers or {}).get(
            "Allow", "").split(",") if m.strip()]
        headers = {**(headers or {}), "Allow": ", ".join(allow)}
        detail = f"{request.method} is not served at {request.url.path}; allowed: " \
            f"{', '.join(allow)}"
    return problem(exc.status_code, title, detail, headers=headers)


async def _api(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return problem(exc.status, exc.title, exc.detail, headers=exc.headers)


def http_status(exc: ServiceError) -> int:
    """The HTTP status of a service error: 404 not found, 409 conflict, 503 busy, else 422."""
    if isinstance(exc, NotFoundError):
        return 404
    if isinstance(exc, BusyError):
        return 503
    if isinstance(exc, ConflictError):
        return 409
    return 422


async def _cranetwin(request: Request, exc: Exception) -> JSONResponse:
    if isinstance(exc, MissingExtraError):
        return problem(501, "Not installed on this server", str(exc))
    if isinstance(exc, BusyError):
        return problem(503, exc.title, exc.detail,
                       headers={"Retry-After": str(max(1, math.ceil(exc.retry_after_s)))})
    if isinstance(exc, ServiceError):
        return problem(http_status(exc), exc.title, exc.detail)
    if isinstance(exc, StorageError):
        log.error("storage error on %s: %s", request.url.path, exc)
        return problem(503, "Storage unavailable", str(exc))
    if isinstance(exc, TwinError | SignalError | PhysicsError):
        return problem(422, "Cannot replay this range", str(exc))
    if isinstance(exc, AnalyticsError | ReportError):
        return problem(422, "Cannot analyse this range", str(exc))
    if isinstance(exc, ModelError):
        return problem(422, "Invalid machine description", str(exc))
    return problem(422, "Unprocessable request", str(exc))


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem(500, "Internal error", "the server failed; the error was logged")


def install_error_handlers(app: FastAPI) -> None:
    """Register the problem-JSON handlers on ``app``."""
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(ApiError, _api)
    app.add_exception_handler(CraneTwinError, _cranetwin)
    app.add_exception_handler(Exception, _unexpected)


_RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before retrying",
                                 "schema": {"type": "integer", "minimum": 1}}}


def _problem_response(description: str, retry_after: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {
        "description": description, "model": Problem,
        "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}}
    if retry_after:
        out["headers"] = _RETRY_AFTER
    return out


PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: _problem_response(desc, status in (429, 503))
    for status, desc in ((400, "Malformed request"), (401, "No or unknown API key"),
                         (403, "The key's role is too low"), (404, "Unknown machine"),
                         (422, "Invalid parameters (range, channel, limits)"),
                         (429, "The key's rate limit is used up (Retry-After)"),
                         (503, "Storage unavailable, or heavy work queue full (Retry-After)"))
}
"""OpenAPI ``responses`` entries for the problem JSON errors every data route may return."""


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """The :data:`PROBLEM_RESPONSES` entries of ``statuses``."""
    return {k: v for k, v in PROBLEM_RESPONSES.items() if k in statuses}
