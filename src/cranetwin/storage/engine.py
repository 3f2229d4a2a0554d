"""Engines for the two supported databases, and schema migration to the newest revision.

SQLite (the embedded default, ``sqlite:///cranetwin.db``) runs in WAL mode with
``synchronous=FULL``, so a committed transaction survives a crash of the process or the machine;
PostgreSQL is reached by URL (``postgresql+psycopg://user@host:5432/db``).

The SQLite file holds the machines' HMAC secrets: a new database file is created with mode 0600
before SQLite opens it, and SQLite gives its ``-wal``, ``-shm`` and ``-journal`` files the mode of
the database file; an existing file readable by others is left as it is, with a warning.

After an outage the engines reconnect by themselves: PostgreSQL connections are checked before
use (``pool_pre_ping``; one dropped by the server or a restart is replaced), a connection lost in
a transaction is discarded with the rest of the pool, new connections time out after
:data:`PG_CONNECT_TIMEOUT_S` and TCP keepalives notice a silent peer.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, SQLAlchemyError

from cranetwin.errors import StorageError
from cranetwin.storage.dberrors import is_unavailable, unavailable

log = logging.getLogger(__name__)

DEFAULT_URL = "sqlite:///cranetwin.db"
MIGRATIONS = Path(__file__).with_name("migrations")
BUSY_TIMEOUT_S = 30.0
"""How long a SQLite write waits for another writer's lock before failing [s]."""
PG_CONNECT_TIMEOUT_S = 10
"""How long opening a PostgreSQL connection may take [s]."""
_PG_KEEPALIVES = {"keepalives": 1, "keepalives_idle": 30, "keepalives_interval": 10,
                  "keepalives_count": 3}


def _sqlite_pragmas(busy_timeout_s: float) -> Any:
    ms = max(0, round(busy_timeout_s * 1000))

    def on_connect(dbapi_conn: Any, _record: Any) -> None:
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA synchronous=FULL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute(f"PRAGMA busy_timeout={ms}")
        cur.close()

    return on_connect


def display_url(url: str) -> str:
    """A database URL fit for a log line or a report: the password hidden (``***``), and
    only the host part when the URL does not parse."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except (ArgumentError, ValueError):
        return url.rsplit("@", 1)[-1]


def sqlite_path(u: URL) -> Path | None:
    """The file of a SQLite URL, or None for an in-memory or URI-style database."""
    db = u.database
    if not db or db == ":memory:" or db.startswith("file:") or "mode" in u.query:
        return None
    return Path(db)


def create_private(path: Path) -> None:
    """Create ``path`` empty with mode 0600 unless it exists (then warn if group or others may
    read or write it). SQLite treats an empty file as a new database."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except FileExistsError:
        try:
            mode = path.stat().st_mode & 0o777
        except OSError:
            return
        if mode & 0o077:
            log.warning("database file %s has mode %03o: it holds the machines' secrets; "
                        "make it private with chmod 600", path, mode)
        return
    except OSError:
        return  # no such directory, ...: SQLite reports it with the database's own error
    os.close(fd)


def make_engine(url: str, *, echo: bool = False,
                busy_timeout_s: float = BUSY_TIMEOUT_S) -> Engine:
    """Create an engine for ``url`` (SQLite or PostgreSQL), configured for durable writes.

    Args:
        url: SQLAlchemy URL, e.g. ``sqlite:///cranetwin.db`` or
            ``postgresql+psycopg://postgres@127.0.0.1:5432/test``. A bare ``postgresql://`` URL
            uses psycopg 3.
        echo: Log every SQL statement.
        busy_timeout_s: SQLite only: how long a write waits for another connection's lock
            before it fails with "database is locked" [s].

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
        path = sqlite_path(u)
        if path is not None:
            create_private(path)
        engine = create_engine(u, echo=echo, connect_args={"check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas(busy_timeout_s))
        return engine
    if backend == "postgresql":
        args: dict[str, Any] = {k: v for k, v in
                                {"connect_timeout": PG_CONNECT_TIMEOUT_S, **_PG_KEEPALIVES}.items()
                                if k not in u.query}
        return create_engine(u, echo=echo, pool_pre_ping=True, connect_args=args)
    raise StorageError(f"unsupported database {backend!r} in {url!r}; "
                       "expected sqlite or postgresql")


def relax_commit_durability(engine: Engine) -> None:
    """PostgreSQL: commits of ``engine``'s connections return before their WAL reaches disk
    (``synchronous_commit = off``); no effect on SQLite.

    For writers of derived data only (the twin worker): a server crash may lose the last
    fraction of a second of its commits, each a whole transaction (a window's summaries with its
    progress mark), so the window is replayed again from the stored samples; nothing is ever
    half written. It saves the wait for a disk flush at every commit (several per window).
    Never for sample storage: an acknowledged sample must be on disk."""
    if engine.dialect.name != "postgresql":
        return

    def _set(dbapi_conn: Any, _record: Any) -> None:
        with dbapi_conn.cursor() as cur:
            cur.execute("SET synchronous_commit = off")
        dbapi_conn.commit()

    event.listen(engine, "connect", _set)
    engine.dispose()  # pooled connections made before the listener: closed, made anew


def migrate(engine: Engine, revision: str = "head") -> None:
    """Apply the Alembic migrations shipped in ``cranetwin.storage.migrations`` up to ``revision``.

    Raises:
        StorageUnavailableError: The database could not be reached (or stayed locked).
        StorageError: A migration failed.
    """
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    try:
        with engine.begin() as conn:
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, revision)
    except SQLAlchemyError as exc:
        if is_unavailable(exc):
            raise unavailable(f"migration of {engine.url.render_as_string()}", exc) from exc
        raise StorageError(f"could not migrate {engine.url.render_as_string()}: {exc}") from exc
