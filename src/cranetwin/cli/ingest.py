"""``cranetwin ingest`` (the UDP daemon) and ``cranetwin machines add|list`` (registration).

Every option left out falls back to the shared settings (:class:`cranetwin.settings.Settings`,
environment ``CRANETWIN_…``): ``--db`` to ``CRANETWIN_DATABASE_URL``, ``--bind`` to
``CRANETWIN_INGEST_BIND``, ``--metrics-bind`` to ``CRANETWIN_INGEST_METRICS_BIND``, ``--live`` to
``CRANETWIN_LIVE_BUS_URL`` and so on, then to the defaults shown by ``--help``.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import stat
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from cranetwin.errors import CraneTwinError
from cranetwin.settings import Settings, load_settings

if TYPE_CHECKING:
    from cranetwin.bus.subjects import BusConfig
    from cranetwin.ingest.config import DaemonConfig
    from cranetwin.storage import StoreSpec

machines_app = typer.Typer(help="Register machines (wire id and HMAC secret) and list them.",
                           no_args_is_help=True)

SECRET_ENV = "CRANETWIN_MACHINE_SECRET"
_DB_HELP = "sqlite:///… or postgresql://… (default: $CRANETWIN_DATABASE_URL, else " \
           "sqlite:///cranetwin.db)."


class CliError(CraneTwinError):
    """A command-line option is unusable (printed as one line, exit status 2)."""


def parse_bind(bind: str, option: str = "--bind") -> tuple[str, int]:
    """``HOST:PORT`` (IPv6 as ``[::1]:5005``) → (host, port).

    Raises:
        CliError: not HOST:PORT, or the port outside 0..65535.
    """
    host, sep, port = bind.strip().rpartition(":")
    host = host.strip()
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit():
        raise CliError(f"{option} must be HOST:PORT (e.g. 127.0.0.1:5005), got {bind!r}")
    if int(port) > 65535:
        raise CliError(f"{option} {bind!r}: port {port} outside 0..65535")
    return host, int(port)


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def ingest(
    bind: str | None = typer.Option(
        None, help="UDP address to listen on, HOST:PORT (default: $CRANETWIN_INGEST_BIND, else "
                   "127.0.0.1:5005)."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    metrics_bind: str | None = typer.Option(
        None, help="HTTP address of the Prometheus /metrics endpoint, HOST:PORT (port 0: any "
                   "free port), or 0 to serve none (default: $CRANETWIN_INGEST_METRICS_BIND, "
                   "else 127.0.0.1:9105)."),
    metrics_interval: float = typer.Option(10.0, min=0.01,
                                           help="Seconds between metrics log lines [s]."),
    live: str | None = typer.Option(
        None, help="Fan-out bus: postgresql://… or redis://H:P (default: "
                   "$CRANETWIN_LIVE_BUS_URL, else none)."),
    queue_max: int | None = typer.Option(None, min=1,
                                         help="Datagrams accepted and not yet decoded at "
                                              "most (default 50000)."),
    batch_max: int | None = typer.Option(None, min=1,
                                         help="Datagrams decoded together, blocks written "
                                              "per transaction at most (default 1000)."),
    batch_wait: float | None = typer.Option(None, min=0.0,
                                            help="Seconds a batch is gathered after its "
                                                 "first datagram [s] (default 0.05)."),
    max_past: float | None = typer.Option(
        None, help="Oldest sample time accepted, before the server clock [s] (default 400 "
                   "days); older datagrams are refused (bad_time)."),
    max_future: float | None = typer.Option(
        None, help="Newest sample time accepted, after the server clock [s] (default 300)."),
    range_margin: float | None = typer.Option(
        None, help="Share of each sensor's [min, max] span a value may lie beyond it (default "
                   "0.1); beyond, the datagram is refused (out_of_range)."),
    shutdown_timeout: float | None = typer.Option(
        None, help="Longest flush of queued datagrams on SIGTERM while the database is "
                   "writable [s] (default 60); during an outage the daemon exits in ~5 s."),
    rollup_interval: float = typer.Option(  # fleet bus work: benchmarks set it beyond the run
        30.0, min=0.1, help="Seconds between 1-min summary rollups [s] (one more at shutdown)."),
    bus: str | None = typer.Option(  # fleet bus (docs/BUS.md)
        None, "--bus", help="Publish blocks to the NATS JetStream fleet bus nats://HOST:PORT "
                            "instead of writing them to the database (acked after the PubAck; "
                            "`cranetwin store-writer` stores them) (default: $CRANETWIN_BUS_URL, "
                            "else none)."),
    log_level: str = typer.Option("INFO", help="Logging level."),
    processes: int = typer.Option(
        1, min=1, max=64, help="Daemon processes sharing the UDP address (SO_REUSEPORT; each "
                               "machine always served by process wire_id % N; a dead one is "
                               "restarted). Linux only. Metrics of process i on PORT + i."),
) -> None:
    """Receive machine datagrams over UDP and store them (ack after commit; SIGTERM flushes).

    Prints one JSON line on stdout once listening: {"event": "ready", "udp": "HOST:PORT",
    "metrics": "http://HOST:PORT/metrics" or null, "pid": N}, and one after a graceful stop:
    {"event": "stopped", <final counters>}. Logs go to stderr. With --processes N > 1 the
    ready line has "metrics" as a list and "children" (index, pid, metrics) and the stopped
    line the summed counters, "restarts" and per child its own under "children".
    """
    from cranetwin.ingest.daemon import DaemonConfig, IngestDaemon, serve
    from cranetwin.protocol import Limits
    from cranetwin.storage import store_spec
    from cranetwin.storage.live import open_bus

    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: "
                        "%(message)s")
    st = load_settings(Settings, database_url=db, ingest_bind=bind,
                       ingest_metrics_bind=metrics_bind, live_bus_url=live,
                       ingest_queue_max=queue_max, ingest_batch_max=batch_max,
                       ingest_batch_wait_s=batch_wait, ingest_max_past_s=max_past,
                       ingest_max_future_s=max_future, ingest_range_margin=range_margin,
                       ingest_shutdown_timeout_s=shutdown_timeout, bus_url=bus)
    host, port = parse_bind(st.ingest_bind)
    mhost: str | None = None
    mport = 0
    if st.ingest_metrics_bind.strip() not in ("0", "", "off"):
        mhost, mport = parse_bind(st.ingest_metrics_bind, "--metrics-bind")
    cfg = DaemonConfig(host=host, port=port, metrics_host=mhost, metrics_port=mport,
                       metrics_interval_s=metrics_interval, rollup_interval_s=rollup_interval,
                       queue_max=st.ingest_queue_max, batch_max=st.ingest_batch_max,
                       batch_wait_s=st.ingest_batch_wait_s,
                       shutdown_timeout_s=st.ingest_shutdown_timeout_s,
                       limits=Limits(max_past_s=st.ingest_max_past_s,
                                     max_future_s=st.ingest_max_future_s,
                                     range_margin=st.ingest_range_margin))

    if processes > 1:
        from cranetwin.cli.store_writer import bus_config

        _run_group(store_spec(st), cfg, processes, st.live_bus_url, st.ingest_busy_timeout_s,
                   log_level, bus_config(st) if st.bus_url else None)
        return

    def ready(d: IngestDaemon) -> None:
        h, p = d.address or (host, port)
        udp = f"{h}:{p}" if ":" not in h else f"[{h}]:{p}"
        sys.stdout.write(json.dumps({"event": "ready", "udp": udp, "metrics": d.metrics_url,
                                     "pid": os.getpid()}) + "\n")
        sys.stdout.flush()

    live_bus = open_bus(st.live_bus_url) if st.live_bus_url else None
    if st.bus_url:  # fleet bus (docs/BUS.md): blocks to JetStream, the database for keys/status
        from cranetwin.cli.store_writer import bus_config
        from cranetwin.ingest.bus_serve import serve_to_bus

        final = serve_to_bus(store_spec(st), bus_config(st), cfg, live_bus, on_ready=ready,
                             busy_timeout_s=st.ingest_busy_timeout_s)
    else:
        final = serve(store_spec(st), cfg, live_bus, on_ready=ready,
                      busy_timeout_s=st.ingest_busy_timeout_s)
    sys.stdout.write(json.dumps({"event": "stopped", **final}) + "\n")
    sys.stdout.flush()


def _run_group(db_url: StoreSpec, cfg: DaemonConfig, processes: int, live_url: str | None,
               busy_timeout_s: float, log_level: str, bus: BusConfig | None) -> None:
    """``--processes N``: the parent of N daemon processes (blocking until SIGTERM/SIGINT),
    each publishing to ``bus`` if given."""
    from cranetwin.ingest.processes import ProcessGroup

    def ready(g: ProcessGroup) -> None:
        info = g.ready_info()
        sys.stdout.write(json.dumps({"event": "ready", **info, "metrics": [
            c["metrics"] for c in info["children"]]}) + "\n")
        sys.stdout.flush()

    group = ProcessGroup(db_url, cfg, processes, live_url=live_url,
                         busy_timeout_s=busy_timeout_s, log_level=log_level, bus=bus)
    final = group.run(on_ready=ready)
    sys.stdout.write(json.dumps({"event": "stopped", **final}) + "\n")
    sys.stdout.flush()


# --- machines ----------------------------------------------------------------------------------
def _read_secret_file(path: Path) -> str:
    try:
        mode = path.stat().st_mode
        text = path.read_text()
    except OSError as exc:
        raise CliError(f"--secret-file {path}: cannot read: {exc.strerror or exc}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        typer.echo(f"warning: {path} is readable by other users (chmod 600 it)", err=True)
    return text


def _parse_secret(text: str, where: str) -> bytes:
    t = text.strip()
    try:
        key = bytes.fromhex(t)
    except ValueError:
        raise CliError(f"{where}: the secret must be hex digits (≥ 32 of them)") from None
    if len(key) < 16:
        raise CliError(f"{where}: the secret must be at least 16 bytes (32 hex digits), "
                       f"got {len(key)}")
    return key


def _model_text(model: str) -> tuple[str, str]:
    """(text to store, source name): a built-in name as is, else the file's TOML text."""
    from cranetwin.model import builtin_machines

    if model in builtin_machines():
        return model, model
    path = Path(model)
    try:
        return path.read_text("utf-8"), str(path)
    except FileNotFoundError:
        raise CliError(f"--model {model!r}: no such file, and not a built-in machine "
                       f"({', '.join(builtin_machines())})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CliError(f"--model {model}: cannot read: {exc}") from None


def _open_secret_out(path: Path) -> int:
    try:
        return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise CliError(f"--secret-out {path}: exists; not overwritten") from None
    except OSError as exc:
        raise CliError(f"--secret-out {path}: cannot create: {exc.strerror or exc}") from None


@machines_app.command("add")
def add(
    machine_id: str = typer.Argument(..., help="Machine identifier, e.g. crane-17."),
    wire_id: int = typer.Option(..., help="32-bit id the machine sends in its datagrams."),
    secret_file: Path | None = typer.Option(
        None, help="File holding the HMAC key as hex (≥ 32 hex digits). Else "
                   f"${SECRET_ENV}; neither: a random 32-byte key is generated."),
    secret_out: Path | None = typer.Option(
        None, help="Write a generated secret to this new file (mode 0600) instead of printing "
                   "it."),
    secret: str | None = typer.Option(None, hidden=True,
                                      help="Refused: secrets on the command line are visible "
                                           "to every user."),
    model: str = typer.Option("patu655", help="Built-in machine name or a machine TOML file "
                                              "(validated before it is registered)."),
    metadata: str = typer.Option("{}", help="JSON object of free-form metadata."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
) -> None:
    """Register a machine. A generated secret is printed once (or written to --secret-out)."""
    from cranetwin.ingest.daemon import check_model
    from cranetwin.storage import open_store, store_spec

    if secret is not None:
        raise _fail("--secret is refused: a secret on the command line is visible to every user "
                    f"(/proc/PID/cmdline); use --secret-file PATH or ${SECRET_ENV}")
    env_secret = os.environ.get(SECRET_ENV)
    if secret_file is not None and env_secret:
        raise CliError(f"give the secret once: --secret-file or ${SECRET_ENV}, not both")
    key: bytes | None = None
    if secret_file is not None:
        key = _parse_secret(_read_secret_file(secret_file), f"--secret-file {secret_file}")
    elif env_secret:
        key = _parse_secret(env_secret, f"${SECRET_ENV}")
    if key is not None and secret_out is not None:
        raise CliError("--secret-out is for a generated secret; this one was given")
    try:
        meta = json.loads(metadata)
    except json.JSONDecodeError as exc:
        raise CliError(f"--metadata must be a JSON object: {exc}") from None
    if not isinstance(meta, dict):
        raise CliError("--metadata must be a JSON object")
    model_text, source = _model_text(model)
    check_model(model_text, source)  # MachineFileError lists every "field.path: problem"
    generated = key is None
    if key is None:
        key = secrets.token_bytes(32)
    st = load_settings(Settings, database_url=db)
    fd = _open_secret_out(secret_out) if secret_out is not None else None
    try:
        with open_store(store_spec(st)) as store:
            info = store.add_machine(machine_id, wire_id, key, model=model_text, metadata=meta)
    except BaseException:
        if fd is not None and secret_out is not None:
            os.close(fd)
            secret_out.unlink(missing_ok=True)
        raise
    typer.echo(f"registered {info.machine_id} (wire id {info.wire_id})")
    if fd is not None:
        with os.fdopen(fd, "w") as f:
            f.write(key.hex() + "\n")
        typer.echo(f"secret written to {secret_out} (mode 0600)")
    elif generated:
        typer.echo(f"secret (hex, shown once): {key.hex()}")


@machines_app.command("list")
def list_(
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """List registered machines (never their secrets)."""
    from cranetwin.storage import open_store, store_spec

    st = load_settings(Settings, database_url=db)
    with open_store(store_spec(st)) as store:
        ms = store.machines()
    if as_json:
        typer.echo(json.dumps([m.__dict__ for m in ms], indent=1))
        return
    for m in ms:
        model = m.model if "\n" not in m.model else "<toml>"
        seen = "never" if m.last_seen_s is None else f"{m.last_seen_s:.3f}"
        typer.echo(f"{m.machine_id}\twire {m.wire_id}\tmodel {model}\tlast seen {seen}")


def register(app: typer.Typer) -> None:
    app.command("ingest")(ingest)
    app.add_typer(machines_app, name="machines")
