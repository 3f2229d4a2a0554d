"""Engines for the two supported databases, and schema migration to the newest revision.

SQLite (the embedded default, ``sqlite:///cranetwin.db``) runs in WAL mode with
``synchronous=FULL``, so a committed transaction survives a crash of the process or the machine;
PostgreSQL is reached by URL (``postgresql+psycopg://user@host:5432/db``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, SQLAlchemyError

from cranetwin.errors import StorageError

log = logging.getLogger(__name__)

DEFAULT_URL = "sqlite:///cranetwin.db"
MIGRATIONS = Path(__file__).with_name("migrations")


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=FULL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def make_engine(url: str, *, echo: bool = False) -> Engine:
    """Create an engine for ``url`` (SQLite or PostgreSQL), configured for durable writes.

    Args:
        url: SQLAlchemy URL, e.g. ``sqlite:///cranetwin.db`` or
            ``postgresql+psycopg://postgres@127.0.0.1:5432/test``. A bare ``postgresql://`` URL
            uses psycopg 3.
        echo: Log every SQL statement.

    Raises:
        StorageError: The URL is malformed or names an unsupported database.
    """
    try:
        u = make_url(url)
    except ArgumentError as exc:
        raise StorageError(f"bad database URL {url!r}: {exc}; expected e.g. {DEFAULT_URL}") from exc
    backend = u.get_backend_name()
    if backend == "postgresql" and u.drivername == "postgresql":
        u = u.set(drivername="postgresql+psycopg")
    if backend == "sqlite":
        engine = create_engine(u, echo=echo, connect_args={"check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    if backend == "postgresql":
        return create_engine(u, echo=echo, pool_pre_ping=True)
    raise StorageError(f"unsupported database {backend!r} in {url!r}; "
                       "expected sqlite or postgresql")


def migrate(engine: Engine, revision: str = "head") -> None:
    """Apply the Alembic migrations shipped in ``cranetwin.storage.migrations`` up to ``revision``.

    Raises:
        StorageError: The database could not be reached or a migration failed.
    """
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    try:
        with engine.begin() as conn:
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, revision)
    except SQLAlchemyError as exc:
        raise StorageError(f"could not migrate {engine.url.render_as_string()}: {exc}") from exc
