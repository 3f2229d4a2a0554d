"""API keys and roles over HTTP: who may call what.

A key is ``ctk_<key_id>_<secret>``; only ``sha256(secret)`` is stored, compared in constant time
(:mod:`cranetwin.service.keys`). Roles are ordered ``viewer < fleet < admin``; a route needing
``fleet`` accepts ``fleet`` and ``admin`` keys. A key is read from ``X-API-Key``,
``Authorization: Bearer``, or the ``key`` query parameter (browser links and websockets), in that
order.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from fastapi.security import APIKeyHeader, APIKeyQuery, HTTPBearer
from starlette.requests import HTTPConnection

from cranetwin.api.errors import ApiError
from cranetwin.service.keys import KEY_PREFIX, ROLES, Role, new_key, split_token, verify

_RANK = {r: i for i, r in enumerate(ROLES)}


@dataclass(frozen=True)
class ApiKey:
    """An authenticated caller.

    Attributes:
        key_id: Public identifier of the key (12 hex digits).
        name: Label given when the key was created.
        role: ``viewer``, ``fleet`` or ``admin``.
    """

    key_id: str
    name: str
    role: Role

    def allows(self, role: Role) -> bool:
        """Whether this key's role is at least ``role``."""
        return _RANK[self.role] >= _RANK[role]


# OpenAPI security schemes (documentation); the actual check is `authenticate`.
header_scheme = APIKeyHeader(name="X-API-Key", auto_error=False,
                             description="API key (`cranetwin keys create --role viewer`)")
bearer_scheme = HTTPBearer(auto_error=False, description="API key as a bearer token")
query_scheme = APIKeyQuery(name="key", auto_error=False,
                           description="API key in the query (browser links, websockets)")


def presented_token(conn: HTTPConnection) -> str | None:
    """The key a request or websocket presents, if any."""
    token = conn.headers.get("x-api-key")
    if token:
        return token.strip()
    auth = conn.headers.get("authorization", "")
    scheme, _, value = auth.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    q = conn.query_params.get("key")
    return q.strip() if q else None


KeyLookup = Callable[[str], tuple[str, str, Role] | None]
"""``key_id -> (secret_hash, name, role)`` of an active key, or None."""


class KeyVerifier:
    """Checks presented tokens against the key store, caching successes for ``ttl_s`` seconds.

    Args:
        lookup: Reads an active key by id (``storage.apikeys``).
        ttl_s: How long a verified key is trusted without a database read [s]; a revoked key stops
            working within this time.
    """

    def __init__(self, lookup: KeyLookup, ttl_s: float = 10.0) -> None:
        self._lookup = lookup
        self._ttl_s = ttl_s
        self._cache: dict[str, tuple[float, ApiKey]] = {}

    def check(self, token: str | None) -> ApiKey:
        """The key of ``token``; raise 401 :class:`ApiError` when missing or unknown."""
        if not token:
            raise ApiError(401, "API key required",
                           "send a key in the X-API-Key header, as 'Authorization: Bearer <key>' "
                           "or as ?key=<key> (create one with `cranetwin keys create`)",
                           headers={"WWW-Authenticate": "Bearer"})
        now = time.monotonic()
        hit = self._cache.get(token)
        if hit is not None and now - hit[0] < self._ttl_s:
            return hit[1]
        parts = split_token(token)
        row = self._lookup(parts[0]) if parts else None
        if parts is None or row is None or not verify(row[0], parts[1]):
            raise ApiError(401, "Invalid API key",
                           "the key is malformed, unknown or revoked (expected ctk_<id>_<secret>)",
                           headers={"WWW-Authenticate": "Bearer"})
        key = ApiKey(key_id=parts[0], name=row[1], role=row[2])
        if len(self._cache) > 10_000:
            self._cache.clear()
        self._cache[token] = (now, key)
        return key

    def forget(self) -> None:
        """Drop the cache (after a key was revoked)."""
        self._cache.clear()


def authorise(key: ApiKey, role: Role) -> ApiKey:
    """``key`` if its role is at least ``role``, else 403."""
    if not key.allows(role):
        raise ApiError(403, "Insufficient role",
                       f"this operation needs a {role!r} key (or higher); yours is {key.role!r}")
    return key


__all__ = ["KEY_PREFIX", "ROLES", "ApiKey", "KeyVerifier", "Role", "authorise", "new_key",
           "presented_token"]
