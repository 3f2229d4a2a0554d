"""``cranetwin worker``: the twin worker as its own process.

It replays every machine's stored samples in whole-minute windows into derived summaries, events
and progress counters (:mod:`cranetwin.service.worker`), on the database every process of the
deployment shares. Options left out fall back to the one settings object
(:class:`cranetwin.settings.Settings`, ``CRANETWIN_…``).

Lifecycle: prints ``cranetwin worker ready …`` once the store is open; SIGTERM or SIGINT ends it
after the window being replayed is committed (each window is one transaction, so a kill instead
loses nothing: the window is done again by the next run); exit status 0.
"""

from __future__ import annotations

import logging
import signal
from types import FrameType

import typer

from cranetwin.settings import Settings, load_settings

log = logging.getLogger(__name__)

_DB_HELP = "sqlite:///… or postgresql://… (default: $CRANETWIN_DATABASE_URL, else " \
           "sqlite:///cranetwin.db)."


def worker(
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    metrics_bind: str | None = typer.Option(
        None, help="HTTP address of the worker's Prometheus /metrics, HOST:PORT, or 0 for none "
                   "(default: $CRANETWIN_WORKER_METRICS_BIND, else 0)."),
    interval: float | None = typer.Option(
        None, min=0.01, help="Seconds between passes when caught up (default: "
                             "$CRANETWIN_WORKER_INTERVAL_S, else 1)."),
    log_level: str = typer.Option("info", help="Log level."),
) -> None:
    """Run the twin worker: replay stored samples window by window into derived summaries,
    events and counters, until SIGTERM/SIGINT."""
    from cranetwin.service.backend import Backend
    from cranetwin.service.metrics import Metrics
    from cranetwin.service.worker import TwinWorker
    from cranetwin.storage.engine import display_url

    settings = load_settings(Settings, database_url=db, worker_metrics_bind=metrics_bind,
                             worker_interval_s=interval)
    logging.basicConfig(level=log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    metrics = Metrics()
    bind = settings.worker_metrics_bind.strip()
    if bind not in ("0", "", "off"):
        from prometheus_client import start_http_server

        from cranetwin.cli.ingest import parse_bind

        host, port = parse_bind(bind, "--metrics-bind")
        start_http_server(port, addr=host, registry=metrics.registry)
    backend = Backend.open(settings.database_url)
    try:
        tw = TwinWorker(backend, settings, metrics)

        def _stop(signum: int, frame: FrameType | None) -> None:
            log.info("%s: stopping after the current window", signal.Signals(signum).name)
            tw.stop_event.set()

        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
        typer.echo(f"cranetwin worker ready: {display_url(settings.database_url)}, windows of "
                   f"{settings.worker_window_s:g} s")
        windows = tw.run()
    finally:
        backend.close()
    typer.echo(f"cranetwin worker stopped: {windows} window(s) replayed")


def register(app: typer.Typer) -> None:
    """Add ``cranetwin worker``."""
    app.command("worker")(worker)
