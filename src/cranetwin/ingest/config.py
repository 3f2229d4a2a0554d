"""The ingest daemon's configuration: machine models as registered, and :class:`DaemonConfig`."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from cranetwin.errors import CraneTwinError, MachineFileError
from cranetwin.model import builtin_machines, load_machine, machine_from_dict
from cranetwin.model.schema import Machine
from cranetwin.protocol import Layout, Limits


class IngestConfigError(CraneTwinError):
    """The daemon cannot start as configured (address in use, unresolvable host, …)."""


# --- machine models -----------------------------------------------------------------------------
def check_model(model: str, source: str = "machine model") -> tuple[Machine, Layout]:
    """Load and validate a machine model as registered: a built-in name or description TOML text.

    The one check used when a machine is registered (CLI and API) and when the daemon loads its
    keys, so that what registration accepts the daemon can serve.

    Returns:
        The machine description and its wire channel layout.

    Raises:
        MachineFileError: The model does not load; ``problems`` lists ``"field.path: message"``.
    """
    if model in builtin_machines():
        machine = load_machine(model)
    else:
        try:
            data = tomllib.loads(model)
        except tomllib.TOMLDecodeError as exc:
            known = ", ".join(builtin_machines())
            hint = "" if "\n" in model or "=" in model else f" (and not a built-in: {known})"
            raise MachineFileError(source, [f"(file): TOML syntax error: {exc}{hint}"]) from None
        machine = machine_from_dict(data, source)
    try:
        layout = Layout.from_channels(machine.channels)
    except (CraneTwinError, ValueError, TypeError) as exc:
        raise MachineFileError(source, [f"channels: {exc}"]) from exc
    return machine, layout


def layout_of(model: str) -> Layout:
    """Channel layout of a machine model: a built-in name or machine-description TOML text.

    Raises:
        MachineFileError: The model does not load.
    """
    return check_model(model, "<stored model>")[1]


# --- settings -----------------------------------------------------------------------------------
@dataclass
class DaemonConfig:
    """Settings of one daemon.

    Attributes:
        host, port: UDP address to bind (port 0 picks a free one; see ``IngestDaemon.address``).
        queue_max: Accepted datagrams waiting for the writer; beyond it they are dropped
            (counted as ``queue_full``) and the sender retransmits.
        batch_max: Blocks written per transaction at most.
        batch_wait_s: How long the writer gathers a batch after its first item [s].
        rcvbuf_bytes: Requested SO_RCVBUF [bytes] (the kernel caps it at net.core.rmem_max).
        metrics_host, metrics_port: HTTP address of the Prometheus ``/metrics`` endpoint
            (``metrics_host`` None: not served; port 0 picks a free one, see
            ``IngestDaemon.metrics_address``).
        metrics_path: Deprecated: JSON file of :meth:`IngestDaemon.snapshot` rewritten every
            ``metrics_interval_s`` (None: not written). Use ``/metrics``.
        metrics_interval_s: Period of the metrics log line (and file) [s].
        rollup_interval_s: Period of the 1-min summary rollup [s].
        key_refresh_s: Least time between reloads of machine keys after an unknown wire id [s].
        retry_min_s, retry_max_s: First and longest wait between retries of a batch while
            storage is unavailable [s] (doubling in between).
        shutdown_timeout_s: Longest flush of the queue after SIGTERM while storage is writable [s].
        stall_timeout_s: At shutdown, a database call that has not returned for this long is
            given up (its batch was never acknowledged) [s].
        supervise_interval_s: Period of the check that restarts a dead decoder/writer thread [s].
        limits: What is accepted from authenticated machines: datagram size, time window
            around the server clock [s], sensor range margin (:class:`~cranetwin.protocol.Limits`).
    """

    host: str = "127.0.0.1"
    port: int = 5005
    queue_max: int = 50_000
    batch_max: int = 1000
    batch_wait_s: float = 0.05
    rcvbuf_bytes: int = 8 * 1024 * 1024
    metrics_host: str | None = None
    metrics_port: int = 9105
    metrics_path: Path | None = None
    metrics_interval_s: float = 10.0
    rollup_interval_s: float = 30.0
    key_refresh_s: float = 2.0
    retry_min_s: float = 0.05
    retry_max_s: float = 5.0
    shutdown_timeout_s: float = 60.0
    stall_timeout_s: float = 5.0
    supervise_interval_s: float = 0.2
    limits: Limits = field(default_factory=Limits)
