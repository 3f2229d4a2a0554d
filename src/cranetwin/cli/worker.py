"""``cranetwin worker``: the twin worker as its own process.

It replays every machine's stored samples in whole-minute windows into derived summaries, events
and progress counters (:mod:`cranetwin.service.worker`), on the database every process of the
deployment shares. Options left out fall back to the one settings object
(:class:`cranetwin.settings.Settings`, ``CRANETWIN_…``).

Scale-out: ``--partitions auto --of 16`` (or a fixed ``I/P``, ``0,3,5 --of 8``, ``all``) makes it
one of several workers, each processing only the machines of the partitions it owns through a
PostgreSQL advisory lock (:mod:`cranetwin.service.ownership`); the metrics endpoint then serves
per-partition lag. Without ``--partitions`` it processes every machine, without locks.

Lifecycle: prints ``cranetwin worker ready …`` once the store is open; SIGTERM or SIGINT ends it
after the window being replayed is committed (each window is one transaction, so a kill instead
loses nothing: the window is done again by the next run, or by the worker that takes over the
partition); exit status 0.

``cranetwin worker redo --machine ID --from T0 --to T1`` records an operator's redo request
(:mod:`cranetwin.storage.redo`): the running worker's next pass processes again every window of
the range behind the machine's watermark that holds stored samples — processed, failed or never
processed — and rolls its hours and days up again (after the machine's description changed, or
to retry windows skipped before failed spans were recorded). Exit status 2 on an error.
"""

from __future__ import annotations

import json
import logging
import signal
from types import FrameType

import typer

from cranetwin.settings import Settings, load_settings

log = logging.getLogger(__name__)

_DB_HELP = "sqlite:///… or postgresql://… (default: $CRANETWIN_DATABASE_URL, else " \
           "sqlite:///cranetwin.db)."


worker_app = typer.Typer(help="Run the twin worker (no command), or ask it to redo a range "
                         "(redo).", no_args_is_help=False, invoke_without_command=True)


