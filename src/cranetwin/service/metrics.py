"""Prometheus metrics of one service instance (own registry, so several can live in a process).

The HTTP API counts its requests here (:mod:`cranetwin.api.metrics` is the middleware) and the
twin worker its windows, whether it runs inside ``cranetwin serve`` or as ``cranetwin worker``.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest


class Metrics:
    """Counters and gauges of the HTTP service, the live stream and the twin worker."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("cranetwin_http_requests", "HTTP requests handled",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("cranetwin_http_request_seconds", "HTTP request latency [s]",
                                 ["route"], registry=r,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.2, 0.5, 1, 2.5, 10))
        self.live_clients = Gauge("cranetwin_live_clients", "open live websockets", registry=r)
        self.live_frames = Counter("cranetwin_live_frames", "live frames sent", registry=r)
        self.twin_cache_hits = Gauge("cranetwin_twin_cache_hits", "replay cache hits", registry=r)
        self.twin_cache_misses = Gauge("cranetwin_twin_cache_misses", "replay cache misses",
                                       registry=r)
        self.twin_cache_bytes = Gauge("cranetwin_twin_cache_bytes",
                                      "bytes held by the replay cache", registry=r)
        self.twin_cache_max_bytes = Gauge("cranetwin_twin_cache_max_bytes",
                                          "byte bound of the replay cache", registry=r)
        self.twin_cache_evictions = Gauge("cranetwin_twin_cache_evictions",
                                          "replay results evicted to keep the cache's bounds",
                                          registry=r)
        self.refused = Counter("cranetwin_http_refused",
                               "requests refused by the service limits (rate_limit: 429, "
                               "busy: 503)", ["reason", "role"], registry=r)
        self.heavy_admitted = Gauge("cranetwin_heavy_admitted",
                                    "heavy requests running or waiting for a heavy thread",
                                    registry=r)
        self.worker_windows = Counter("cranetwin_worker_windows",
                                      "windows processed by the twin worker", ["machine"],
                                      registry=r)
        self.worker_lag = Gauge("cranetwin_worker_lag_seconds",
                                "newest sample minus the worker's watermark [s]", ["machine"],
                                registry=r)
        self.worker_partition_lag = Gauge(
            "cranetwin_worker_partition_lag_seconds",
            "largest newest-sample-minus-watermark of the partition's machines [s]",
            ["partition"], registry=r)
        self.worker_partition_age = Gauge(
            "cranetwin_worker_partition_watermark_age_seconds",
            "now minus the oldest watermark of the partition's machines [s]", ["partition"],
            registry=r)
        self.worker_partitions_owned = Gauge("cranetwin_worker_partitions_owned",
                                             "machine partitions this worker owns", registry=r)
        self.worker_errors = Counter("cranetwin_worker_errors",
                                     "windows the twin worker could not process", ["machine"],
                                     registry=r)

    def render(self) -> bytes:
        """Prometheus text exposition of every metric."""
        return generate_latest(self.registry)
