"""The OpenAPI document, made to say what the server does.

FastAPI documents each route's declared responses and parameter bounds; these additions make
the document true for what is decided elsewhere:

* every operation that needs a key may answer 401 (no or unknown key), 429 (its rate limit used
  up, ``Retry-After``) and 503 (storage unavailable, heavy work queue full, ``Retry-After``):
  :mod:`cranetwin.api.limits` and :mod:`cranetwin.api.errors` apply them to every keyed route;
* every operation on ``/api/v1/machines/{machine_id}/…`` may answer 404 (unknown machine) and,
  when it takes parameters, 422;
* parameter bounds that are settings (``max_samples_limit``, ``max_history_points``,
  ``max_twin_rate_hz``) are documented with the running server's values, so an input the schema
  permits is not refused for being too large.

A 405 (a method the path does not serve, with ``Allow``) is not an operation's response and
cannot be written into the document; ``tests/test_api_openapi.py`` checks it for every path.
"""

from __future__ import annotations

from typing import Any

from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.settings import Settings

_METHODS = ("get", "put", "post", "delete", "patch")


def _bounds(settings: Settings) -> dict[tuple[str, str], float]:
    """(path suffix, query parameter) → its largest accepted value."""
    return {("/samples", "limit"): settings.max_samples_limit,
            ("/history", "max_points"): settings.max_history_points,
            ("/twin", "rate_hz"): settings.max_twin_rate_hz}


def make_truthful(schema: dict[str, Any], settings: Settings) -> dict[str, Any]:
    """Add the responses and bounds of the module docstring to ``schema`` (in place)."""
    bounds = _bounds(settings)
    for path, item in schema.get("paths", {}).items():
        for method in _METHODS:
            op = item.get(method)
            if op is None:
                continue
            responses = op.setdefault("responses", {})
            statuses: list[int] = []
            if op.get("security"):
                statuses += [401, 429, 503]
            if path.startswith("/api/v1/machines/{machine_id}"):
                statuses.append(404)
                if op.get("parameters") or op.get("requestBody"):
                    statuses.append(422)
            for status in statuses:
                responses.setdefault(str(status), _openapi_response(status))
            for param in op.get("parameters", []):
                for (suffix, name), top in bounds.items():
                    if path.endswith(suffix) and param.get("name") == name:
                        _set_maximum(param.setdefault("schema", {}), top)
    return schema


def _openapi_response(status: int) -> dict[str, Any]:
    entry = PROBLEM_RESPONSES[status]
    return {k: v for k, v in entry.items() if k != "model"}


def _set_maximum(schema: dict[str, Any], top: float) -> None:
    """Lower the ``maximum`` of a parameter schema (also inside ``anyOf``) to ``top``."""
    for sub in schema.get("anyOf", [schema]):
        if sub.get("type") in ("integer", "number"):
            sub["maximum"] = min(float(sub.get("maximum", top)), top) \
                if sub.get("type") == "number" else int(min(sub.get("maximum", top), top))