@worker_app.callback(invoke_without_command=True)
def worker(
    ctx: typer.Context,
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    metrics_bind: str | None = typer.Option(
        None, help="HTTP address of the worker's Prometheus /metrics, HOST:PORT, or 0 for none "
                   "(default: $CRANETWIN_WORKER_METRICS_BIND, else 0)."),
    interval: float | None = typer.Option(
        None, min=0.01, help="Seconds between passes when caught up (default: "
                             "$CRANETWIN_WORKER_INTERVAL_S, else 1)."),
    partitions: str | None = typer.Option(
        None, help="Machine partitions to own: auto (a rebalanced share), all, I/P, or I,J,… "
                   "with --of (default: $CRANETWIN_WORKER_PARTITIONS, else every machine, "
                   "no locks)."),
    of: int | None = typer.Option(
        None, "--of", min=1, max=65536,
        help="Number of partitions P (default: $CRANETWIN_WORKER_PARTITION_COUNT, else 16)."),
    quiet_s: float | None = typer.Option(
        None, "--quiet-s", min=0.001,
        help="A machine silent this long gets its last window processed [s] (default: "
             "$CRANETWIN_WORKER_QUIET_S, else 60)."),
    threads: int | None = typer.Option(
        None, min=1, max=32,
        help="Machines replayed at once, in threads (default: $CRANETWIN_WORKER_THREADS, "
             "else 1)."),
    log_level: str = typer.Option("info", help="Log level."),
) -> None:
    """Run the twin worker: replay stored samples window by window into derived summaries,
    events and counters, until SIGTERM/SIGINT (``redo``: have it process a range again)."""
    if ctx.invoked_subcommand is not None:
        return
    from cranetwin.service.backend import Backend
    from cranetwin.service.metrics import Metrics
    from cranetwin.service.ownership import Ownership, PartitionSpecError, parse_partitions
    from cranetwin.service.worker import TwinWorker
    from cranetwin.storage import store_spec

    settings = load_settings(Settings, database_url=db, worker_metrics_bind=metrics_bind,
                             worker_interval_s=interval, worker_partitions=partitions,
                             worker_partition_count=of, worker_quiet_s=quiet_s,
                             worker_threads=threads)
    spec = None
    if settings.worker_partitions:
        try:
            given = "worker_partition_count" in settings.model_fields_set  # option or env
            spec = parse_partitions(settings.worker_partitions,
                                    settings.worker_partition_count if given else None)
        except PartitionSpecError as exc:
            raise typer.BadParameter(str(exc), param_hint="--partitions") from exc
    logging.basicConfig(level=log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    metrics = Metrics()
    bind = settings.worker_metrics_bind.strip()
    if bind not in ("0", "", "off"):
        from prometheus_client import start_http_server

        from cranetwin.cli.ingest import parse_bind

        host, port = parse_bind(bind, "--metrics-bind")
        start_http_server(port, addr=host, registry=metrics.registry)
    from cranetwin.service.warmup import warm_up
    from cranetwin.storage.engine import relax_commit_durability

    backend = Backend.open(store_spec(settings))
    for engine in backend.store.engines:  # derived data only: replayed again if lost
        relax_commit_durability(engine)
    own = None if spec is None else Ownership(spec, backend.store.engine)
    try:
        tw = TwinWorker(backend, settings, metrics, quiet_s=settings.worker_quiet_s,
                        ownership=own)

        def _stop(signum: int, frame: FrameType | None) -> None:
            log.info("%s: stopping after the current window", signal.Signals(signum).name)
            tw.stop_event.set()

        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
        part = "" if spec is None else (
            f", partitions {'auto' if spec.fixed is None else ','.join(map(str, spec.fixed))} "
            f"of {spec.count}" + ("" if own is not None and own.locked else " (no locks)"))
        warm_up()  # compiled kernels loaded before "ready": the first window waits for none
        typer.echo(f"cranetwin worker ready: {store_spec(settings).display()}, windows of "
                   f"{settings.worker_window_s:g} s{part}")
        windows = tw.run()
    finally:
        if own is not None:
            own.close()
        backend.close()
    typer.echo(f"cranetwin worker stopped: {windows} window(s) replayed")


@worker_app.command("redo")
def redo_cmd(
    machine: str = typer.Option(..., "--machine", "-m", help="Registered machine id."),
    t_from: str = typer.Option(..., "--from", help="Start of the range (epoch s or ISO 8601 "
                               "UTC)."),
    t_to: str = typer.Option(..., "--to", help="End of the range, exclusive."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the result as one JSON object."),
) -> None:
    """Have the twin worker process a machine's windows with from ≤ t < to again, at its next
    pass: every window behind its watermark that holds stored samples (processed, failed or
    never processed) is replayed with the machine's current description and payload, its hours
    and days rolled up again; windows ahead of the watermark are processed as they come. The
    request stays until the worker has done it (one recorded again meanwhile: once more)."""
    from cranetwin.cli.report import parse_time
    from cranetwin.errors import StorageError
    from cranetwin.service.backend import Backend
    from cranetwin.service.timerange import iso
    from cranetwin.storage import store_spec
    from cranetwin.storage.redo import survey

    settings = load_settings(Settings, database_url=db)
    t0, t1 = parse_time(t_from), parse_time(t_to)
    if t1 <= t0:
        raise StorageError(f"--to ({t_to}) must be after --from ({t_from})")
    win = settings.worker_window_s
    backend = Backend.open(store_spec(settings))
    try:
        req = backend.store.request_redo(machine, t0, t1)
        prog = backend.progress(machine)
        wm = None if prog is None else prog.watermark_s
        got = survey(backend.store.engine_for(machine), machine, req.t0_ns, req.t1_ns, win,
                     wm)
    finally:
        backend.close()
    a, z = iso(req.t0_ns / 1e9), iso((req.t1_ns + 1) / 1e9)
    if as_json:
        typer.echo(json.dumps({
            "machine": machine, "from": a, "to": z, "from_ns": req.t0_ns,
            "to_ns": req.t1_ns + 1, "version": req.version,
            "watermark": None if wm is None else iso(wm), "window_s": win,
            "windows": {"processed": got.processed, "failed": got.failed,
                        "never_processed": got.never, "ahead": got.ahead}}))
        return
    behind = got.processed + got.failed + got.never
    typer.echo(
        f"machine {machine}: redo of {a} – {z} requested (version {req.version}); "
        + ("nothing processed yet" if wm is None else f"watermark {iso(wm)}")
        + f"; windows of {win:g} s holding samples: {behind} behind the watermark "
        f"({got.processed} processed, {got.failed} failed, {got.never} never processed), "
        "redone at the twin worker's next pass"
        + (f"; {got.ahead} ahead of it, processed as they come" if got.ahead else ""))


def register(app: typer.Typer) -> None:
    """Add ``cranetwin worker`` (and ``cranetwin worker redo``)."""
    app.add_typer(worker_app, name="worker")
