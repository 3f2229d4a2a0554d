"""The ingest daemon writing to the fleet bus instead of the database (docs/BUS.md).

:func:`serve_to_bus` is :func:`cranetwin.ingest.daemon.serve` with the store replaced by a
:class:`~cranetwin.bus.sink.JetStreamStore`: machine keys and status reports still come from and
go to the database at ``db_url``; sample blocks go to JetStream, and a machine is acknowledged
once the PubAcks of its blocks are in. The daemon itself is unchanged.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from cranetwin.bus.sink import JetStreamStore
from cranetwin.bus.subjects import BusConfig
from cranetwin.ingest.config import DaemonConfig
from cranetwin.ingest.daemon import IngestDaemon
from cranetwin.ingest.sockets import new_event_loop
from cranetwin.storage.live import LiveBus


def serve_to_bus(db_url: str, bus: BusConfig, config: DaemonConfig | None = None,
                 live: LiveBus | None = None,
                 on_ready: Callable[[IngestDaemon], None] | None = None,
                 busy_timeout_s: float = 3.0) -> dict[str, Any]:
    """Run the daemon with its blocks going to ``bus`` until SIGTERM/SIGINT (blocking).

    Args:
        db_url: The database of machine keys and status reports.
        bus: The fleet bus.
        live: Live fan-out of published blocks (None: none; in a bus deployment the storage
            writers announce blocks after they are stored, so the daemons usually have none).
        on_ready, busy_timeout_s: As :func:`cranetwin.ingest.daemon.serve`.

    Returns:
        The final :meth:`IngestDaemon.snapshot`.
    """
    store = JetStreamStore.open_bus(db_url, bus, busy_timeout_s=busy_timeout_s)
    try:
        daemon = IngestDaemon(store, config, live)
        with asyncio.Runner(loop_factory=new_event_loop) as runner:
            runner.run(daemon.serve(on_ready=on_ready))
        return daemon.snapshot()
    finally:
        if live is not None:
            live.close()
        store.close()
