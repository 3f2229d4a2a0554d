"""The service's adapter over :class:`cranetwin.storage.Store`: the one module that knows storage.

The service and the API see :class:`MachineRecord`, :class:`Progress`, numpy arrays and
:class:`~cranetwin.samples.SampleArrays`; an unknown machine raises
:class:`~cranetwin.service.errors.NotFoundError`, a taken id
:class:`~cranetwin.service.errors.ConflictError`, an unknown model
:class:`~cranetwin.service.errors.InvalidRequestError`. The service's own tables (API keys, twin
progress, :mod:`cranetwin.storage.apikeys`) are read and written here with sessions on the
store's engine.

Two processes share the progress rows: the twin worker (``cranetwin worker``) writes them, the
API reads them on every request that needs them (nothing is cached across processes). A
window's commit is conditional on the watermark it started from (:meth:`Backend.commit_window`),
so two workers on one machine never both count a window: the second one's transaction, summaries
included, is rolled back and it re-reads the progress.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from cranetwin.errors import CraneTwinError, ModelError, StorageError
from cranetwin.model import Machine, builtin_machines, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.errors import ConflictError, InvalidRequestError, NotFoundError
from cranetwin.storage import Store, StoreSpec, open_store
from cranetwin.storage import apikeys as keyrepo
from cranetwin.storage import summaries as summ
from cranetwin.storage.machines import get_row

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MachineRecord:
    """A registered machine as the service sees it.

    Attributes:
        machine_id: Identifier.
        name: Display name (metadata ``name``, else the id).
        model: Machine description name (built-in) or ``"custom"`` for inline TOML.
        model_source: Built-in name or TOML text, as stored.
        wire_id: Numeric id on the wire.
        location: (latitude [deg], longitude [deg], time [s]) or None.
        payload_version: Version of the machine's stored known payload when the record was
            read (:meth:`Backend.machine`: with the record, no query of its own); None when
            not read (listings).
        newest_block_s: End of the machine's newest stored block when the record was read [s
            since the epoch], or None (nothing stored).
        late_version: The machine's late-data version (:mod:`cranetwin.storage.late_version`),
            read with ``newest_block_s`` (:meth:`Backend.machine`); None when not read
            (listings).
    """

    machine_id: str
    name: str
    model: str
    model_source: str
    wire_id: int | None
    location: tuple[float, float, float] | None
    payload_version: int | None = None
    newest_block_s: float | None = None
    late_version: int | None = None


@dataclass(frozen=True)
class Progress:
    """The twin worker's state of one machine (mirrors ``twin_progress``)."""

    machine_id: str
    watermark_s: float
    windows: int = 0
    operating_s: float = 0.0
    idle_s: float = 0.0
    load_count: int = 0
    payload_total_kg: float = 0.0
    load_cube_sum: float = 0.0
    overloads: int = 0
    max_payload_kg: float = 0.0
    in_lift: bool = False
    lift_peak_kg: float = 0.0
    lift_peak_ratio: float = 0.0
    last_payload_kg: float | None = None
    theta0_rad: float | None = None

    @staticmethod
    def empty(machine_id: str, watermark_s: float = 0.0) -> Progress:
        """Progress before the first window."""
        return Progress(machine_id=machine_id, watermark_s=watermark_s)


@lru_cache(maxsize=64)
def _load_model(source: str) -> Machine:
    if source in builtin_machines():
        return load_machine(source)
    import tomllib

    from cranetwin.model import machine_from_dict

    return machine_from_dict(tomllib.loads(source), "stored machine description")


