"""API hardening: odd static paths are 4xx (never 500), ``?key=`` never reaches a log line in
clear, and ``/samples`` pages continue past gaps of any length."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.app import ACCESS_LOGGERS, RedactKeysFilter, redact_keys
from cranetwin.api.services import Services
from cranetwin.samples import SampleBlock
from cranetwin.settings import Settings

pytestmark = pytest.mark.timeout(60)

MID = "crane-1"
CHANNELS = ("lift_pA", "lift_s")
RES = (5000.0, 1e-4)
PERIOD = 10_000_000
T0_NS = 1_780_000_000 * 10**9
DAY_NS = 86_400 * 10**9


@dataclass
class Api:
    client: TestClient
    services: Services
    key: str

    def get(self, path: str, **params: Any) -> httpx.Response:
        return self.client.get(path, params=params, headers={"X-API-Key": self.key})


@pytest.fixture
def api(db_url: str) -> Iterator[Api]:
    app = create_app(Settings(database_url=db_url, worker_in_process=False))
    with TestClient(app) as client:
        services: Services = app.state.services
        admin = services.backend.create_key("admin", "test")[1]
        r = client.post("/api/v1/machines", headers={"X-API-Key": admin},
                        json={"machine_id": MID, "model": "patu655"})
        assert r.status_code == 201, r.text
        yield Api(client, services, admin)


# --- static paths --------------------------------------------------------------------------------
ODD_STATIC = ["%00", "css/app.css%00", "foo%00.js", "vendor/%00", "%0a", "a%5Cb",
              "..%2F..%2Fpyproject.toml", "%2e%2e/%2e%2e/pyproject.toml", "css/..%2F..%2FREADME.md",
              "css//app.css", "a" * 5000, "a/" * 3000, ("x" * 255 + "/") * 20, "%ff%fe", ""]


@pytest.mark.parametrize("path", ODD_STATIC, ids=lambda p: p[:24])
def test_odd_static_paths_are_4xx_never_500(sqlite_url: str, path: str) -> None:
    app = create_app(Settings(database_url=sqlite_url, worker_in_process=False))
    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get(f"/static/{path}")
        assert r.status_code in (400, 404), (r.status_code, r.text[:200])
        assert r.headers["content-type"].startswith("application/problem+json")
        assert "[project]" not in r.text and "cranetwin" not in r.text.lower()
        assert client.get("/static/css/app.css").status_code == 200  # real files still served


# --- keys in logs --------------------------------------------------------------------------------
def test_redact_keys_rewrites_every_key_parameter() -> None:
    assert redact_keys("GET /a?key=ctk_1_s3cret HTTP/1.1") == "GET /a?key=*** HTTP/1.1"
    assert redact_keys("/a?x=1&key=s3cret&y=2") == "/a?x=1&key=***&y=2"
    assert redact_keys("/a?%6Bey=s3cret") == "/a?%6Bey=***"
    assert redact_keys("/a?monkey=1&keys=2") == "/a?monkey=1&keys=2"  # other names untouched


class _Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_access_log_of_a_real_server_never_holds_the_key(sqlite_url: str) -> None:
    import uvicorn

    secret = "ctk_0123456789ab_supersecretvalue"
    app = create_app(Settings(database_url=sqlite_url, worker_in_process=False))
    port = _free_port()
    # as `cranetwin serve` does: the app first, then uvicorn configures logging
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="info",
                            access_log=True, lifespan="on")
    server = uvicorn.Server(config)
    capture = _Capture()
    access = logging.getLogger("uvicorn.access")
    access.addHandler(capture)
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    try:
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline and t.is_alive(), "uvicorn did not start"
            time.sleep(0.05)
        base = f"http://127.0.0.1:{port}"
        r1 = httpx.get(f"{base}/api/v1/machines?key={secret}", timeout=10)
        r2 = httpx.get(f"{base}/healthz?x=1&key={secret}&y=2", timeout=10)
        assert r1.status_code == 401 and r2.status_code == 200
        deadline = time.monotonic() + 5
        while len(capture.records) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        server.should_exit = True
        t.join(10)
        access.removeHandler(capture)
    lines = [r.getMessage() for r in capture.records]
    assert len(lines) >= 2, lines
    assert any("/api/v1/machines?key=***" in x for x in lines), lines
    assert any("/healthz?x=1&key=***&y=2" in x for x in lines), lines
    assert not any(secret in x or "supersecret" in x for x in lines), lines
    # the formatter uvicorn prints with sees the redacted arguments too
    fmt = uvicorn.logging.AccessFormatter('%(client_addr)s - "%(request_line)s" %(status_code)s')
    assert all(secret not in fmt.format(r) for r in capture.records)


def test_redaction_is_installed_once_on_every_logger_that_sees_query_strings(
        sqlite_url: str) -> None:
    create_app(Settings(database_url=sqlite_url))
    create_app(Settings(database_url=sqlite_url))
    for name in ACCESS_LOGGERS:
        filters = [f for f in logging.getLogger(name).filters if isinstance(f, RedactKeysFilter)]
        assert len(filters) == 1, name
    rec = logging.LogRecord("uvicorn.error", logging.INFO, __file__, 1,
                            '%s - "WebSocket %s" [accepted]',
                            ("127.0.0.1:5", "/api/v1/live?key=s3cret"), None)
    assert logging.getLogger("uvicorn.error").filter(rec)
    assert "s3cret" not in rec.getMessage() and "key=***" in rec.getMessage()


# --- samples paging across gaps ------------------------------------------------------------------
def _block(seq: int, t0_ns: int, n: int = 100) -> SampleBlock:
    k = np.column_stack([np.arange(n) + 1000 * seq, np.arange(n) * 3])
    return SampleBlock(MID, seq, t0_ns, PERIOD, CHANNELS, RES, k * np.asarray(RES))


def _pages(api: Api, t0: float, t1: float, limit: int) -> tuple[list[float], int]:
    t: list[float] = []
    cursor = None
    pages = 0
    while True:
        params: dict[str, Any] = {"from": t0, "to": t1, "limit": limit}
        if cursor is not None:
            params["cursor"] = cursor
        r = api.get(f"/api/v1/machines/{MID}/samples", **params)
        assert r.status_code == 200, r.text
        page = r.json()
        assert len(page["t"]) <= limit
        t += page["t"]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            return t, pages
        assert pages < 50, "paging does not end"


@pytest.mark.parametrize("limit", [70, 100, 1000])
def test_samples_paging_continues_past_a_500_day_gap(api: Api, limit: int) -> None:
    a = _block(0, T0_NS)
    b = _block(1, T0_NS + 500 * DAY_NS)
    c = _block(2, b.t0_ns + 900 * DAY_NS + 7 * PERIOD, n=30)
    res = api.services.backend.store.write_batch([a, b, c])
    assert [o.status for o in res.outcomes] == ["stored"] * 3
    expected = np.concatenate([x.times_ns() for x in (a, b, c)]) / 1e9
    # from well before the first block (a leading gap) to well after the last
    t, pages = _pages(api, T0_NS / 1e9 - 3 * 86400 * 365, c.t_end_ns / 1e9 + 86400 * 365, limit)
    assert len(t) == 230 and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(t, expected, atol=1e-6)
    assert pages >= 2
    # a range ending inside the gap has no cursor into it; one ending just after b stops there
    t, _ = _pages(api, T0_NS / 1e9, b.t0_ns / 1e9 - 1.0, limit)
    assert len(t) == 100
    t, _ = _pages(api, T0_NS / 1e9, b.t_end_ns / 1e9 + 1e-3, limit)
    assert len(t) == 200
