"""API keys and roles over HTTP: who may call what.

A key is ``ctk_<key_id>_<secret>``; only ``sha256(secret)`` is stored, compared in constant time
(:mod:`cranetwin.service.keys`). Roles are ordered ``viewer < fleet < admin``; a route needing
``fleet`` accepts ``fleet`` and ``admin`` keys. A key is read from ``X-API-Key``,
``Authorization: Bearer``, or the ``key`` query parameter (API clients), in that order; without
one, from the browser's session cookie.

**Browser sessions.** ``POST /api/v1/session`` with a key sets an HttpOnly, ``SameSite=Strict``
cookie (:data:`SESSION_COOKIE`) holding a signed token ``v1.<key_id>.<expiry>.<nonce>.<mac>``:
the MAC is HMAC-SHA256 under a key derived from the API key's stored hash (and the optional
``session_secret`` setting), so nothing is stored per session, every API process can check it,
it cannot be forged without the database, and revoking the key ends its sessions. Pages,
REST calls and websockets of the web UI carry only the cookie; no key travels in a URL.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
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


SESSION_COOKIE = "cranetwin_session"
"""Name of the browser session cookie."""


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

    def __init__(self, lookup: KeyLookup, ttl_s: float = 10.0, session_secret: str = "") -> None:
        self._lookup = lookup
        self._ttl_s = ttl_s
        self._cache: dict[str, tuple[float, ApiKey]] = {}
        self._session_secret = session_secret.encode()

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

    def _session_mac(self, secret_sha256: str, body: str) -> str:
        mac_key = hmac.new(self._session_secret, secret_sha256.encode(), hashlib.sha256).digest()
        return hmac.new(mac_key, body.encode(), hashlib.sha256).hexdigest()

    def issue_session(self, token: str | None, ttl_s: float,
                      now: float | None = None) -> tuple[ApiKey, str, float]:
        """Sign in with the key ``token``: (its key, the cookie value, expiry [s since epoch]).

        Raises:
            ApiError: 401 for a missing, malformed, unknown or revoked key.
        """
        if not token or not token.strip():
            raise ApiError(401, "API key required", "enter an API key (it starts with "
                           f"{KEY_PREFIX}; `cranetwin keys create --role viewer` makes one)")
        key = self.check(token.strip())
        row = self._lookup(key.key_id)
        if row is None:  # revoked between the two reads
            raise ApiError(401, "Invalid API key", "the key was revoked")
        expires = int((time.time() if now is None else now) + ttl_s)
        body = f"v1.{key.key_id}.{expires}.{secrets.token_urlsafe(12)}"
        return key, f"{body}.{self._session_mac(row[0], body)}", float(expires)

    def check_session(self, cookie: str, now: float | None = None) -> ApiKey:
        """The key a session cookie was issued for.

        Raises:
            ApiError: 401 when the cookie is malformed, forged, expired, or its key revoked.
        """
        ended = ApiError(401, "Signed out", "your session has ended (expired, signed out or its "
                         "key revoked); sign in again with an API key",
                         headers={"WWW-Authenticate": "Bearer"})
        t_now = time.time() if now is None else now
        hit = self._cache.get("session:" + cookie)
        if hit is not None and time.monotonic() - hit[0] < self._ttl_s:
            expires_s = float(cookie.split(".")[2])
            if expires_s > t_now:
                return hit[1]
        parts = cookie.split(".")
        if len(parts) != 5 or parts[0] != "v1":
            raise ended
        body, mac = ".".join(parts[:4]), parts[4]
        try:
            expires = int(parts[2])
        except ValueError:
            raise ended from None
        if expires <= t_now:
            raise ended
        row = self._lookup(parts[1])
        if row is None or not hmac.compare_digest(self._session_mac(row[0], body), mac):
            raise ended
        key = ApiKey(key_id=parts[1], name=row[1], role=row[2])
        if len(self._cache) > 10_000:
            self._cache.clear()
        self._cache["session:" + cookie] = (time.monotonic(), key)
        return key

    def peek(self, conn: HTTPConnection) -> ApiKey | None:
        """The caller of a request if its key or session was verified within ``ttl_s`` (no
        database read, no error), else None."""
        now = time.monotonic()
        token = presented_token(conn)
        if token:
            hit = self._cache.get(token)
        else:
            cookie = conn.cookies.get(SESSION_COOKIE)
            hit = self._cache.get("session:" + cookie) if cookie else None
            if hit is not None and cookie is not None:
                parts = cookie.split(".")
                if len(parts) != 5 or not parts[2].isdigit() or int(parts[2]) <= time.time():
                    return None
        if hit is None or now - hit[0] >= self._ttl_s:
            return None
        return hit[1]

    def authenticate(self, conn: HTTPConnection) -> ApiKey:
        """The caller of a request or websocket: its presented key, else its session cookie.

        Raises:
            ApiError: 401 (no key and no valid session, or an invalid key).
        """
        token = presented_token(conn)
        if token:
            return self.check(token)
        cookie = conn.cookies.get(SESSION_COOKIE)
        if cookie:
            return self.check_session(cookie)
        return self.check(None)

    def forget(self) -> None:
        """Drop the cache (after a key was revoked)."""
        self._cache.clear()


def authorise(key: ApiKey, role: Role) -> ApiKey:
    """``key`` if its role is at least ``role``, else 403."""
    if not key.allows(role):
        raise ApiError(403, "Insufficient role",
                       f"this operation needs a {role!r} key (or higher); yours is {key.role!r}")
    return key


__all__ = ["KEY_PREFIX", "ROLES", "SESSION_COOKIE", "ApiKey", "KeyVerifier", "Role", "authorise",
           "new_key", "presented_token"]
