"""``cranetwin db upgrade``: migrate the database, or every shard of the shard map, to the
newest schema (every command also migrates on start; this does it alone, e.g. before a
rolling upgrade or after adding a shard)."""

from __future__ import annotations

import typer

from cranetwin.settings import Settings, load_settings

db_app = typer.Typer(help="Database schema: migrate the database or every shard.",
                     no_args_is_help=True)


@db_app.command("upgrade")
def upgrade(
    db: str | None = typer.Option(None, "--db", help="Database URL (default: "
                                  "$CRANETWIN_DATABASE_URL; with $CRANETWIN_STORAGE_SHARDS set, "
                                  "every shard of the map instead)."),
) -> None:
    """Apply the migrations up to the newest revision on the database or on every shard;
    prints one line per database (passwords hidden). Exit status 2 if one fails."""
    from cranetwin.errors import StorageError
    from cranetwin.storage import store_spec
    from cranetwin.storage.engine import display_url, make_engine, migrate

    spec = store_spec(load_settings(Settings, database_url=db))
    m = spec.shard_map()
    urls = [spec.url] if m is None else list(m.urls)
    failed = 0
    for i, url in enumerate(urls):
        name = display_url(url) if m is None else f"shard {i} ({m.describe()[i]})"
        engine = make_engine(url)
        try:
            migrate(engine)
            typer.echo(f"{name}: at the newest revision")
        except StorageError as exc:
            failed += 1
            typer.echo(f"{name}: FAILED: {exc}", err=True)
        finally:
            engine.dispose()
    if failed:
        raise StorageError(f"{failed} of {len(urls)} database(s) not migrated (see above)")


def register(app: typer.Typer) -> None:
    """Add ``cranetwin db``."""
    app.add_typer(db_app, name="db")
