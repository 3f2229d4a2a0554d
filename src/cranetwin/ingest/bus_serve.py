"""The ingest daemon writing to the fleet bus instead of the database (docs/BUS.md).

:func:`serve_to_bus` is :func:`cranetwin.ingest.daemon.serve` with the store replaced by a
:class:`~cranetwin.bus.sink.JetStreamStore`: machine keys and status reports still come from and
go to the database at ``db_url``; sample blocks go to JetStream, and a machine is acknowledged
once the PubAcks of its blocks are in. The daemon itself is unchanged
(:func:`~cranetwin.ingest.daemon.serve_store` runs it on either store). With ``--processes N``
every child process runs it (:mod:`cranetwin.ingest.child`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from cranetwin.bus.sink import JetStreamStore
from cranetwin.bus.subjects import BusConfig
from cranetwin.ingest.config import DaemonConfig
from cranetwin.ingest.daemon import IngestDaemon, serve_store
from cranetwin.storage.live import LiveBus
from cranetwin.storage.shardmap import StoreSpec


def serve_to_bus(db_url: str | StoreSpec, bus: BusConfig, config: DaemonConfig | None = None,
                 live: LiveBus | None = None,
                 on_ready: Callable[[IngestDaemon], None] | None = None,
                 busy_timeout_s: float = 3.0) -> dict[str, Any]:
    """Run the daemon with its blocks going to ``bus`` until SIGTERM/SIGINT (blocking).

    Args:
        db_url: The database of machine keys and status reports (a URL, or a
            :class:`~cranetwin.storage.StoreSpec` with the shards).
        bus: The fleet bus.
        live: Live fan-out of published blocks (None: none; in a bus deployment the storage
            writers announce blocks after they are stored, so the daemons usually have none).
        on_ready, busy_timeout_s: As :func:`cranetwin.ingest.daemon.serve`.

    Returns:
        The final :meth:`IngestDaemon.snapshot`.
    """
    return serve_store(JetStreamStore.open_bus(db_url, bus, busy_timeout_s=busy_timeout_s),
                       config, live, on_ready)
