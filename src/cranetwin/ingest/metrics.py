"""The ingest daemon's counters (:class:`Metrics`) and their Prometheus view."""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector


class _Snapshotting(Protocol):
    """What the collector reads from the daemon."""

    @property
    def storage_outage(self) -> bool: ...

    def snapshot(self) -> dict[str, Any]: ...


# --- counters -----------------------------------------------------------------------------------
COUNTERS: dict[str, str] = {
    "received": "datagrams received on the UDP socket",
    "received_bytes": "bytes of UDP payload received",
    "accepted": "datagrams authenticated, valid and handed to the writer",
    "stored_blocks": "sample blocks newly stored",
    "stored_samples": "samples newly stored",
    "duplicates": "blocks already stored (retransmissions), acknowledged again",
    "status_reports": "status reports stored",
    "acks_sent": "ack datagrams sent",
    "refusals_sent": "refusal datagrams sent (authenticated datagrams never to be stored)",
    "batches": "write batches committed",
    "write_errors": "failed write attempts (storage unavailable or an unexpected error)",
    "rollup_errors": "failed summary rollups (queries stay exact; retried)",
    "writer_restarts": "writer threads restarted after dying",
    "decoder_restarts": "decoder threads restarted after dying",
}
"""Counter name → help text; each is a key of :meth:`IngestDaemon.snapshot` and, with the prefix
``cranetwin_ingest_`` and the suffix ``_total``, a Prometheus counter."""


@dataclass
class Metrics:
    """Counters of one daemon run (ints; those touched by several threads go through
    :meth:`add` / :meth:`drop`)."""

    received: int = 0
    received_bytes: int = 0
    accepted: int = 0
    stored_blocks: int = 0
    stored_samples: int = 0
    duplicates: int = 0
    status_reports: int = 0
    acks_sent: int = 0
    refusals_sent: int = 0
    batches: int = 0
    write_errors: int = 0
    rollup_errors: int = 0
    writer_restarts: int = 0
    decoder_restarts: int = 0
    write_seconds: float = 0.0
    dropped: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, name: str, n: int = 1) -> None:
        """Add ``n`` to counter ``name`` (thread-safe)."""
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def drop(self, reason: str, n: int = 1) -> None:
        """Count ``n`` datagrams dropped for ``reason`` (thread-safe)."""
        with self._lock:
            self.dropped[reason] += n

    def snapshot(self, queue_depth: int, queue_max: int, started: float) -> dict[str, Any]:
        with self._lock:
            d: dict[str, Any] = {k: v for k, v in self.__dict__.items()
                                 if k not in ("dropped", "_lock")}
            d["dropped"] = dict(self.dropped)
        d["dropped_total"] = sum(d["dropped"].values())
        d["queue_depth"] = queue_depth
        d["queue_max"] = queue_max
        d["uptime_s"] = round(time.monotonic() - started, 3)
        d["time_unix_s"] = time.time()
        return d


class SnapshotCollector(Collector):
    """Prometheus view of :meth:`IngestDaemon.snapshot`, read at scrape time (the hot path only
    increments ints)."""

    def __init__(self, daemon: _Snapshotting) -> None:
        self.daemon = daemon

    def describe(self) -> Iterable[Metric]:
        return []  # names are not known before the first scrape (drop reasons); no clash check

    def collect(self) -> Iterable[Metric]:
        s = self.daemon.snapshot()
        for name, doc in COUNTERS.items():
            yield CounterMetricFamily(f"cranetwin_ingest_{name}", doc, value=s[name])
        dropped = CounterMetricFamily("cranetwin_ingest_dropped",
                                      "datagrams dropped, by reason", labels=["reason"])
        for reason, n in sorted(s["dropped"].items()):
            dropped.add_metric([reason], n)
        yield dropped
        yield GaugeMetricFamily("cranetwin_ingest_queue_depth",
                                "datagrams not yet decoded", value=s["queue_depth"])
        yield GaugeMetricFamily("cranetwin_ingest_queue_max",
                                "capacity of the datagram queue", value=s["queue_max"])
        yield GaugeMetricFamily("cranetwin_ingest_storage_available",
                                "1 while the last write attempt succeeded, 0 during an outage",
                                value=0.0 if self.daemon.storage_outage else 1.0)
        yield GaugeMetricFamily("cranetwin_ingest_uptime_seconds", "seconds since start [s]",
                                value=s["uptime_s"])
