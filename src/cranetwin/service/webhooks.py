"""Webhook notification of new alarms: an HMAC-signed JSON POST per event, sent from a thread.

:class:`WebhookNotifier` queues alarms (:meth:`~WebhookNotifier.offer` never waits: a full
queue drops the alarm with a warning) and one daemon thread delivers them in order. A delivery
that fails with a connection error, a timeout, HTTP 429 or 5xx is retried after
``backoff_s``·2^k (k = 0, 1, …; at most 60 s) up to ``retries`` times; any other 4xx is given up
at once (the receiver refused it; retrying cannot help). Nothing here runs in the ingest daemon
or the twin worker: the API's alarm check finds new events in the database
(:meth:`cranetwin.service.alarms.AlarmService.notify_new`) and offers them here.

Request: ``POST <url>`` with the JSON body of :func:`payload` and the headers

* ``X-Cranetwin-Timestamp``: Unix time of this attempt [s];
* ``X-Cranetwin-Signature``: ``sha256=<hex HMAC-SHA256 of "<timestamp>.<body>" under the
  secret>`` (the receiver recomputes it over the raw body; comparing the timestamp with its
  clock refuses replays);
* ``X-Cranetwin-Delivery``: ``<event id>`` (the same on every retry, to drop duplicates);
* ``X-Cranetwin-Attempt``: 1, 2, …

The secret comes from the settings (``CRANETWIN_ALARM_WEBHOOK_SECRET``, environment only) and is
never logged; the URL is logged without its query string.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import httpx

log = logging.getLogger(__name__)

MAX_BACKOFF_S = 60.0
QUEUE_SIZE = 1000


def signature(secret: str, timestamp: str, body: bytes) -> str:
    """``sha256=<hex>``: HMAC-SHA256 of ``timestamp + "." + body`` under ``secret``."""
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify(secret: str, timestamp: str, body: bytes, header: str) -> bool:
    """Whether ``header`` is the signature of ``body`` at ``timestamp`` (constant time)."""
    return hmac.compare_digest(signature(secret, timestamp, body), header)


def payload(alarm: dict[str, Any]) -> dict[str, Any]:
    """The JSON body for one alarm (in the API's ``/api/v1/alarms`` item shape)."""
    return {"type": "cranetwin.alarm", "alarm": alarm}


def _safe_url(url: str) -> str:
    p = urlsplit(url)
    return f"{p.scheme}://{p.hostname}{':' + str(p.port) if p.port else ''}{p.path}"


class WebhookNotifier:
    """Delivers alarms to one webhook URL from a background thread.

    Args:
        url: Receiver URL (http or https).
        secret: HMAC key of the signature header.
        retries: Retries after the first attempt.
        backoff_s: First retry delay [s]; doubled each retry, at most :data:`MAX_BACKOFF_S`.
        timeout_s: Timeout of one request [s].
        sleep: Sleep function (tests pass a fast one).
    """

    def __init__(self, url: str, secret: str, retries: int = 5, backoff_s: float = 1.0,
                 timeout_s: float = 5.0, sleep: Callable[[float], None] | None = None) -> None:
        self.url, self.secret = url, secret
        self.retries, self.backoff_s, self.timeout_s = retries, backoff_s, timeout_s
        self._stop = threading.Event()
        self._sleep: Callable[[float], object] = sleep or self._stop.wait
        self.queue: queue.Queue[dict[str, Any] | None] = queue.Queue(QUEUE_SIZE)
        self.delivered = 0
        self.failed = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="cranetwin-webhook", daemon=True)
        self._thread.start()

    def offer(self, alarm: dict[str, Any]) -> bool:
        """Queue ``alarm`` for delivery without waiting; False when the queue is full."""
        try:
            self.queue.put_nowait(alarm)
            return True
        except queue.Full:
            self.dropped += 1
            log.warning("webhook: queue full, alarm %s not sent", alarm.get("id"))
            return False

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop after the alarm being delivered (queued ones are not sent)."""
        self._stop.set()
        try:
            self.queue.put_nowait(None)
        except queue.Full:
            pass
        self._thread.join(timeout_s)

    def _run(self) -> None:
        with httpx.Client(timeout=self.timeout_s) as client:
            while not self._stop.is_set():
                item = self.queue.get()
                if item is None:
                    return
                try:
                    ok = self._deliver(client, item)
                except Exception as exc:  # noqa: BLE001 - the thread must keep serving
                    log.warning("webhook: alarm %s not sent: %s", item.get("id"), exc)
                    ok = False
                if ok:
                    self.delivered += 1
                else:
                    self.failed += 1

    def _deliver(self, client: httpx.Client, alarm: dict[str, Any]) -> bool:
        body = json.dumps(payload(alarm), separators=(",", ":"), sort_keys=True).encode()
        for attempt in range(1, self.retries + 2):
            ts = str(int(time.time()))
            headers = {"Content-Type": "application/json", "User-Agent": "cranetwin-webhook",
                       "X-Cranetwin-Timestamp": ts,
                       "X-Cranetwin-Signature": signature(self.secret, ts, body),
                       "X-Cranetwin-Delivery": str(alarm.get("id")),
                       "X-Cranetwin-Attempt": str(attempt)}
            try:
                resp = client.post(self.url, content=body, headers=headers)
                status: int | None = resp.status_code
                why = f"HTTP {status}"
            except httpx.HTTPError as exc:
                status, why = None, type(exc).__name__
            if status is not None and 200 <= status < 300:
                return True
            if status is not None and 400 <= status < 500 and status != 429:
                log.warning("webhook %s refused alarm %s (%s); not retried",
                            _safe_url(self.url), alarm.get("id"), why)
                return False
            if attempt > self.retries or self._stop.is_set():
                break
            delay = min(self.backoff_s * 2 ** (attempt - 1), MAX_BACKOFF_S)
            log.info("webhook %s: alarm %s attempt %d failed (%s); retry in %.1f s",
                     _safe_url(self.url), alarm.get("id"), attempt, why, delay)
            self._sleep(delay)
        log.warning("webhook %s: alarm %s not delivered after %d attempts",
                    _safe_url(self.url), alarm.get("id"), self.retries + 1)
        return False
