"""``cranetwin serve`` (the HTTP API with uvicorn) and ``cranetwin keys create|list|revoke``.

Options left out fall back to the one settings object (:class:`cranetwin.settings.Settings`,
``CRANETWIN_…``). The twin worker is its own process (``cranetwin worker``); ``serve --worker``
(or ``CRANETWIN_WORKER_IN_PROCESS=1``) runs it inside the API process instead, for a one-process
setup.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime

import typer

from cranetwin.settings import Settings, load_settings

keys_app = typer.Typer(help="API keys: create (shown once), list, revoke.", no_args_is_help=True)

_DB_HELP = "Database URL (default: CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."


def _settings(db: str | None, **overrides: object) -> Settings:
    return load_settings(Settings, database_url=db, **overrides)


def serve(
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    host: str | None = typer.Option(None, help="Bind address (default 127.0.0.1)."),
    port: int | None = typer.Option(None, help="TCP port (default 8000)."),
    worker: bool | None = typer.Option(
        None, "--worker/--no-worker",
        help="Run the twin worker inside this process (default: "
             "$CRANETWIN_WORKER_IN_PROCESS, else no: run `cranetwin worker`)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
) -> None:
    """Serve the HTTP API and live websockets (uvicorn, uvloop when available)."""
    import uvicorn

    from cranetwin.api import create_app

    settings = _settings(db, host=host, port=port, worker_in_process=worker)
    logging.basicConfig(level=log_level.upper())
    app = create_app(settings)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=log_level,
                loop="auto", ws="websockets", lifespan="on")


@keys_app.command("create")
def create(
    role: str = typer.Option(..., help="viewer, fleet or admin."),
    name: str = typer.Option("", help="A label (who or what uses the key)."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
) -> None:
    """Create a key and print it (only its hash is stored: copy it now)."""
    from cranetwin.service.backend import Backend
    from cranetwin.service.keys import ROLES
    from cranetwin.storage import store_spec

    if role not in ROLES:
        raise typer.BadParameter(f"{role!r}: expected one of {', '.join(ROLES)}",
                                 param_hint="--role")
    backend = Backend.open(store_spec(_settings(db)))
    try:
        _, token = backend.create_key(role, name)
    finally:
        backend.close()
    typer.echo(token)


@keys_app.command("list")
def list_keys(db: str | None = typer.Option(None, "--db", help=_DB_HELP)) -> None:
    """List keys (id, role, name, created, revoked); secrets are not stored."""
    from cranetwin.service.backend import Backend
    from cranetwin.storage import apikeys, store_spec

    backend = Backend.open(store_spec(_settings(db)))
    try:
        with backend.session() as s:
            rows = apikeys.list_keys(s)
    finally:
        backend.close()

    def when(t: float | None) -> str:
        return "-" if t is None else datetime.fromtimestamp(t, UTC).isoformat(timespec="seconds")

    for k in rows:
        typer.echo(f"{k.key_id}  {k.role:6}  created {when(k.created_s)}  "
                   f"revoked {when(k.revoked_s)}  {k.name}")


@keys_app.command("revoke")
def revoke(key_id: str = typer.Argument(..., help="The key id (12 hex digits after ctk_)."),
           db: str | None = typer.Option(None, "--db", help=_DB_HELP)) -> None:
    """Revoke a key (servers stop accepting it within 10 s)."""
    from cranetwin.service.backend import Backend
    from cranetwin.storage import apikeys, store_spec

    backend = Backend.open(store_spec(_settings(db)))
    try:
        with backend.session() as s, s.begin():
            found = apikeys.revoke_key(s, key_id)
    finally:
        backend.close()
    if not found:
        typer.echo(f"no key {key_id!r}", err=True)
        raise typer.Exit(1)
    typer.echo(f"revoked {key_id}")


def register(app: typer.Typer) -> None:
    app.command("serve")(serve)
    app.add_typer(keys_app, name="keys")
