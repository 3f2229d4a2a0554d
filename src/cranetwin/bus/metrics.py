"""Prometheus metrics of the storage writer (``cranetwin store-writer --metrics-bind``).

The same library as the ingest daemon and the twin worker (``prometheus_client``), in a
registry of its own, served by ``prometheus_client.start_http_server``:

``cranetwin_store_writer_consumed_total{partition}``
    messages delivered to this writer (redeliveries included);
``cranetwin_store_writer_committed_total{partition}``
    blocks acked after their transaction committed (stored now or already stored);
``cranetwin_store_writer_stored_samples_total``
    samples newly stored;
``cranetwin_store_writer_redelivered_total{partition}``
    messages delivered more than once (JetStream's delivery count > 1: a writer died before
    acking, an ack was lost, or the block was held back by an unavailable shard);
``cranetwin_store_writer_refused_total{reason}``
    blocks storage refused (terminated on the bus), and ``reason="bad_message"``;
``cranetwin_store_writer_unavailable_total{partition}``
    blocks not stored because their database shard was unavailable (negatively acked,
    delivered again);
``cranetwin_store_writer_write_retries_total``
    batch writes retried while the database was unavailable;
``cranetwin_store_writer_lag_messages{partition}``
    messages of the partition not acked yet (the consumer's pending plus ack-pending counts,
    read from JetStream every few seconds).
"""

from __future__ import annotations

from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, generate_latest

PREFIX = "cranetwin_store_writer"


class WriterMetrics:
    """The storage writer's counters and gauges (see the module docstring)."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.consumed = Counter(f"{PREFIX}_consumed", "messages delivered to this writer",
                                ["partition"], registry=r)
        self.committed = Counter(f"{PREFIX}_committed", "blocks acked after their transaction "
                                 "committed (stored now or already stored)", ["partition"],
                                 registry=r)
        self.stored_samples = Counter(f"{PREFIX}_stored_samples", "samples newly stored",
                                      registry=r)
        self.redelivered = Counter(f"{PREFIX}_redelivered", "messages delivered more than once",
                                   ["partition"], registry=r)
        self.refused = Counter(f"{PREFIX}_refused", "blocks refused by storage (terminated)",
                               ["reason"], registry=r)
        self.unavailable = Counter(f"{PREFIX}_unavailable", "blocks held back because their "
                                   "database shard was unavailable (delivered again)",
                                   ["partition"], registry=r)
        self.write_retries = Counter(f"{PREFIX}_write_retries", "batch writes retried while "
                                     "the database was unavailable", registry=r)
        self.lag = Gauge(f"{PREFIX}_lag_messages", "messages of the partition not acked yet "
                         "(pending + ack pending)", ["partition"], registry=r)
        self._children: dict[int, tuple[Any, Any, Any, Any]] = {}

    def of(self, partition: int) -> tuple[Any, Any, Any, Any]:
        """The (consumed, committed, redelivered, unavailable) counters of one partition
        (labelled children cached: the message path does not build labels per message)."""
        got = self._children.get(partition)
        if got is None:
            p = str(partition)
            got = (self.consumed.labels(p), self.committed.labels(p),
                   self.redelivered.labels(p), self.unavailable.labels(p))
            self._children[partition] = got
        return got

    def render(self) -> bytes:
        """The registry in the Prometheus text format."""
        return generate_latest(self.registry)
