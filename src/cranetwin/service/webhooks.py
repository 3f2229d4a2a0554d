"""Webhook notification of new alarms: an HMAC-signed JSON POST per event, delivered at least once
from a durable outbox.

:meth:`WebhookNotifier.offer_many` writes alarms to the database's outbox
(:mod:`cranetwin.storage.webhook_outbox`), in the same transaction as the alarm check's cursor, and
returns: nothing waits for the receiver. One daemon thread per notifier claims due rows (a lease
of :attr:`WebhookNotifier.lease_s`), POSTs each and records the outcome. A delivery that fails
with a connection error, a timeout, HTTP 429 or 5xx is tried again ``backoff_s``·2^k later
(k = 0, 1, …; at most 60 s) up to ``retries`` times; any other 4xx is given up at once (the
receiver refused it; retrying cannot help). Retries of one alarm do not hold up the others.

A process that stops or is killed while alarms wait (or while one is on the wire) loses none:
the rows stay pending, and the next process with the webhook setting sends them — the one that
was on the wire again, with the same ``X-Cranetwin-Delivery``, once its lease has run out (so a
receiver may see a delivery twice and drops the repeat by that header). Several API processes
with the setting share the outbox: each row is claimed by one of them.

Nothing here runs in the ingest daemon or the twin worker: the API's alarm check finds new
events in the database (:meth:`cranetwin.service.alarms.AlarmService.notify_new`) and offers
them here.

Request: ``POST <url>`` with the JSON body of :func:`payload` and the headers

* ``X-Cranetwin-Timestamp``: Unix time of this attempt [s];
* ``X-Cranetwin-Signature``: ``sha256=<hex HMAC-SHA256 of "<timestamp>.<body>" under the
  secret>`` (the receiver recomputes it over the raw body; comparing the timestamp with its
  clock refuses replays);
* ``X-Cranetwin-Delivery``: ``<event id>`` (the same on every retry, to drop duplicates);
* ``X-Cranetwin-Attempt``: 1, 2, … (counted in the outbox, across restarts).

The secret comes from the settings (``CRANETWIN_ALARM_WEBHOOK_SECRET``, environment only) and is
never logged; the URL is logged without its query string.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import httpx
from sqlalchemy.orm import Session

from cranetwin.storage import webhook_outbox as outbox

log = logging.getLogger(__name__)

MAX_BACKOFF_S = 60.0
KEEP_DONE_S = 7 * 86400.0
"""Delivered and given-up rows are deleted after this long [s]."""
PURGE_EVERY_S = 3600.0


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


@dataclass(frozen=True)
class WebhookConfig:
    """Where and how alarms are sent.

    Attributes:
        url: Receiver URL (http or https).
        secret: HMAC key of the signature header.
        retries: Retries after the first attempt.
        backoff_s: First retry delay [s]; doubled each retry, at most :data:`MAX_BACKOFF_S`.
        timeout_s: Timeout of each phase of one request (connect, send, answer) [s].
        poll_s: Longest wait between two looks at the outbox [s] (an offer wakes the sender at
            once; this picks up rows other processes queued and leases that ran out).
    """

    url: str
    secret: str
    retries: int = 5
    backoff_s: float = 1.0
    timeout_s: float = 5.0
    poll_s: float = 1.0


class WebhookNotifier:
    """Delivers alarms from the database's outbox to one webhook URL, from a background thread.

    Args:
        config: Receiver and retry policy.
        sessions: New ORM sessions on the database (``Backend.session``).
        clock: Wall clock [s since the epoch] (timestamps, due times and leases).
    """

    def __init__(self, config: WebhookConfig, sessions: Callable[[], Session],
                 clock: Callable[[], float] = time.time) -> None:
        self.config = config
        self.sessions = sessions
        self.clock = clock
        self.lease_s = 3.0 * config.timeout_s + 2.0
        """How long a claimed row is held [s]: longer than one attempt can take, after which a
        row whose sender died is sent again."""
        self.delivered = 0
        self.failed = 0
        self.retry_delays: list[float] = []  # the delays scheduled, newest last (logs, tests)
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._last_purge = 0.0
        self._thread = threading.Thread(target=self._run, name="cranetwin-webhook", daemon=True)
        self._thread.start()

    # -- the caller's side: queue and return -------------------------------------------------
    def offer(self, alarm: dict[str, Any]) -> bool:
        """Queue one alarm (its ``id`` is the delivery id) without waiting for the receiver."""
        self.offer_many([alarm])
        return True

    def offer_many(self, alarms: Sequence[dict[str, Any]], cursor: int | None = None,
                   cursors: Mapping[str, int] | None = None) -> None:
        """Queue ``alarms`` and, in the same transaction, move the alarm check's cursor to the
        event id ``cursor`` (None: leave it) and each named cursor of ``cursors`` (one per
        storage shard); wakes the sender. An alarm already queued is not queued again."""
        items = [(str(a.get("id")), json.dumps(payload(a), separators=(",", ":"),
                                               sort_keys=True)) for a in alarms]
        with self.sessions() as s, s.begin():
            outbox.enqueue(s, items, self.clock())
            if cursor is not None:
                outbox.advance_cursor(s, cursor)
            for name, value in (cursors or {}).items():
                outbox.advance_cursor(s, value, name)
        if items:
            self._wake.set()

    def cursor(self, name: str = "events") -> int | None:
        """The newest event id the alarm check has considered (of the shard the cursor
        ``name`` follows), or None before the first."""
        with self.sessions() as s:
            return outbox.cursor(s, name)

    def states(self) -> dict[str, int]:
        """Rows of the outbox per state (``pending``, ``delivered``, ``failed``)."""
        with self.sessions() as s:
            return outbox.counts(s)

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop after the attempt on the wire; rows not sent stay in the outbox for the next
        process."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout_s)

    # -- the sender thread ---------------------------------------------------------------------
    def _run(self) -> None:
        with httpx.Client(timeout=self.config.timeout_s) as client:
            while not self._stop.is_set():
                self._wake.clear()
                try:
                    batch = self._claim()
                except Exception as exc:  # noqa: BLE001 - the database may be away for a while
                    log.warning("webhook: cannot read the outbox: %s", exc)
                    self._stop.wait(self.config.poll_s)
                    continue
                for k, item in enumerate(batch):
                    if self._stop.is_set():
                        self._release(batch[k:])
                        return
                    try:
                        self._attempt(client, item)
                    except Exception as exc:  # noqa: BLE001 - the thread must keep serving
                        log.warning("webhook: delivery %s: %s", item.delivery_id, exc)
                if not batch:
                    self._wake.wait(self._idle_s())

    def _claim(self) -> list[outbox.OutboxItem]:
        now = self.clock()
        with self.sessions() as s, s.begin():
            if now - self._last_purge > PURGE_EVERY_S:
                self._last_purge = now
                outbox.purge(s, now - KEEP_DONE_S)
            return outbox.claim(s, now, self.lease_s)

    def _idle_s(self) -> float:
        try:
            with self.sessions() as s:
                due = outbox.next_due(s)
        except Exception:  # noqa: BLE001 - look again after poll_s
            due = None
        if due is None:
            return self.config.poll_s
        return min(max(due - self.clock(), 0.01), self.config.poll_s)

    def _release(self, items: Sequence[outbox.OutboxItem]) -> None:
        """Give back claimed rows not attempted (stopping), so the next process need not wait
        for their lease."""
        try:
            with self.sessions() as s, s.begin():
                outbox.release(s, [it.id for it in items])
        except Exception as exc:  # noqa: BLE001 - their lease runs out anyway
            log.warning("webhook: leases not released: %s", exc)

    def _attempt(self, client: httpx.Client, item: outbox.OutboxItem) -> None:
        cfg = self.config
        attempt = item.attempts
        body = item.body.encode()
        ts = str(int(self.clock()))
        headers = {"Content-Type": "application/json", "User-Agent": "cranetwin-webhook",
                   "X-Cranetwin-Timestamp": ts,
                   "X-Cranetwin-Signature": signature(cfg.secret, ts, body),
                   "X-Cranetwin-Delivery": item.delivery_id,
                   "X-Cranetwin-Attempt": str(attempt)}
        try:
            resp = client.post(cfg.url, content=body, headers=headers)
            status: int | None = resp.status_code
            why = f"HTTP {status}"
        except httpx.HTTPError as exc:
            status, why = None, type(exc).__name__
        now = self.clock()
        outcome: outbox.Outcome
        due = None
        if status is not None and 200 <= status < 300:
            outcome = "delivered"
        elif status is not None and 400 <= status < 500 and status != 429:
            outcome = "failed"
            log.warning("webhook %s refused alarm %s (%s); not retried", _safe_url(cfg.url),
                        item.delivery_id, why)
        elif attempt > cfg.retries:
            outcome = "failed"
            log.warning("webhook %s: alarm %s not delivered after %d attempts (%s)",
                        _safe_url(cfg.url), item.delivery_id, attempt, why)
        else:
            outcome = "retry"
            delay = min(cfg.backoff_s * 2 ** (attempt - 1), MAX_BACKOFF_S)
            due = now + delay
            self.retry_delays.append(delay)
            log.info("webhook %s: alarm %s attempt %d failed (%s); retry in %.1f s",
                     _safe_url(cfg.url), item.delivery_id, attempt, why, delay)
        with self.sessions() as s, s.begin():
            outbox.finish(s, item.id, outcome, now, due, None if outcome == "delivered" else why)
        if outcome == "delivered":
            self.delivered += 1
        elif outcome == "failed":
            self.failed += 1
