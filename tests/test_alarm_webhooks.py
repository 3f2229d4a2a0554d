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

from cranetwin.service.backend import Backend
from cranetwin.service.webhooks import WebhookConfig, WebhookNotifier, signature, verify
from cranetwin.storage import Event
from cranetwin.storage import webhook_outbox as outbox

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


def _notifier(url: str, db: str, **kw: Any) -> tuple[WebhookNotifier, Backend]:
    backend = Backend.open(db)
    return WebhookNotifier(WebhookConfig(url, SECRET, **kw), backend.session), backend


@pytest.mark.timeout(30)
def test_a_slow_or_dead_receiver_never_blocks_the_caller(tmp_path: Path) -> None:
    slow = Receiver(delay_s=2.0)
    try:
        n, backend = _notifier(slow.url, f"sqlite:///{tmp_path / 'a.db'}", retries=0,
                               timeout_s=5.0)
        t = time.monotonic()
        n.offer_many([{"id": i} for i in range(50)])
        assert time.monotonic() - t < 0.5  # queued in the outbox, not sent, by the caller
        _wait(lambda: len(slow.requests) >= 1, 10)
        n.close(timeout_s=5.0)
        assert n.states().get("pending", 0) >= 48  # the rest wait for the next process
        backend.close()
    finally:
        slow.close()
    # a refused connection is retried with backoff, then given up, without raising
    dead, backend = _notifier("http://127.0.0.1:9/none", f"sqlite:///{tmp_path / 'b.db'}",
                              retries=3, backoff_s=0.2, timeout_s=1.0)
    dead.offer({"id": 1})
    _wait(lambda: dead.failed == 1, 20)
    dead.close()
    assert dead.retry_delays == [0.2, 0.4, 0.8]
    with backend.session() as s:
        assert outbox.items(s) == [("1", "failed", 4)]
    backend.close()


@pytest.mark.timeout(30)
def test_a_refusal_is_not_retried_and_the_signature_covers_the_timestamp(tmp_path: Path) -> None:
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
        n, backend = _notifier(f"http://127.0.0.1:{srv.server_address[1]}/",
                               f"sqlite:///{tmp_path / 'c.db'}", retries=4, backoff_s=0.01)
        n.offer({"id": 7})
        _wait(lambda: n.failed == 1, 10)
        n.close()
        backend.close()
    finally:
        srv.shutdown()
        srv.server_close()
    assert seen == [1]
    body = b'{"a":1}'
    assert signature(SECRET, "100", body) != signature(SECRET, "101", body)


@pytest.mark.timeout(60)
def test_two_processes_share_the_outbox_and_send_each_alarm_once(db_url: str) -> None:
    """Two notifiers on one database (two API processes): every alarm is claimed by one of
    them, so a healthy receiver gets each delivery id exactly once; offering an alarm again
    (both processes' checks see it) queues nothing new."""
    rx = Receiver()
    try:
        a, ba = _notifier(rx.url, db_url, poll_s=0.1)
        b, bb = _notifier(rx.url, db_url, poll_s=0.1)
        alarms = [{"id": i, "kind": "overload"} for i in range(1, 41)]
        a.offer_many(alarms[:30])
        b.offer_many(alarms[10:])
        _wait(lambda: len(rx.ok()) >= 40, 30)
        time.sleep(0.5)
        a.close()
        b.close()
        ids = [r["headers"]["X-Cranetwin-Delivery"] for r in rx.ok()]
        assert sorted(ids, key=int) == [str(i) for i in range(1, 41)]
        assert a.delivered > 0 and b.delivered > 0 and a.delivered + b.delivered == 40
        with ba.session() as s:
            assert outbox.counts(s) == {"delivered": 40}
        ba.close()
        bb.close()
    finally:
        rx.close()


