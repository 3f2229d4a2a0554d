"""Webhook notification of new critical events, against a local HTTP receiver.

The real ``create_app`` on SQLite with the webhook settings; the receiver (``http.server`` on
loopback) answers 500 to the first deliveries so the retries are exercised, checks each request's
HMAC signature with the shared secret, and can be made slow to show that nothing waits for it.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from cranetwin.service.webhooks import WebhookNotifier, signature, verify
from cranetwin.storage import Event

SECRET = "s3cret-for-the-test"
T0 = 1_790_000_000.0


class Receiver:
    """A local webhook receiver: records every request; fails the first ``fail`` of them with
    HTTP 500; waits ``delay_s`` before answering."""

    def __init__(self, fail: int = 0, delay_s: float = 0.0) -> None:
        self.requests: list[dict[str, Any]] = []
        self.fail, self.delay_s = fail, delay_s
        self.lock = threading.Lock()
        rx = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                time.sleep(rx.delay_s)
                with rx.lock:
                    rx.requests.append({"headers": dict(self.headers), "body": body})
                    status = 500 if len(rx.requests) <= rx.fail else 200
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook?token=abc"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    def ok(self) -> list[dict[str, Any]]:
        """The requests that were answered 200."""
        with self.lock:
            return self.requests[self.fail:]


@pytest.fixture()
def receiver() -> Iterator[Receiver]:
    rx = Receiver(fail=2)
    yield rx
    rx.close()


def _wait(cond: Any, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


@pytest.mark.timeout(60)
def test_new_critical_events_are_signed_posted_and_retried(tmp_path: Path,
                                                           receiver: Receiver) -> None:
    from cranetwin.api import create_app
    from cranetwin.settings import Settings

    url = f"sqlite:///{tmp_path / 'wh.db'}"
    # a machine and a critical event from before the webhook was configured: never sent
    with TestClient(create_app(Settings(database_url=url, worker_in_process=False,
                                        alarm_check_interval_s=0))) as client:
        services = client.app.state.services  # type: ignore[attr-defined]
        admin = {"X-API-Key": services.backend.create_key("admin", "admin")[1]}
        assert client.post("/api/v1/machines", headers=admin,
                           json={"machine_id": "crane-1", "model": "patu655"}).status_code == 201
        services.backend.store.add_events([Event("crane-1", T0 - 10, "overload", "critical",
                                                 {})])
    app = create_app(Settings(database_url=url, worker_in_process=False,
                              alarm_check_interval_s=0.2, alarm_offline_s=1e6,
                              alarm_webhook_url=receiver.url, alarm_webhook_secret=SECRET,
                              alarm_webhook_backoff_s=0.05))
    with TestClient(app) as client:
        store = app.state.services.backend.store
        store.add_events([
            Event("crane-1", T0, "overload", "critical",
                  {"value": 2.84e4, "limit": 2e4, "unit": "N*m", "component": "load"}),
            Event("crane-1", T0 + 1, "shock_load", "warning", {}),
        ])
        _wait(lambda: len(receiver.ok()) >= 1)
        time.sleep(0.6)  # three more checks: nothing else is sent
    assert len(receiver.requests) == 3  # 500, 500, then 200
    attempts = [r["headers"]["X-Cranetwin-Attempt"] for r in receiver.requests]
    assert attempts == ["1", "2", "3"]
    deliveries = {r["headers"]["X-Cranetwin-Delivery"] for r in receiver.requests}
    assert len(deliveries) == 1
    req = receiver.ok()[0]
    h = req["headers"]
    assert h["Content-Type"] == "application/json"
    assert verify(SECRET, h["X-Cranetwin-Timestamp"], req["body"], h["X-Cranetwin-Signature"])
    assert not verify("another secret", h["X-Cranetwin-Timestamp"], req["body"],
                      h["X-Cranetwin-Signature"])
    assert abs(int(h["X-Cranetwin-Timestamp"]) - time.time()) < 60
    body = json.loads(req["body"])
    assert body["type"] == "cranetwin.alarm"
    a = body["alarm"]
    assert (a["machine_id"], a["kind"], a["severity"], a["t"]) == ("crane-1", "overload",
                                                                   "critical", T0)
    assert a["message"] == "overload on load: 28.4 kN·m (limit 20 kN·m, 142 % of it)"
    assert str(a["id"]) == h["X-Cranetwin-Delivery"]
    assert SECRET.encode() not in req["body"]


@pytest.mark.timeout(30)
def test_a_slow_or_dead_receiver_never_blocks_the_caller() -> None:
    slow = Receiver(delay_s=2.0)
    try:
        n = WebhookNotifier(slow.url, SECRET, retries=0, timeout_s=5.0)
        t = time.monotonic()
        for i in range(50):
            assert n.offer({"id": i})
        assert time.monotonic() - t < 0.2  # queued, not sent, by the caller
        _wait(lambda: len(slow.requests) >= 1, 10)
        n.close(timeout_s=5.0)
    finally:
        slow.close()
    # a refused connection is retried with backoff, then given up, without raising
    slept: list[float] = []
    dead = WebhookNotifier("http://127.0.0.1:9/none", SECRET, retries=3, backoff_s=0.5,
                           timeout_s=1.0, sleep=slept.append)
    dead.offer({"id": 1})
    _wait(lambda: dead.failed == 1, 20)
    dead.close()
    assert slept == [0.5, 1.0, 2.0]


@pytest.mark.timeout(30)
def test_a_refusal_is_not_retried_and_the_signature_covers_the_timestamp() -> None:
    # 4xx: the receiver refused; one attempt only
    seen: list[int] = []

    class H(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802
            self.rfile.read(int(self.headers["Content-Length"]))
            seen.append(1)
            self.send_response(401)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    srv = ThreadingHTTPServer(("127.0.0.1", 0), H)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        n = WebhookNotifier(f"http://127.0.0.1:{srv.server_address[1]}/", SECRET, retries=4,
                            backoff_s=0.01)
        n.offer({"id": 7})
        _wait(lambda: n.failed == 1, 10)
        n.close()
    finally:
        srv.shutdown()
        srv.server_close()
    assert seen == [1]
    body = b'{"a":1}'
    assert signature(SECRET, "100", body) != signature(SECRET, "101", body)