class Backend:
    """Store access for the service, the API and the twin worker.

    Args:
        store: An open :class:`cranetwin.storage.Store`.
    """

    def __init__(self, store: Store) -> None:
        self.store = store
        self._progress_cache: dict[str, Progress] = {}
        self._pks: dict[str, int] = {}
        self._lock = threading.Lock()

    @classmethod
    def open(cls, url: str | StoreSpec) -> Backend:
        """Open (and migrate) the database at ``url``, or every shard of a
        :class:`~cranetwin.storage.StoreSpec` (:func:`cranetwin.storage.open_store`)."""
        return cls(open_store(url))

    def close(self) -> None:
        """Close the store."""
        self.store.close()

    def session(self, machine_id: str | None = None) -> Session:
        """A new ORM session on the engine holding ``machine_id``'s rows (its shard), or on
        the store's home engine (API keys, rows of no machine)."""
        return Session(self.store.engine if machine_id is None
                       else self.store.engine_for(machine_id))

    # -- machines -----------------------------------------------------------------------------
    @staticmethod
    def _record(info: Any) -> MachineRecord:
        meta = dict(info.metadata or {})
        source = str(info.model)
        model = source if "\n" not in source and "[" not in source else "custom"
        loc = None
        if info.latitude_deg is not None and info.longitude_deg is not None:
            t = meta.get("location_t_s") or info.last_seen_s or 0.0
            loc = (float(info.latitude_deg), float(info.longitude_deg), float(t))
        return MachineRecord(machine_id=info.machine_id, name=str(meta.get("name") or
                                                                   info.machine_id),
                             model=model, model_source=source, wire_id=int(info.wire_id),
                             location=loc, payload_version=info.payload_version,
                             newest_block_s=(None if info.newest_block_ns is None
                                             else info.newest_block_ns / 1e9),
                             late_version=info.late_version)

    def list_machines(self) -> list[MachineRecord]:
        """Every registered machine, by id."""
        return sorted((self._record(i) for i in self.store.machines()),
                      key=lambda r: r.machine_id)

    def machine(self, machine_id: str) -> MachineRecord:
        """The machine ``machine_id``.

        Raises:
            NotFoundError: No machine of that id is registered.
        """
        try:
            info = self.store.get_machine(machine_id)
        except StorageError:
            info = None
        if info is None:
            raise NotFoundError("Unknown machine", f"no machine {machine_id!r} is registered "
                                "(GET /api/v1/machines lists them)")
        return self._record(info)

    def model_of(self, rec: MachineRecord) -> Machine:
        """The machine description of ``rec`` (cached)."""
        try:
            return _load_model(rec.model_source)
        except CraneTwinError as exc:
            raise InvalidRequestError("Invalid machine description",
                                      f"machine {rec.machine_id!r}: {exc}") from exc

    def create_machine(self, machine_id: str, model: str, name: str | None = None,
                       wire_id: int | None = None,
                       location: tuple[float, float] | None = None) -> tuple[MachineRecord, str]:
        """Register a machine of a built-in model; returns it and its HMAC secret (hex).

        Args:
            machine_id: Identifier.
            model: Built-in machine description name.
            name: Display name (default: the id).
            wire_id: Numeric id on the wire (default: the largest in use + 1).
            location: (latitude, longitude) [deg], or None.

        Raises:
            InvalidRequestError: Unknown or invalid model.
            ConflictError: The id or the wire id is taken.
        """
        if model not in builtin_machines():
            raise InvalidRequestError("Unknown model", f"model {model!r}: expected one of "
                                      f"{', '.join(builtin_machines())}")
        existing = {i.machine_id: i for i in self.store.machines()}
        if machine_id in existing:
            raise ConflictError("Machine exists", f"machine {machine_id!r} is already "
                                "registered (PATCH it to change metadata)")
        wire_ids = {int(i.wire_id) for i in existing.values()}
        if wire_id is not None and wire_id in wire_ids:
            raise ConflictError("Wire id taken", f"wire_id {wire_id} is used by another machine")
        wid = wire_id if wire_id is not None else (max(wire_ids, default=0) + 1)
        secret = secrets.token_bytes(32)
        now = time.time()
        meta: dict[str, Any] = {"name": name or machine_id, "registered_t_s": now}
        if location is not None:
            meta["location_t_s"] = now  # the position's time: when it was registered
        try:
            self.store.add_machine(machine_id, wire_id=wid, model=model, secret=secret,
                                   metadata=meta)
            if location is not None:
                self._set_location(machine_id, location[0], location[1])
        except ModelError as exc:
            raise InvalidRequestError("Invalid machine", str(exc)) from exc
        return self.machine(machine_id), secret.hex()

    def _set_location(self, machine_id: str, lat: float, lon: float) -> None:
        with self.session(machine_id) as s, s.begin():
            row = get_row(s, machine_id)
            row.latitude_deg, row.longitude_deg = lat, lon

    def update_machine(self, machine_id: str, name: str | None = None,
                       location: tuple[float, float] | None = None) -> MachineRecord:
        """Change a machine's display name and/or location ((latitude, longitude) [deg]);
        None leaves a field as it is."""
        import json

        with self.session(machine_id) as s, s.begin():
            row = get_row(s, machine_id)
            meta = json.loads(row.meta_json or "{}")
            if name is not None:
                meta["name"] = name
            if location is not None:
                row.latitude_deg, row.longitude_deg = location
                meta["location_t_s"] = time.time()
            row.meta_json = json.dumps(meta)
        return self.machine(machine_id)

    # -- samples ------------------------------------------------------------------------------
    def _pk(self, s: Session, machine_id: str) -> int:
        pk = self._pks.get(machine_id)
        if pk is None:
            pk = int(get_row(s, machine_id).id)
            self._pks[machine_id] = pk
        return pk

    def data_range(self, machine_id: str) -> tuple[float, float] | None:
        """(first, last) stored sample time [s], or None when nothing is stored."""
        return self.store.data_range(machine_id)

    def data_ranges(self, machine_ids: list[str]) -> dict[str, tuple[int, tuple[float, float] |
                                                                        None]]:
        """:meth:`data_range` of many machines, one statement per engine (an index probe per
        machine each way): machine → (its primary key, (first, last) or None). Unregistered
        machines are left out."""
        from sqlalchemy import func, select

        from cranetwin.storage.blocks import BlockRow
        from cranetwin.storage.machines import MachineRow

        b, m = BlockRow, MachineRow
        lo = select(func.min(b.t_start_ns)).where(b.machine_pk == m.id).scalar_subquery()
        hi = select(func.max(b.t_end_ns)).where(b.machine_pk == m.id).scalar_subquery()
        out: dict[str, tuple[int, tuple[float, float] | None]] = {}
        for engine, ids in self.store.engines_of(machine_ids):
            with Session(engine) as s:
                for mid, pk, a, z in s.execute(select(m.machine_id, m.id, lo, hi)
                                               .where(m.machine_id.in_(ids))):
                    out[mid] = (int(pk), None if a is None else (int(a) / 1e9, int(z) / 1e9))
        with self._lock:
            self._pks.update({mid: v[0] for mid, v in out.items()})
        return out

    def payload_version(self, machine_id: str) -> int:
        """The version of the machine's stored known payload, raised by every change of it
        in any process (:mod:`cranetwin.storage.payload_version`): one primary-key lookup."""
        return int(self.store.payload_version(machine_id))

    def read_samples(self, machine_id: str, t0_s: float, t1_s: float) -> SampleArrays:
        """Samples with t in [t0_s, t1_s]."""
        out: SampleArrays = self.store.read_samples(machine_id, t0_s, t1_s)
        return out

    def read_after(self, machine_id: str, after_s: float) -> SampleArrays | None:
        """Samples newer than ``after_s`` (live follower), at most the last 10 s of them.

        One query in the usual case (new samples just after ``after_s``); when there are none
        within 10 s, the newest stored 10 s (a gap, or a follower far behind).
        """
        s = self.read_samples(machine_id, after_s, after_s + 10.0)
        if s.t_s.shape[0] == 0 or s.t_s[-1] <= after_s:
            dr = self.data_range(machine_id)
            if dr is None or dr[1] <= after_s:
                return None
            s = self.read_samples(machine_id, max(after_s, dr[1] - 10.0), dr[1] + 1.0)
        return s.take(s.t_s > after_s)

    def next_sample_time(self, machine_id: str, after_s: float) -> float | None:
        """Start of the first stored block ending at or after ``after_s`` [s], or None."""
        r = self.store.next_block_start(machine_id, after_s)
        return None if r is None else max(r, after_s)

    # -- summaries ----------------------------------------------------------------------------
    def finest_interval_s(self) -> float:
        """Width of the finest stored summary bucket [s]."""
        return float(min(summ.LEVELS_S))

    def summaries(self, machine_id: str, channels: list[str], t0_s: float, t1_s: float,
                  max_points: int) -> dict[str, tuple[F64, F64, F64, F64]]:
        """Per channel (t, min, max, mean) of non-empty buckets, ≤ max_points each."""
        res = self.store.summaries(machine_id, channels, t0_s, t1_s, max_points)
        out = {}
        for j, ch in enumerate(res.channels):
            ok = res.count[:, j] > 0
            out[ch] = (res.t_s[ok], res.min[ok, j], res.max[ok, j], res.mean[ok, j])
        for ch in channels:
            out.setdefault(ch, (np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)))
        return out

    # -- events -------------------------------------------------------------------------------
    def events(self, machine_id: str, t0_s: float, t1_s: float) -> list[dict[str, Any]]:
        """Events in [t0_s, t1_s) as contract dicts (t, kind, severity, message, evidence)."""
        out = []
        for e in self.store.events(machine_id, t0_s, t1_s):
            ev = dict(e.evidence or {})
            msg = str(ev.get("message") or _message(e.kind, ev))
            out.append({"t": float(e.t_s), "kind": e.kind, "severity": e.severity,
                        "message": msg, "evidence": ev})
        return out

    def count_events(self, machine_id: str, t0_s: float, t1_s: float, level: str) -> int:
        """Events of severity ``level`` (``info``, ``warning``, ``critical``) in a range."""
        return sum(1 for e in self.store.events(machine_id, t0_s, t1_s)
                   if e.severity == level)

    # -- keys ---------------------------------------------------------------------------------
    def key_lookup(self, key_id: str) -> tuple[str, str, Any] | None:
        """``(secret_sha256, name, role)`` of an active key."""
        with self.session() as s:
            return keyrepo.active_key(s, key_id)

    def create_key(self, role: str, name: str = "") -> tuple[str, str]:
        """A new key of ``role``: ``(key_id, token)``; only the hash is stored."""
        from cranetwin.service.keys import new_key

        key_id, token, digest = new_key()
        with self.session() as s, s.begin():
            keyrepo.add_key(s, key_id, digest, role, name)
        return key_id, token

    # -- twin worker progress -----------------------------------------------------------------
    def progress(self, machine_id: str) -> Progress | None:
        """The worker's stored progress of a machine."""
        with self.session(machine_id) as s:
            row = keyrepo.get_progress(s, machine_id)
            if row is None:
                return None
            p = Progress(**{f: getattr(row, f) for f in Progress.__dataclass_fields__})
        with self._lock:
            self._progress_cache[machine_id] = p
        return p

    def progress_many(self, machine_ids: list[str]) -> dict[str, Progress]:
        """:meth:`progress` of many machines, one statement per engine (machines without a
        progress row left out)."""
        from sqlalchemy import select

        row_t = keyrepo.TwinProgressRow
        fields = list(Progress.__dataclass_fields__)
        cols = [getattr(row_t, f) for f in fields]  # plain rows: no ORM object per machine
        out: dict[str, Progress] = {}
        for engine, ids in self.store.engines_of(machine_ids):
            with Session(engine) as s:
                for row in s.execute(select(*cols).where(row_t.machine_id.in_(ids))):
                    p = Progress(**dict(zip(fields, row, strict=True)))
                    out[p.machine_id] = p
        with self._lock:
            self._progress_cache.update(out)
        return out

    def cached_progress(self, machine_id: str) -> Progress | None:
        """Last progress seen by this process (no database read; for the live stream)."""
        with self._lock:
            return self._progress_cache.get(machine_id)

    def save_progress(self, prog: Progress, expected_watermark_s: float | None) -> bool:
        """Store progress alone (a skipped or failed window), if the stored watermark is still
        ``expected_watermark_s`` (None: no progress row stored yet).

        Returns:
            Whether it was stored (False: another worker moved the watermark first).
        """
        return self.commit_window(prog, expected_watermark_s, [], np.zeros(0),
                                  np.zeros((0, 0)))

    def reset_progress(self, prog: Progress) -> None:
        """Store progress unconditionally (position the worker: tests, benchmarks, operators)."""
        with self.session(prog.machine_id) as s, s.begin():
            row = s.get(keyrepo.TwinProgressRow, prog.machine_id)
            values = asdict(prog)
            values["updated_s"] = time.time()
            if row is None:
                s.add(keyrepo.TwinProgressRow(**values))
            else:
                for k, v in values.items():
                    setattr(row, k, v)
        with self._lock:
            self._progress_cache[prog.machine_id] = prog

    @staticmethod
    def _put_progress(s: Session, prog: Progress, expected_watermark_s: float | None) -> None:
        """Insert or update the progress row, only from the expected watermark.

        Raises:
            _WatermarkMoved: The stored row is not at ``expected_watermark_s`` (or exists when
                None was expected); the transaction must be rolled back.
        """
        values = asdict(prog)
        values["updated_s"] = time.time()
        row_t = keyrepo.TwinProgressRow
        if expected_watermark_s is None:
            if s.get(row_t, prog.machine_id) is not None:
                raise _WatermarkMoved
            s.add(row_t(**values))
            s.flush()  # a concurrent insert fails here (primary key)
            return
        conn = s.connection()
        sql, cols = _progress_update(conn.dialect.paramstyle)
        res = conn.exec_driver_sql(sql, tuple(values[c] for c in cols[:-2])
                                   + (prog.machine_id, expected_watermark_s))
        if getattr(res, "rowcount", 0) != 1:
            raise _WatermarkMoved

    def commit_window(self, prog: Progress, expected_watermark_s: float | None,
                      channels: list[str], t_s: F64, values: F64,
                      also: Callable[[Session, int], None] | None = None) -> bool:
        """Derived summaries of one window and the new progress, in one transaction, committed
        only if the stored watermark is still ``expected_watermark_s`` (None: no row yet).

        Args:
            also: Further writes of the window in the same transaction, given the session and
                the machine's primary key (the twin worker's analytics part, lift seconds and
                events).

        Returns:
            Whether it was committed. False: another worker committed this window first; nothing
            of this one was written (summaries and ``also`` included).
        """
        try:
            with self.session(prog.machine_id) as s, s.begin():
                if t_s.size or also is not None:
                    pk = self._pk(s, prog.machine_id)
                if t_s.size:
                    t_ns = np.round(t_s * 1e9).astype(np.int64)
                    summ.replace(s, pk, channels, t_ns, values)
                if also is not None:
                    also(s, pk)
                self._put_progress(s, prog, expected_watermark_s)
        except (_WatermarkMoved, IntegrityError):
            return False
        with self._lock:
            self._progress_cache[prog.machine_id] = prog
        return True

    def commit_spans(self, commits: list[SpanCommit]) -> set[str]:
        """The spans of many machines (a worker pass), one transaction per engine: each
        machine's progress moves only from its expected watermark, and only the machines whose
        progress moved get their summaries, analytics rows and events written, in the same
        transaction. On PostgreSQL that is a fixed number of statements for all the machines
        (progress, then summaries, rows, events of the winners); elsewhere one
        :meth:`commit_window` per machine.

        A crash or an error before the commit leaves every machine of the engine as it was
        (the worker replays them again); a machine whose watermark another worker moved is
        left out, nothing of its spans written.

        Returns:
            The machines committed.
        """
        from cranetwin.storage import analytics_windows as aw
        from cranetwin.storage import events as ev

        by_id = {c.prog.machine_id: c for c in commits}
        won: set[str] = set()
        for engine, ids in self.store.engines_of(sorted(by_id)):
            if engine.dialect.name != "postgresql":
                for mid in ids:
                    if self._commit_one(by_id[mid]):
                        won.add(mid)
                continue
            with Session(engine) as s, s.begin():
                got = _put_progress_many(s, [by_id[m] for m in ids])
                groups: dict[tuple[str, ...], list[tuple[int, Any, F64]]] = {}
                rows: list[dict[str, Any]] = []
                events: list[tuple[int, list[Any]]] = []
                for mid in ids:
                    if mid not in got:
                        continue
                    c = by_id[mid]
                    pk = self._pk(s, mid)
                    for t_s, values in c.spans:
                        groups.setdefault(tuple(c.channels), []).append(
                            (pk, np.round(t_s * 1e9).astype(np.int64), values))
                    rows += c.rows
                    events.append((pk, c.events))
                ev.add_many(s, events)
                for chans, spans in groups.items():
                    summ.replace_many(s, chans, spans)
                aw.put_rows(s, rows)
            won |= got
        with self._lock:
            self._progress_cache.update({m: by_id[m].prog for m in won})
        return won

    def _commit_one(self, c: SpanCommit) -> bool:
        """:meth:`commit_spans` of one machine, one transaction (any database)."""
        from cranetwin.storage import analytics_windows as aw
        from cranetwin.storage import events as ev

        try:
            with self.session(c.prog.machine_id) as s, s.begin():
                pk = self._pk(s, c.prog.machine_id)
                summ.replace_many(s, c.channels, [
                    (pk, np.round(t * 1e9).astype(np.int64), v) for t, v in c.spans])
                aw.put_rows(s, c.rows)
                ev.add_in(s, pk, c.events)
                self._put_progress(s, c.prog, c.expected_watermark_s)
        except (_WatermarkMoved, IntegrityError):
            return False
        with self._lock:
            self._progress_cache[c.prog.machine_id] = c.prog
        return True