_CHILD = """
import sys, time
from cranetwin.service.alarms import AlarmService
from cranetwin.service.backend import Backend
from cranetwin.service.webhooks import WebhookConfig, WebhookNotifier
backend = Backend.open(sys.argv[1])
alarms = AlarmService(backend, 1e6, 1e6)
alarms.set_notifier(WebhookNotifier(WebhookConfig(sys.argv[2], sys.argv[3], retries=5,
                                                  backoff_s=0.1, timeout_s=1.0, poll_s=0.1),
                                    backend.session))
print("ready", flush=True)
while True:
    alarms.notify_new()
    time.sleep(0.1)
"""


class HoldingReceiver(Receiver):
    """Answers 200 after ``delay_s``, except request number ``hold_at``, which it holds (no
    answer) until :attr:`release` is set: the sender is killed while that delivery is on the
    wire."""

    def __init__(self, hold_at: int) -> None:
        self.hold_at = hold_at
        self.holding = threading.Event()
        self.release = threading.Event()
        self.answered: list[str] = []
        super().__init__(delay_s=0.05)
        rx = self
        base = self.server.RequestHandlerClass

        class Handler(base):  # type: ignore[valid-type,misc]
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                with rx.lock:
                    rx.requests.append({"headers": dict(self.headers), "body": body})
                    n = len(rx.requests)
                if n == rx.hold_at:
                    rx.holding.set()
                    rx.release.wait(30)
                    return  # the sender is gone: no answer
                time.sleep(rx.delay_s)
                self.send_response(200)
                self.send_header("Content-Length", "0")
                self.end_headers()
                with rx.lock:
                    rx.answered.append(self.headers["X-Cranetwin-Delivery"])

        self.server.RequestHandlerClass = Handler


@pytest.mark.timeout(90)
def test_alarms_survive_a_kill_mid_delivery(tmp_path: Path) -> None:
    """The sending process is killed (SIGKILL) while the receiver holds one delivery and more
    alarms wait; more events are stored while no process runs. A new process delivers every
    critical event, the interrupted one again under the same delivery id: none lost."""
    import os
    import signal
    import subprocess
    import sys

    from cranetwin.storage import Store

    url = f"sqlite:///{tmp_path / 'kill.db'}"
    store = Store.open(url)
    store.add_machine("crane-1", 1, b"x" * 32)
    store.add_events([Event("crane-1", T0 - 10, "overload", "critical", {})])  # before: not sent
    rx = HoldingReceiver(hold_at=4)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}

    def child() -> subprocess.Popen[str]:
        p = subprocess.Popen([sys.executable, "-c", _CHILD, url, rx.url, SECRET], env=env,
                             stdout=subprocess.PIPE, text=True, start_new_session=True)
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
        return p

    first = child()
    try:
        evs = [Event("crane-1", T0 + i, "overload", "critical", {"value": float(i)})
               for i in range(12)]
        store.add_events(evs[:8] + [Event("crane-1", T0 + 50, "shock_load", "warning", {})])
        assert rx.holding.wait(30), "the fourth delivery never arrived"
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10)
        rx.release.set()
        store.add_events(evs[8:])  # stored while no process sends
        answered_before = list(rx.answered)
        second = child()
        try:
            _wait(lambda: len(set(rx.answered)) >= 12, 40)
            time.sleep(0.5)  # nothing more arrives
        finally:
            os.killpg(second.pid, signal.SIGKILL)
            second.wait(10)
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
        rx.release.set()
        rx.close()
    held = rx.requests[3]["headers"]["X-Cranetwin-Delivery"]
    assert held not in answered_before  # it was on the wire when the process died
    bodies = {r["headers"]["X-Cranetwin-Delivery"]: json.loads(r["body"]) for r in rx.requests}
    sent = {d: b["alarm"] for d, b in bodies.items()}
    assert len(set(rx.answered)) == 12  # every critical event after the start, none lost
    assert {a["kind"] for a in sent.values()} == {"overload"}
    assert sorted(a["t"] for a in sent.values()) == [T0 + i for i in range(12)]
    repeats = [r for r in rx.requests if r["headers"]["X-Cranetwin-Delivery"] == held]
    # sent again, as its second attempt (attempts are counted when a row is claimed)
    assert [r["headers"]["X-Cranetwin-Attempt"] for r in repeats] == ["1", "2"]
    store.close()
