"""Which database errors mean "unavailable, retry later" and which mean "these values are
rejected", for both dialects (SQLAlchemy wraps the drivers' exceptions)."""

from __future__ import annotations

from sqlalchemy import exc as sa_exc

from cranetwin.errors import StorageUnavailableError


def is_unavailable(exc: BaseException) -> bool:
    """The database could not be used (unreachable, connection lost, locked beyond the busy
    timeout, pool exhausted): the same call may succeed later."""
    if isinstance(exc, sa_exc.OperationalError | sa_exc.InterfaceError
                  | sa_exc.DisconnectionError | sa_exc.TimeoutError):
        return True
    return isinstance(exc, sa_exc.DBAPIError) and bool(exc.connection_invalidated)


def unavailable_in_chain(exc: BaseException) -> bool:
    """Whether ``exc`` means the database is unavailable: a
    :class:`~cranetwin.errors.StorageUnavailableError` (what storage raises for these), or an
    error :func:`is_unavailable` recognises anywhere in its cause chain (for calls that let the
    SQLAlchemy errors through). The write should then be retried, not refused."""
    if isinstance(exc, StorageUnavailableError):
        return True
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if is_unavailable(cur):
            return True
        cur = cur.__cause__ or cur.__context__
    return False


def is_data_error(exc: BaseException) -> bool:
    """The database rejected the values written (data or integrity error; an integer the driver
    cannot bind), as opposed to a failure of the database or a bug."""
    if isinstance(exc, sa_exc.IntegrityError | sa_exc.DataError | OverflowError):
        return True
    if isinstance(exc, sa_exc.DBAPIError):
        state = getattr(exc.orig, "sqlstate", None)
        # PostgreSQL classes 22 (data exception), 23 (integrity constraint violation) and
        # 42804 (an integer beyond BIGINT, bound as numeric)
        return isinstance(state, str) and (state[:2] in ("22", "23") or state == "42804")
    return False


def unavailable(what: str, exc: BaseException) -> StorageUnavailableError:
    """The error to raise when ``what`` failed because the database is unavailable."""
    first = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return StorageUnavailableError(f"database unavailable, {what} not done (retry later): "
                                   f"{first}")