def _put_progress_many(s: Session, commits: list[SpanCommit]) -> set[str]:
    """PostgreSQL: move the progress rows of ``commits`` each from its expected watermark
    (an update of the rows that have one, an insert of the rows that have none), two statements
    at most; returns the machines whose row moved."""
    from cranetwin.storage.bulk import insert_rows, pg_array_casts, pg_columns

    now = time.time()
    fields = [c for c in Progress.__dataclass_fields__ if c != "machine_id"]
    cols = ("machine_id", *fields, "updated_s")
    upd = [c for c in commits if c.expected_watermark_s is not None]
    new = [c for c in commits if c.expected_watermark_s is None]
    won: set[str] = set()
    if upd:
        names = ("machine_id", "watermark_s", *cols[1:])  # the expected watermark, then row
        data: list[list[Any]] = [[c.prog.machine_id for c in upd],
                                 [c.expected_watermark_s for c in upd]]
        data += [[getattr(c.prog, f) for c in upd] for f in fields] + [[now] * len(upd)]
        casts = pg_array_casts("twin_progress", names)
        sets = ", ".join(f"{c} = v.{c}" for c in cols[1:])
        sql = (f"UPDATE twin_progress AS p SET {sets} FROM unnest({', '.join(casts)}) AS "
               f"v(machine_id, expected_s, {', '.join(cols[1:])}) WHERE p.machine_id = "
               "v.machine_id AND p.watermark_s = v.expected_s RETURNING p.machine_id")
        conn = s.connection()
        won |= {r[0] for r in conn.exec_driver_sql(sql, pg_columns(conn, "twin_progress",
                                                                   names, data))}
    if new:
        rows = [(c.prog.machine_id, *(getattr(c.prog, f) for f in fields), now) for c in new]
        won |= {r[0] for r in insert_rows(s.connection(), "twin_progress", cols, rows,
                                          "ON CONFLICT (machine_id) DO NOTHING "
                                          "RETURNING machine_id")}
    return won


