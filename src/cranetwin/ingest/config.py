"""The ingest daemon's configuration: machine models as registered, and :class:`DaemonConfig`."""

from __future__ import annotations

from dataclasses import dataclass, field

from cranetwin.errors import CraneTwinError
from cranetwin.protocol import Limits
from cranetwin.protocol.machine import check_model, layout_of

__all__ = ["DaemonConfig", "IngestConfigError", "check_model", "layout_of"]


class IngestConfigError(CraneTwinError):
    """The daemon cannot start as configured (address in use, unresolvable host, …)."""


# --- settings -----------------------------------------------------------------------------------
@dataclass
class DaemonConfig:
    """Settings of one daemon.

    Attributes:
        host, port: UDP address to bind (port 0 picks a free one; see ``IngestDaemon.address``).
        queue_max: Accepted datagrams not yet decoded; beyond it they are dropped
            (counted as ``queue_full``) and the sender retransmits.
        batch_max: Datagrams decoded together and blocks written per transaction at most.
        batch_wait_s: How long the event loop gathers a batch after its first datagram before
            handing it to the decoder [s].
        rcvbuf_bytes: Requested SO_RCVBUF [bytes] (the kernel caps it at net.core.rmem_max).
        metrics_host, metrics_port: HTTP address of the Prometheus ``/metrics`` endpoint
            (``metrics_host`` None: not served; port 0 picks a free one, see
            ``IngestDaemon.metrics_address``).
        metrics_interval_s: Period of the metrics log line [s].
        rollup_interval_s: Period of the 1-min summary rollup [s].
        key_refresh_s: Least time between reloads of machine keys after an unknown wire id [s].
        retry_min_s, retry_max_s: First and longest wait between retries of a batch while
            storage is unavailable [s] (doubling in between).
        shutdown_timeout_s: Longest flush of the queue after SIGTERM while storage is writable [s].
        stall_timeout_s: At shutdown, a database call that has not returned for this long is
            given up (its batch was never acknowledged) [s].
        supervise_interval_s: Period of the backstop check that restarts a dead decoder/writer
            thread [s] (a dying thread asks for its restart at once).
        limits: What is accepted from authenticated machines: datagram size, time window
            around the server clock [s], sensor range margin (:class:`~cranetwin.protocol.Limits`).
        socket_fd: A bound UDP socket inherited from the parent of ``--processes``
            (:mod:`~cranetwin.ingest.processes`), used instead of binding ``host``/``port``.
    """

    host: str = "127.0.0.1"
    port: int = 5005
    queue_max: int = 50_000
    batch_max: int = 1000
    batch_wait_s: float = 0.05
    rcvbuf_bytes: int = 8 * 1024 * 1024
    metrics_host: str | None = None
    metrics_port: int = 9105
    metrics_interval_s: float = 10.0
    rollup_interval_s: float = 30.0
    key_refresh_s: float = 2.0
    retry_min_s: float = 0.05
    retry_max_s: float = 5.0
    shutdown_timeout_s: float = 60.0
    stall_timeout_s: float = 5.0
    supervise_interval_s: float = 5.0
    limits: Limits = field(default_factory=Limits)
    socket_fd: int | None = None
