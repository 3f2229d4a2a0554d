"""PostgreSQL session advisory locks on one connection held for a process's life.

:class:`SessionLocks` keeps one autocommit connection open and takes two-key advisory locks on it
(``pg_try_advisory_lock(ns, key)``, never waiting). A lock lives as long as that connection: when
the process dies (even by SIGKILL) the server ends its session and every lock it held is free at
once for another process; a lost connection (server restart, network) loses them too, which
:meth:`SessionLocks.alive` reports so the owner stops assuming it holds anything.

:meth:`SessionLocks.holders` reads ``pg_locks`` (readable by every role), so processes can see
who holds what in a namespace: the twin workers count each other and find the free partitions
this way (:mod:`cranetwin.service.ownership`). Namespaces are 31-bit keys derived from a name and
the connection's schema, so deployments (and tests) sharing one database in separate schemas
never see each other's locks.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass

from sqlalchemy import Connection, Engine
from sqlalchemy.exc import SQLAlchemyError

from cranetwin.errors import StorageError
from cranetwin.storage.dberrors import is_unavailable, unavailable

log = logging.getLogger(__name__)

_HOLDERS = (
    "SELECT classid::bigint, objid::bigint, pid FROM pg_locks "
    "WHERE locktype = 'advisory' AND granted AND objsubid = 2 "
    "AND database = (SELECT oid FROM pg_database WHERE datname = current_database()) "
    "AND classid::bigint = ANY(%s)")


@dataclass(frozen=True)
class Holder:
    """A granted advisory lock: namespace, key and the server pid of the holding session."""

    ns: int
    key: int
    pid: int


class SessionLocks:
    """Advisory locks held on one dedicated PostgreSQL connection.

    Args:
        engine: A PostgreSQL engine (the connection is taken from it and kept).

    Raises:
        StorageUnavailableError: The server cannot be reached (from :meth:`connect`).
    """

    def __init__(self, engine: Engine) -> None:
        if engine.dialect.name != "postgresql":
            raise StorageError("advisory locks need PostgreSQL")
        self.engine = engine
        self._conn: Connection | None = None
        self.pid: int | None = None
        self._schema = ""

    def connect(self) -> None:
        """Open the session (a no-op while it is open)."""
        if self._conn is not None:
            return
        try:
            conn = self.engine.connect().execution_options(isolation_level="AUTOCOMMIT")
            self.pid = int(conn.exec_driver_sql("SELECT pg_backend_pid()").scalar_one())
            self._schema = str(conn.exec_driver_sql("SELECT current_schema()").scalar())
        except SQLAlchemyError as exc:
            raise unavailable("advisory-lock session", exc) from exc
        self._conn = conn

    def namespace(self, name: str) -> int:
        """31-bit namespace key for ``name`` in this session's schema."""
        self.connect()
        return zlib.crc32(f"{name}:{self._schema}".encode()) & 0x7FFF_FFFF

    def _c(self) -> Connection:
        self.connect()
        assert self._conn is not None
        return self._conn

    def alive(self) -> bool:
        """Whether the session (and so every lock taken on it) still exists; a dead one is
        closed, and the next call opens a new session holding nothing."""
        if self._conn is None:
            return False
        try:
            self._conn.exec_driver_sql("SELECT 1").scalar()
            return True
        except SQLAlchemyError as exc:
            log.warning("advisory-lock session lost (its locks are gone): %s",
                        str(exc).splitlines()[0])
            self.close()
            return False

    def _run(self, sql: str, params: tuple[object, ...]) -> object:
        try:
            return self._c().exec_driver_sql(sql, params).scalar()
        except SQLAlchemyError as exc:
            self.close()
            if is_unavailable(exc):
                raise unavailable("advisory lock", exc) from exc
            raise StorageError(f"advisory lock: {exc}".splitlines()[0]) from exc

    def try_lock(self, ns: int, key: int) -> bool:
        """Take lock (ns, key) if free (never waits); True if this session holds it now."""
        return bool(self._run("SELECT pg_try_advisory_lock(%s, %s)", (ns, key)))

    def unlock(self, ns: int, key: int) -> bool:
        """Release lock (ns, key); False if this session did not hold it."""
        return bool(self._run("SELECT pg_advisory_unlock(%s, %s)", (ns, key)))

    def holders(self, namespaces: list[int]) -> list[Holder]:
        """Every granted lock in ``namespaces``, of any session of this database."""
        try:
            rows = self._c().exec_driver_sql(_HOLDERS, (list(namespaces),)).all()
        except SQLAlchemyError as exc:
            self.close()
            if is_unavailable(exc):
                raise unavailable("advisory lock holders", exc) from exc
            raise StorageError(f"advisory lock holders: {exc}".splitlines()[0]) from exc
        return [Holder(int(a), int(b), int(p)) for a, b, p in rows]

    def close(self) -> None:
        """End the session (its locks are released).

        The locks are released by a statement first: the server ends a closed session's
        backend a moment after the socket closes, and until then its locks still look held to
        every other session (a worker leaving in order must free its partitions at once)."""
        conn, self._conn = self._conn, None
        if conn is not None:  # invalidated: really closed, never handed back to the pool
            try:
                conn.exec_driver_sql("SELECT pg_advisory_unlock_all()").scalar()
            except SQLAlchemyError:
                pass  # a dead session holds nothing
            try:
                conn.invalidate()
                conn.close()
            except SQLAlchemyError:
                pass