@dataclass
class SpanCommit:
    """What one machine's spans of a worker pass commit together (:meth:`Backend.commit_spans`).

    Attributes:
        prog: The machine's progress after its last span.
        expected_watermark_s: The stored watermark its first span started from (None: no
            progress row stored yet).
        channels: Derived channel names of the spans' values.
        spans: Per span, (grid times (k,) [s], derived values (k, c)).
        rows: Analytics-window rows (parts, lift seconds) of the spans.
        events: Events found in the spans.
        windows: Windows the spans hold.
    """

    prog: Progress
    expected_watermark_s: float | None
    channels: list[str]
    spans: list[tuple[F64, F64]]
    rows: list[dict[str, Any]]
    events: list[Any]
    windows: int = 0


@lru_cache(maxsize=4)
def _progress_update(paramstyle: str) -> tuple[str, tuple[str, ...]]:
    """``UPDATE twin_progress`` of every field where the machine and the watermark match, in the
    driver's parameter style (built once), and its parameters in order (the fields but the
    machine, ``updated_s``, then ``machine_id`` and the expected watermark)."""
    ph = "?" if paramstyle == "qmark" else "%s"
    cols = tuple(c for c in [*Progress.__dataclass_fields__, "updated_s"] if c != "machine_id")
    sql = (f"UPDATE twin_progress SET {', '.join(f'{c} = {ph}' for c in cols)} "
           f"WHERE machine_id = {ph} AND watermark_s = {ph}")
    return sql, (*cols, "machine_id", "watermark_s")


class _WatermarkMoved(Exception):
    """Internal: the stored watermark is not the one a window started from (rolls back)."""


def _message(kind: str, ev: dict[str, Any]) -> str:
    parts = [kind.replace("_", " ")]
    for k in ("value", "limit", "channel"):
        if k in ev:
            parts.append(f"{k} {ev[k]}")
    return ", ".join(parts)


__all__ = ["Backend", "MachineRecord", "Progress"]
