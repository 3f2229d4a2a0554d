"""Browser sign-in: a key entered once becomes an HttpOnly session cookie.

``POST /api/v1/session`` checks the key and sets :data:`~cranetwin.api.auth.SESSION_COOKIE`
(HttpOnly, ``SameSite=Strict``, ``Secure`` over HTTPS, ``Path=/``, expiring after the
``session_ttl_s`` setting); ``GET`` says who is signed in; ``DELETE`` signs out (clears the
cookie). The web UI's pages, REST calls and websockets then carry only the cookie.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import Literal

from fastapi import APIRouter, Request, Response, status
from pydantic import BaseModel, ConfigDict, Field

from cranetwin.api.auth import SESSION_COOKIE
from cranetwin.api.deps import CurrentKey, ServicesDep, SettingsDep
from cranetwin.api.errors import PROBLEM_RESPONSES

router = APIRouter(prefix="/api/v1/session", tags=["session"])


class SignIn(BaseModel):
    """An API key to sign in with."""

    model_config = ConfigDict(extra="forbid")

    key: str = Field(max_length=200, description="API key (`ctk_<id>_<secret>`)",
                     examples=["ctk_0123456789ab_…"])


class SessionInfo(BaseModel):
    """Who is signed in."""

    key_id: str = Field(description="public id of the key", examples=["0123456789ab"])
    name: str = Field(description="the key's name (who or what it was made for)",
                      examples=["fleet demo viewer"])
    role: Literal["viewer", "fleet", "admin"] = Field(description="the key's role")
    expires: str | None = Field(None, description="end of the session (ISO 8601 UTC); null when "
                                "the caller presented a key rather than a session cookie")


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _secure(request: Request) -> bool:
    proto = request.headers.get("x-forwarded-proto", request.url.scheme)
    return proto.split(",")[0].strip() == "https"


@router.post("", response_model=SessionInfo, summary="Sign in: a key becomes a session cookie",
             responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401, 422)})
def sign_in(body: SignIn, request: Request, response: Response, services: ServicesDep,
            settings: SettingsDep) -> SessionInfo:
    """Check ``key`` and set the HttpOnly, SameSite=Strict session cookie. A wrong key is a
    401 problem that says why (missing, malformed, unknown or revoked)."""
    key, cookie, expires = services.keys.issue_session(body.key, settings.session_ttl_s)
    response.set_cookie(SESSION_COOKIE, cookie, max_age=int(expires - time.time()),
                        path="/", httponly=True, samesite="strict", secure=_secure(request))
    response.headers["Cache-Control"] = "no-store"
    return SessionInfo(key_id=key.key_id, name=key.name, role=key.role, expires=_iso(expires))


@router.get("", response_model=SessionInfo, summary="Who is signed in",
            responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401,)})
def who(key: CurrentKey, request: Request) -> SessionInfo:
    """The key of the session cookie (or of a presented key)."""
    cookie = request.cookies.get(SESSION_COOKIE, "")
    parts = cookie.split(".")
    presented = any(h in request.headers for h in ("x-api-key", "authorization")) or \
        "key" in request.query_params
    expires = None
    if not presented and len(parts) == 5 and parts[2].isdigit():
        expires = _iso(float(parts[2]))
    return SessionInfo(key_id=key.key_id, name=key.name, role=key.role, expires=expires)


@router.delete("", status_code=status.HTTP_204_NO_CONTENT, summary="Sign out",
               response_class=Response)
def sign_out(request: Request) -> Response:
    """Clear the session cookie (no key needed: signing out always succeeds)."""
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict",
                           secure=_secure(request))
    return response
