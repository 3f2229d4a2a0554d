"""``cranetwin ingest`` (the UDP daemon) and ``cranetwin machines add|list`` (registration)."""

from __future__ import annotations

import json
import logging
import secrets
from pathlib import Path

import typer

from cranetwin.errors import StorageError
from cranetwin.storage.engine import DEFAULT_URL

machines_app = typer.Typer(help="Register machines (wire id and HMAC secret) and list them.",
                           no_args_is_help=True)


def _parse_bind(bind: str) -> tuple[str, int]:
    host, sep, port = bind.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise StorageError(f"--bind must be HOST:PORT (e.g. 127.0.0.1:5005), got {bind!r}")
    return host.strip("[]"), int(port)


def ingest(
    bind: str = typer.Option("127.0.0.1:5005", help="UDP address to listen on, HOST:PORT."),
    db: str = typer.Option(DEFAULT_URL, "--db", help="sqlite:///… or postgresql://…"),
    metrics_file: Path | None = typer.Option(None, help="JSON metrics file (rewritten)."),
    metrics_interval: float = typer.Option(10.0, help="Seconds between metrics log lines/files."),
    live: str | None = typer.Option(None, help="Fan-out bus: postgresql://… or redis://H:P."),
    queue_max: int = typer.Option(50_000, help="Datagrams waiting for the writer at most."),
    batch_wait: float = typer.Option(0.05, help="Seconds the writer gathers a batch."),
    log_level: str = typer.Option("INFO", help="Logging level."),
) -> None:
    """Receive machine datagrams over UDP and store them (ack after commit; SIGTERM flushes)."""
    from cranetwin.ingest.daemon import DaemonConfig, serve
    from cranetwin.storage.live import open_bus

    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: "
                        "%(message)s")
    host, port = _parse_bind(bind)
    cfg = DaemonConfig(host=host, port=port, metrics_path=metrics_file,
                       metrics_interval_s=metrics_interval, queue_max=queue_max,
                       batch_wait_s=batch_wait)
    serve(db, cfg, open_bus(live) if live else None)


@machines_app.command("add")
def add(
    machine_id: str = typer.Argument(..., help="Machine identifier, e.g. crane-17."),
    wire_id: int = typer.Option(..., help="32-bit id the machine sends in its datagrams."),
    secret: str | None = typer.Option(None, help="HMAC key as hex (≥ 32 hex digits); "
                                      "omitted: a random 32-byte key is generated and printed."),
    model: str = typer.Option("patu655", help="Built-in machine name or a machine TOML file."),
    metadata: str = typer.Option("{}", help="JSON object of free-form metadata."),
    db: str = typer.Option(DEFAULT_URL, "--db", help="Database URL."),
) -> None:
    """Register a machine. Prints the secret once when it was generated here."""
    from cranetwin.storage import Store

    try:
        key = bytes.fromhex(secret) if secret else secrets.token_bytes(32)
    except ValueError as exc:
        raise StorageError(f"--secret must be hex digits: {exc}") from exc
    try:
        meta = json.loads(metadata)
    except json.JSONDecodeError as exc:
        raise StorageError(f"--metadata must be a JSON object: {exc}") from exc
    path = Path(model)
    model_text = path.read_text() if path.suffix == ".toml" and path.exists() else model
    with Store.open(db) as store:
        info = store.add_machine(machine_id, wire_id, key, model=model_text, metadata=meta)
    typer.echo(f"registered {info.machine_id} (wire id {info.wire_id})")
    if not secret:
        typer.echo(f"secret (hex, shown once): {key.hex()}")


@machines_app.command("list")
def list_(
    db: str = typer.Option(DEFAULT_URL, "--db", help="Database URL."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """List registered machines (never their secrets)."""
    from cranetwin.storage import Store

    with Store.open(db) as store:
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
