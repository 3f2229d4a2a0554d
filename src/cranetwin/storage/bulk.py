"""Multi-row inserts through the driver, for the write hot path.

SQLAlchemy's per-row parameter processing costs more than the database itself at 10^3–10^4 rows
per second; these statements go straight to the DBAPI cursor:

* SQLite: ``INSERT ... VALUES (?, …), (?, …)`` with positional parameters, chunked below its
  parameter limit (32766);
* PostgreSQL: ``INSERT ... SELECT * FROM unnest(%s::type[], …)``, one array parameter per column.
  A statement with one placeholder per value costs psycopg more to parse than the server needs to
  insert (measured: 0.26 of 0.55 s for 1000 blocks of 11 columns), and it is a new statement for
  every batch size; the array form is one fixed statement. The arrays are encoded here, in
  PostgreSQL's binary array format, by numpy for the numeric columns (psycopg's list dumper
  packs every element in Python: a third of the twin worker's commit at 10³ elements per
  window); a column holding None or a value of another type is left to psycopg.
"""

from __future__ import annotations

import struct
import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np
from sqlalchemy import Connection
from sqlalchemy.dialects import postgresql

from cranetwin.errors import MissingExtraError
from cranetwin.storage.base import Base

MAX_PARAMS = 30000
_PG = postgresql.dialect()  # type: ignore[no-untyped-call]


def pg_array_casts(table: str, columns: Sequence[str]) -> list[str]:
    """``%b::<type>[]`` per column of ``table`` (types from the mapped schema; ``%b``: sent in
    psycopg's binary format, so no element is text-escaped)."""
    t = Base.metadata.tables[table]
    return [f"%b::{t.c[c].type.compile(dialect=_PG)}[]" for c in columns]


class _Array(bytes):
    """A PostgreSQL array in the binary format (``%b`` parameter); subclasses by element type."""

    array_oid = 0


def _array_type(name: str, oid: int) -> type[_Array]:
    return type(name, (_Array,), {"array_oid": oid})


# element type → (element oid, the array's bytes type); oids of PostgreSQL's catalogue
_F8 = (701, _array_type("_Float8Array", 1022))
_I8 = (20, _array_type("_Int8Array", 1016))
_TEXT = (25, _array_type("_TextArray", 1009))
_BYTEA = (17, _array_type("_ByteaArray", 1001))
_ELEMENT = {float: _F8, int: _I8, str: _TEXT, bytes: _BYTEA}
_HEAD = struct.Struct(">iiIii")
_LEN = struct.Struct(">i")
_NUMERIC = {float: (">f8", "fi"), int: (">i8", "i")}  # (unsigned: psycopg)
_REGISTERED: weakref.WeakSet[Any] = weakref.WeakSet()


def _register(dbapi_conn: Any) -> None:
    """Let the psycopg connection send :class:`_Array` values as they are (once per
    connection)."""
    if dbapi_conn in _REGISTERED:
        return
    try:
        from psycopg.adapt import Dumper
        from psycopg.pq import Format
    except ImportError as exc:  # only reached with a psycopg connection, but say so if not
        raise MissingExtraError("postgres", "PostgreSQL bulk inserts") from exc

    for _elem, cls in _ELEMENT.values():
        dumper = type(f"{cls.__name__}Dumper", (Dumper,),
                      {"format": Format.BINARY, "oid": cls.array_oid,
                       "dump": lambda self, obj: obj})
        dbapi_conn.adapters.register_dumper(cls, dumper)
    _REGISTERED.add(dbapi_conn)


def pg_binary_array(values: Sequence[Any] | np.ndarray, kind: type) -> _Array | None:
    """``values`` as one PostgreSQL array of ``kind`` (float, int, str or bytes) in the binary
    format, or None when a value is None or not of that kind (psycopg then sends the list).

    Numbers are checked by numpy's type of the whole column (an int column holding a float
    is refused, never truncated); floats are sent as float8, ints as int8 (the statement
    casts to the column's type)."""
    got = _ELEMENT.get(kind)
    if got is None:
        return None
    oid, cls = got
    n = len(values)
    if n == 0:
        return cls(struct.pack(">iiI", 0, 0, oid))
    head = _HEAD.pack(1, 0, oid, n, 1)
    if kind in _NUMERIC:
        be, kinds = _NUMERIC[kind]
        try:
            arr = np.asarray(values)
        except (TypeError, ValueError, OverflowError):
            return None
        if arr.ndim != 1 or arr.dtype.kind not in kinds or arr.dtype == np.bool_:
            return None
        body = np.empty(n, dtype=[("n", ">i4"), ("v", be)])
        body["n"] = 8
        body["v"] = arr
        return cls(head + body.tobytes())
    parts: list[bytes] = [head]
    for v in values:
        if kind is str:
            if type(v) is not str:
                return None
            b = v.encode()
        elif isinstance(v, bytes | bytearray | memoryview):
            b = bytes(v)
        else:
            return None
        parts.append(_LEN.pack(len(b)))
        parts.append(b)
    return cls(b"".join(parts))


def pg_columns(conn: Connection, table: str, columns: Sequence[str],
                data: Sequence[Sequence[Any]]) -> tuple[Any, ...]:
    """The statement's parameters: each column as :func:`pg_binary_array` of the type the
    schema maps it to, or as a list for psycopg."""
    t = Base.metadata.tables[table]
    dbapi = conn.connection.dbapi_connection
    if dbapi is not None:
        _register(dbapi)
    out: list[Any] = []
    for c, col in zip(columns, data, strict=True):
        try:
            kind = t.c[c].type.python_type
        except NotImplementedError:
            kind = object
        arr = pg_binary_array(col, kind) if dbapi is not None and kind is not bool else None
        out.append(arr if arr is not None else list(col))
    return tuple(out)


def insert_rows(conn: Connection, table: str, columns: Sequence[str],
                rows: Sequence[Sequence[Any]], suffix: str = "") -> list[tuple[Any, ...]]:
    """Insert ``rows`` into ``table`` with one statement per chunk.

    Args:
        conn: Connection inside the caller's transaction.
        table, columns: Target (trusted identifiers, never user input).
        rows: One tuple per row, values in ``columns`` order.
        suffix: SQL appended to each statement (``ON CONFLICT ...``, ``RETURNING ...``).

    Returns:
        The rows returned by a ``RETURNING`` suffix (empty otherwise).
    """
    if not rows:
        return []
    if conn.dialect.name == "postgresql":
        cols = ",".join(columns)
        sql = (f"INSERT INTO {table} ({cols}) SELECT * FROM unnest("
               f"{','.join(pg_array_casts(table, columns))}) AS u({cols}) {suffix}")
        res = conn.exec_driver_sql(sql, pg_columns(conn, table, columns,
                                                    list(zip(*rows, strict=True))))
        return [tuple(r) for r in res.all()] if res.returns_rows else []
    ph = "?" if conn.dialect.name == "sqlite" else "%s"
    one = "(" + ",".join([ph] * len(columns)) + ")"
    head = f"INSERT INTO {table} ({','.join(columns)}) VALUES "
    per = max(1, MAX_PARAMS // len(columns))
    out: list[tuple[Any, ...]] = []
    for i in range(0, len(rows), per):
        chunk = rows[i:i + per]
        params = tuple(v for r in chunk for v in r)
        res = conn.exec_driver_sql(head + ",".join([one] * len(chunk)) + " " + suffix, params)
        if res.returns_rows:
            out.extend(tuple(r) for r in res.all())
    return out
