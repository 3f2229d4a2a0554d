"""``cranetwin store-writer``: consume partitions of the fleet bus into the database.

Options left out fall back to the shared settings (``CRANETWIN_BUS_URL``,
``CRANETWIN_DATABASE_URL`` or the shards of ``CRANETWIN_STORAGE_SHARDS``,
``CRANETWIN_BUS_PARTITIONS``, ``CRANETWIN_STORE_WRITER_METRICS_BIND``, …; docs/BUS.md).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import sys
from typing import TYPE_CHECKING

import typer

from cranetwin.errors import CraneTwinError
from cranetwin.settings import Settings, load_settings

if TYPE_CHECKING:
    from cranetwin.bus.subjects import BusConfig


class PartitionsError(CraneTwinError):
    """``--partitions`` is not a list of partition numbers and ranges."""


def parse_partitions(spec: str, total: int) -> list[int]:
    """``all`` or ``0-3,7`` → partition numbers, each in 0..total − 1.

    Raises:
        PartitionsError: malformed, or a partition outside 0..total − 1.
    """
    if spec.strip() in ("", "all"):
        return list(range(total))
    out: set[int] = set()
    for part in spec.split(","):
        lo, _, hi = part.strip().partition("-")
        if not lo.isdigit() or (hi and not hi.isdigit()):
            raise PartitionsError(f"--partitions {spec!r}: expected 'all' or e.g. 0-3,7")
        a, b = int(lo), int(hi or lo)
        if a > b or b >= total:
            raise PartitionsError(f"--partitions {spec!r}: partitions are 0..{total - 1}")
        out.update(range(a, b + 1))
    return sorted(out)


def bus_config(st: Settings) -> BusConfig:
    """The :class:`~cranetwin.bus.subjects.BusConfig` of the settings (``bus_url`` set)."""
    from cranetwin.bus.subjects import BusConfig

    assert st.bus_url is not None
    return BusConfig(url=st.bus_url, stream=st.bus_stream, prefix=st.bus_prefix,
                     partitions=st.bus_partitions,
                     duplicate_window_s=st.bus_duplicate_window_s, max_msgs=st.bus_max_msgs,
                     publish_timeout_s=st.bus_publish_timeout_s, ack_wait_s=st.bus_ack_wait_s)


def store_writer(
    bus: str | None = typer.Option(None, "--bus", help="NATS server, nats://HOST:PORT "
                                   "(default: $CRANETWIN_BUS_URL)."),
    db: str | None = typer.Option(None, "--db", help="Database URL (default: "
                                  "$CRANETWIN_DATABASE_URL, else sqlite:///cranetwin.db)."),
    partitions: str = typer.Option("all", help="Partitions this writer owns: 'all' or e.g. "
                                   "0-3,7 (one writer per partition at a time)."),
    live: str | None = typer.Option(None, help="Live fan-out of stored blocks: nats://…, "
                                    "redis://… or postgresql://… (default: "
                                    "$CRANETWIN_LIVE_BUS_URL, else none)."),
    batch_max: int = typer.Option(1000, min=1, help="Blocks per transaction at most."),
    batch_wait: float = typer.Option(0.25, min=0.0, help="Longest wait of a delivered block "
                                     "for others to share its transaction [s] (delays "
                                     "storage, never a machine's ack)."),
    rollup_interval: float = typer.Option(30.0, min=0.1, help="Seconds between 1-min summary "
                                          "rollups [s] (one more at shutdown)."),
    metrics_bind: str | None = typer.Option(
        None, "--metrics-bind", help="HTTP address of the Prometheus /metrics, HOST:PORT, or 0 "
        "for none (default: $CRANETWIN_STORE_WRITER_METRICS_BIND, else 0)."),
    log_level: str = typer.Option("INFO", help="Logging level."),
) -> None:
    """Store the blocks of the fleet bus (JetStream) in the database; ack after commit.

    Prints one JSON line on stdout once consuming: {"event": "ready", "partitions": [...],
    "pid": N, "metrics": "http://HOST:PORT/metrics" or null, "store": where it stores (no
    password)}, and one after SIGTERM/SIGINT: {"event": "stopped", <counters>}.
    """
    from cranetwin.bus.consumer import StoreWriter, WriterConfig
    from cranetwin.cli.ingest import parse_bind
    from cranetwin.storage import open_store, store_spec
    from cranetwin.storage.live import open_bus
    from cranetwin.storage.nats_loop import run_bounded

    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: "
                        "%(message)s")
    st = load_settings(Settings, bus_url=bus, database_url=db, live_bus_url=live,
                       store_writer_metrics_bind=metrics_bind)
    if not st.bus_url:
        raise PartitionsError("no bus: give --bus nats://HOST:PORT or set CRANETWIN_BUS_URL")
    cfg = bus_config(st)
    parts = parse_partitions(partitions, cfg.partitions)
    bind = st.store_writer_metrics_bind.strip()
    where = None if bind in ("0", "", "off") else parse_bind(bind, "--metrics-bind")
    spec = store_spec(st)
    live_bus = open_bus(st.live_bus_url) if st.live_bus_url else None
    store = open_store(spec)
    server = None
    try:
        writer = StoreWriter(store, cfg, parts, live_bus, WriterConfig(
            batch_max=batch_max, batch_wait_s=batch_wait, rollup_interval_s=rollup_interval,
            # the lag gauge costs a JetStream request per partition every 5 s: only when served
            lag_interval_s=WriterConfig.lag_interval_s if where is not None else 0.0))
        metrics_url = None
        if where is not None:
            from prometheus_client import start_http_server

            server, _ = start_http_server(where[1], addr=where[0],
                                          registry=writer.metrics.registry)
            host, port = server.server_address[:2]
            host = str(host)
            metrics_url = f"http://{host if ':' not in host else f'[{host}]'}:{port}/metrics"

        async def main() -> dict[str, object]:
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, writer.stop)

            async def announce() -> None:
                await writer.ready.wait()
                sys.stdout.write(json.dumps({"event": "ready", "partitions": parts,
                                             "pid": os.getpid(), "metrics": metrics_url,
                                             "store": spec.display()}) + "\n")
                sys.stdout.flush()

            task = asyncio.create_task(announce())
            try:
                return await writer.run()
            finally:
                task.cancel()

        final = run_bounded(main())
    finally:
        if server is not None:
            server.shutdown()
        if live_bus is not None:
            live_bus.close()
        store.close()
    sys.stdout.write(json.dumps({"event": "stopped", **final}) + "\n")
    sys.stdout.flush()


def register(app: typer.Typer) -> None:
    app.command("store-writer")(store_writer)
