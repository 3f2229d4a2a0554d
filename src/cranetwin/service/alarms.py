"""Alarms to act on: events listed with filters and paging, acknowledged and cleared by a named
user at a time (kept in the database, ``storage.alarms``), and the connectivity events a fleet
tool is expected to raise by itself:

* ``machine_offline`` (warning): no sample for ``alarm_offline_s`` [s]; stamped at the last
  sample + the timeout (so every API process, and every check, stores it once); cleared by
  ``cranetwin`` when data comes back.
* ``data_gap`` (info): the stream resumed after a silence longer than ``alarm_gap_s`` [s];
  stamped at the last sample before the silence, evidence ``from``, ``to``, ``gap_s``.

New events of a chosen severity and above can be sent to a webhook
(:mod:`cranetwin.service.webhooks`): :meth:`AlarmService.notify_new`, run after each check,
queues the events stored since the notifier's durable cursor (every process's: the twin
worker's, the ingest daemon's and these) in the database's webhook outbox, from which the
notifier's thread signs, sends and retries them; nothing here waits for the receiver. Events
stored before the webhook was first set up on the database are not sent.

:class:`AlarmService` holds no HTTP; the API's ``routes_alarms`` calls it, and ``Services`` runs
:meth:`AlarmService.check_connectivity` every ``alarm_check_interval_s``. A gap is seen by
comparing each machine's newest sample between two checks (one gap per check interval at
most; gaps that happened while no API process ran are not reported).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict
from datetime import UTC, datetime
from typing import Any, Literal

from cranetwin.errors import CraneTwinError
from cranetwin.service.errors import NotFoundError
from cranetwin.service.events import format_duration, format_time, readable_message

log = logging.getLogger(__name__)

SYSTEM_USER = "cranetwin (data resumed)"


def _iso(t: float | None) -> str | None:
    if t is None:
        return None
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _cursor_name(shard: int) -> str:
    """Name of the webhook outbox's cursor over shard ``shard``'s event ids (``events`` for the
    first, the only one without sharding)."""
    return "events" if shard == 0 else f"events.{shard}"


class AlarmService:
    """Alarm listing, acknowledgement and connectivity checks over a :class:`Backend`.

    Args:
        backend: The storage adapter (``service.backend.Backend``).
        offline_s: Silence after which a machine is offline [s].
        gap_s: Silence inside a stream that is reported as a data gap [s].
    """

    def __init__(self, backend: Any, offline_s: float, gap_s: float) -> None:
        self.backend = backend
        self.offline_s = offline_s
        self.gap_s = gap_s
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()
        self.notifier: Any = None  # a service.webhooks.WebhookNotifier, when configured
        self.notify_severities: list[str] = ["critical"]

    # -- webhook notification -----------------------------------------------------------------
    def set_notifier(self, notifier: Any, min_severity: str = "critical") -> None:
        """Send new events of ``min_severity`` and above to ``notifier`` (a
        :class:`~cranetwin.service.webhooks.WebhookNotifier`). The first time a webhook is set
        up on a database its cursor starts after the newest event stored now; later starts
        continue where the last check stopped, so events stored while no API process ran are
        sent too."""
        order = ["info", "warning", "critical"]
        self.notify_severities = order[order.index(min_severity):]
        self.notifier = notifier
        names = [_cursor_name(i) for i in range(len(self.backend.store.engines))]
        start = {n: v for n, v in zip(names, self._newest_id(), strict=True)
                 if notifier.cursor(n) is None}
        if start:
            notifier.offer_many([], cursors=start)

    def _newest_id(self) -> list[int]:
        from cranetwin.storage.alarmshards import newest_ids

        return newest_ids(self.backend.store.engines)

    def notify_new(self) -> int:
        """Queue the events stored since the notifier's cursor (of the notified severities) in
        its outbox, in the order they were stored, and move the cursor past them in the same
        transaction; returns how many. Never waits for a delivery."""
        if self.notifier is None:
            return 0
        from cranetwin.storage.alarmshards import new_since

        engines = self.backend.store.engines
        with self._lock:
            names = [_cursor_name(i) for i in range(len(engines))]
            last = [self.notifier.cursor(n) or 0 for n in names]
            found, marks = new_since(engines, last, self.notify_severities)
            # the cursors pass every event seen, whatever its severity (ids only grow)
            moved = {n: m for n, m, old in zip(names, marks, last, strict=True) if m > old}
            if found or moved:
                self.notifier.offer_many([as_json(a) for a in found], cursors=moved)
        return len(found)

    # -- listing and actions ------------------------------------------------------------------
    def list(self, *, machine_ids: list[str] | None = None, severities: list[str] | None = None,
             kinds: list[str] | None = None, t0_s: float | None = None,
             t1_s: float | None = None, state: str = "active", limit: int = 50,
             offset: int = 0) -> dict[str, Any]:
        """``{"total", "offset", "limit", "items": [...]}``, newest first (see :func:`as_json`)."""
        from cranetwin.storage.alarmshards import list_all

        total, rows, kinds_all = list_all(
            self.backend.store.engines, machine_ids=machine_ids, severities=severities,
            kinds=kinds, t0_s=t0_s, t1_s=t1_s, state=state, limit=limit, offset=offset)
        return {"total": total, "offset": offset, "limit": limit, "kinds": kinds_all,
                "items": [as_json(a) for a in rows]}

    def act(self, event_id: int, action: Literal["acknowledge", "clear"], by: str,
            now_s: float | None = None) -> dict[str, Any]:
        """Acknowledge or clear event ``event_id`` as ``by``; returns the alarm.

        Raises:
            NotFoundError: No such event.
        """
        from cranetwin.storage.alarmshards import act

        a = act(self.backend.store.engines, event_id, action, by,
                time.time() if now_s is None else now_s)
        if a is None:
            raise NotFoundError("Unknown event", f"no event {event_id} (ids are the `id` of GET "
                                "/api/v1/alarms)")
        return as_json(a)

    # -- connectivity -------------------------------------------------------------------------
    def check_connectivity(self, now_s: float | None = None) -> int:
        """Store ``machine_offline`` and ``data_gap`` events that are due; returns how many
        were new. Safe to run from several processes (events are unique per machine, time and
        kind)."""
        from cranetwin.storage import Event

        now = time.time() if now_s is None else now_s
        new: list[Any] = []
        resumed: list[tuple[str, float, float]] = []
        with self._lock:
            for rec in self.backend.list_machines():
                mid = rec.machine_id
                try:
                    rng = self.backend.data_range(mid)
                except CraneTwinError as exc:
                    log.warning("alarms: machine %s not checked: %s", mid, exc)
                    continue
                if rng is None:
                    continue
                last = rng[1]
                prev = self._last.get(mid)
                if prev is not None and last > prev:
                    nxt = self.backend.next_sample_time(mid, prev + 0.5 * self.gap_s)
                    if nxt is not None and nxt - prev > self.gap_s:
                        gap = nxt - prev
                        new.append(Event(mid, prev, "data_gap", "info", {
                            "message": f"data gap: no samples for {format_duration(gap)} "
                                       f"(from {format_time(prev)} to {format_time(nxt)}; "
                                       f"reported above {format_duration(self.gap_s)})",
                            "from": prev, "to": nxt, "gap_s": gap, "limit_s": self.gap_s}))
                        resumed.append((mid, prev, nxt))
                self._last[mid] = last
                if now - last > self.offline_s:
                    new.append(Event(mid, last + self.offline_s, "machine_offline", "warning", {
                        "message": f"machine offline: no samples since {format_time(last)} "
                                   f"(timeout {format_duration(self.offline_s)})",
                        "last_seen": last, "timeout_s": self.offline_s}))
        stored = self.backend.store.add_events(new) if new else 0
        for mid, t0, t1 in resumed:
            self._clear_offline(mid, t0, t1 + 1.0)
        return int(stored)

    def _clear_offline(self, machine_id: str, t0_s: float, t1_s: float) -> None:
        """Clear the ``machine_offline`` events of a silence that has ended."""
        from cranetwin.storage import alarms

        with self.backend.session(machine_id) as s, s.begin():  # the machine's shard
            _, rows = alarms.list_alarms(s, machine_ids=[machine_id], kinds=["machine_offline"],
                                         t0_s=t0_s, t1_s=t1_s, state="active", limit=100)
            for a in rows:
                alarms.set_alarm_state(s, a.event_id, "clear", SYSTEM_USER, time.time())


def as_json(a: Any) -> dict[str, Any]:
    """An :class:`~cranetwin.storage.alarms.Alarm` in the API's shape."""
    d = asdict(a)
    ev = d["evidence"] or {}
    return {
        "id": d["event_id"], "machine_id": d["machine_id"], "t": d["t_s"], "kind": d["kind"],
        "severity": d["severity"], "evidence": ev,
        "message": readable_message(d["kind"], ev, str(ev.get("message") or
                                                      d["kind"].replace("_", " "))),
        "acknowledged": None if d["acked_s"] is None else {"by": d["acked_by"],
                                                           "at": _iso(d["acked_s"])},
        "cleared": None if d["cleared_s"] is None else {"by": d["cleared_by"],
                                                        "at": _iso(d["cleared_s"])},
    }
