"""Browser sign-in: a key entered once becomes an HttpOnly, SameSite=Strict session cookie that
REST calls, the web routes and the live websocket accept; wrong keys and ended sessions get clear
401s; signing out clears the cookie; revoking the key ends its sessions."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.auth import SESSION_COOKIE, KeyVerifier
from cranetwin.api.errors import ApiError
from cranetwin.settings import Settings


@pytest.fixture()
def ctx(db_url: str) -> Iterator[tuple[TestClient, dict[str, str], Any]]:
    app = create_app(Settings(database_url=db_url, worker_in_process=False, session_ttl_s=600))
    with TestClient(app) as client:
        services = app.state.services
        keys = {r: services.backend.create_key(r, f"test {r}")[1]
                for r in ("viewer", "fleet", "admin")}
        r = client.post("/api/v1/machines", headers={"X-API-Key": keys["admin"]},
                        json={"machine_id": "crane-1", "model": "patu655"})
        assert r.status_code == 201, r.text
        yield client, keys, services


def _set_cookie(resp: Any) -> str:
    return str(resp.headers["set-cookie"])


@pytest.mark.timeout(30)
def test_a_key_becomes_an_httponly_strict_cookie_the_api_accepts(ctx: Any) -> None:
    client, keys, _ = ctx
    assert client.get("/api/v1/machines").status_code == 401
    r = client.post("/api/v1/session", json={"key": keys["fleet"]})
    assert r.status_code == 200, r.text
    assert r.json()["role"] == "fleet" and r.json()["name"] == "test fleet"
    cookie = _set_cookie(r).lower()
    assert f"{SESSION_COOKIE}=" in cookie
    assert "httponly" in cookie and "samesite=strict" in cookie and "path=/" in cookie
    assert "max-age=600" in cookie or "max-age=599" in cookie
    assert keys["fleet"] not in _set_cookie(r)  # the cookie is a signed token, not the key
    assert r.headers["cache-control"] == "no-store"
    # later calls carry only the cookie
    assert client.get("/api/v1/machines").status_code == 200
    who = client.get("/api/v1/session").json()
    assert who["role"] == "fleet" and who["expires"].endswith("Z")
    # web routes call the API's own routes with the caller's cookie
    assert client.get("/api/v1/machines/crane-1/scene").status_code == 200
    # the live websocket accepts the cookie (no ?key=)
    with client.websocket_connect("/api/v1/machines/crane-1/live") as ws:
        assert ws.receive_json()["type"] == "hello"


@pytest.mark.timeout(30)
def test_wrong_keys_are_refused_with_reasons(ctx: Any) -> None:
    client, keys, _ = ctx
    for bad, why in (("", "enter an API key"), ("not-a-key", "malformed, unknown or revoked"),
                     (keys["viewer"][:-3] + "xyz", "malformed, unknown or revoked")):
        r = client.post("/api/v1/session", json={"key": bad})
        assert r.status_code == 401, r.text
        assert why in r.json()["detail"]
        assert "set-cookie" not in r.headers
    assert client.post("/api/v1/session", json={}).status_code == 422
    # a forged or tampered cookie is refused
    client.post("/api/v1/session", json={"key": keys["viewer"]})
    good = client.cookies[SESSION_COOKIE]
    body, mac = good.rsplit(".", 1)
    for forged in (f"{body}.{'0' * len(mac)}", "v2" + good[2:],
                   body.rsplit(".", 2)[0] + f".{int(time.time()) + 10**6}.x.{mac}"):
        client.cookies.clear()
        client.cookies.set(SESSION_COOKIE, forged)
        r = client.get("/api/v1/machines")
        assert r.status_code == 401 and r.json()["title"] == "Signed out", r.text
    client.cookies.clear()
    client.cookies.set(SESSION_COOKIE, good)
    assert client.get("/api/v1/machines").status_code == 200


@pytest.mark.timeout(30)
def test_roles_sign_out_and_revocation(ctx: Any) -> None:
    client, keys, services = ctx
    client.post("/api/v1/session", json={"key": keys["viewer"]})
    # a viewer session has a viewer's rights only
    r = client.post("/api/v1/machines", json={"machine_id": "crane-9", "model": "patu655"})
    assert r.status_code == 403
    r = client.delete("/api/v1/session")
    assert r.status_code == 204
    assert f'{SESSION_COOKIE}=""' in _set_cookie(r) or "max-age=0" in _set_cookie(r).lower()
    assert SESSION_COOKIE not in client.cookies
    assert client.get("/api/v1/machines").status_code == 401
    # revoking the key ends its sessions (after the verifier's short cache)
    client.post("/api/v1/session", json={"key": keys["admin"]})
    assert client.get("/api/v1/machines").status_code == 200
    from cranetwin.storage import apikeys

    with services.backend.session() as s, s.begin():
        assert apikeys.revoke_key(s, keys["admin"].split("_")[1])
    services.keys.forget()
    r = client.get("/api/v1/machines")
    assert r.status_code == 401 and "sign in again" in r.json()["detail"]


@pytest.mark.timeout(10)
def test_sessions_expire_and_need_the_servers_secret(tmp_path: Path) -> None:
    import hashlib

    stored = hashlib.sha256(b"secret").hexdigest()

    def lookup(key_id: str) -> tuple[str, str, Any] | None:
        return (stored, "k", "viewer") if key_id == "0123456789ab" else None

    v = KeyVerifier(lookup, session_secret="pepper")
    v.check = lambda token: __import__("cranetwin.api.auth", fromlist=["ApiKey"]).ApiKey(  # type: ignore[method-assign]
        "0123456789ab", "k", "viewer")
    _, cookie, expires = v.issue_session("ctk_0123456789ab_secret", 60.0, now=1000.0)
    assert expires == 1060.0
    assert v.check_session(cookie, now=1059.0).key_id == "0123456789ab"
    v.forget()
    with pytest.raises(ApiError, match="Signed out"):
        v.check_session(cookie, now=1061.0)
    # another server secret: the same cookie is not valid there
    other = KeyVerifier(lookup, session_secret="other")
    with pytest.raises(ApiError):
        other.check_session(cookie, now=1000.0)
