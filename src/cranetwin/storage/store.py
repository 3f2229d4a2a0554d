"""The storage facade every other package calls: :class:`Store`.

One :class:`Store` wraps one engine. Each method is one transaction; repositories in the
concept modules (``machines``, ``blocks``, ``summaries``, ``events``) take the session.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import Engine, func, select
from sqlalchemy.exc import IntegrityError, SQLAlchemyError
from sqlalchemy.orm import Session

from cranetwin.errors import StorageError
from cranetwin.samples import F64, SampleArrays, SampleBlock
from cranetwin.storage import blocks as blocks_mod
from cranetwin.storage import events as events_mod
from cranetwin.storage import late_version, payload_version, redo
from cranetwin.storage import machines as machines_mod
from cranetwin.storage import partitions as partitions_mod
from cranetwin.storage import payloads as payloads_mod
from cranetwin.storage import summaries as summaries_mod
from cranetwin.storage import writes as writes_mod
from cranetwin.storage.dberrors import is_unavailable, unavailable
from cranetwin.storage.engine import BUSY_TIMEOUT_S, DEFAULT_URL, make_engine, migrate
from cranetwin.storage.events import Event, EventRow
from cranetwin.storage.machines import MachineInfo, MachineRow, UnknownMachineError
from cranetwin.storage.payloads import (
    PayloadDelete,
    PayloadRun,
    PayloadSeries,
    PayloadWrite,
    Stretch,
)
from cranetwin.storage.summaries import Summaries
from cranetwin.storage.writes import WriteResult


@dataclass(frozen=True)
class StorageStats:
    """Size of the stored raw data.

    Attributes:
        blocks: Number of stored blocks.
        samples: Number of stored samples (rows of all blocks).
        data_bytes: Bytes of compressed sample data (blob payloads, excluding row overhead).
    """

    blocks: int
    samples: int
    data_bytes: int


_EPS_NS = 1000


def _ns(t_s: float) -> int:
    """Seconds → ns, rounded, limited to the signed 64-bit range."""
    x = float(t_s) * 1e9
    return blocks_mod.clamp_ns(round(x) if abs(x) < 2.0**63 else x)


class Store:
    """Machines, raw sample blocks, summaries and events in one SQL database.

    Create it with :meth:`open`; it is safe to share between threads (each call opens its own
    session from the engine's pool).
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self._pk: dict[str, int] = {}
        self.rollup_skipped = 0
        """Machine-minutes :meth:`rollup` could not roll up and dropped (since open)."""
        self.corrupt_summaries = 0
        """Block rows whose per-second summary :meth:`rollup` could not decode (since open)."""
        self._partitioner: partitions_mod.Partitioner | None = None
        self._partitioned: bool | None = None

    @classmethod
    def open(cls, url: str = DEFAULT_URL, *, echo: bool = False,
             busy_timeout_s: float = BUSY_TIMEOUT_S) -> Store:
        """Connect to ``url`` and migrate its schema to the newest revision.

        Args:
            url: SQLite or PostgreSQL URL (see :func:`cranetwin.storage.engine.make_engine`).
            echo: Log every SQL statement.
            busy_timeout_s: SQLite only: how long a write waits for another connection's lock
                before it fails (then :class:`StorageUnavailableError`) [s].

        Raises:
            StorageUnavailableError: The server is unreachable.
            StorageError: Bad URL or failed migration.
        """
        store = cls(make_engine(url, echo=echo, busy_timeout_s=busy_timeout_s))
        migrate(store.engine)
        return store

    def close(self) -> None:
        """Release the engine's connections."""
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def dialect(self) -> str:
        """``sqlite`` or ``postgresql``."""
        return self.engine.dialect.name

    def engine_for(self, machine_id: str) -> Engine:
        """The engine holding ``machine_id``'s rows (one engine here; its shard's in
        :class:`~cranetwin.storage.shards.ShardedStore`)."""
        return self.engine

    def engines_of(self, machine_ids: Iterable[str]) -> list[tuple[Engine, list[str]]]:
        """``machine_ids`` grouped by the engine holding them (fan-out of fleet reads)."""
        ids = list(machine_ids)
        return [(self.engine, ids)] if ids else []

    @property
    def engines(self) -> list[Engine]:
        """Every engine of the store (one here; one per shard when sharded)."""
        return [self.engine]

    def _session(self) -> Session:
        return Session(self.engine, expire_on_commit=False)

    def _machine_pk(self, s: Session, machine_id: str) -> int:
        pk = self._pk.get(machine_id)
        if pk is None:  # load every id at once: a fleet's first batch names them all
            rows = s.execute(select(MachineRow.machine_id, MachineRow.id)).all()
            self._pk.update({m: int(i) for m, i in rows})
            pk = self._pk.get(machine_id)
            if pk is None:
                pk = machines_mod.get_row(s, machine_id).id  # raises UnknownMachineError
        return pk

    # -- machines -------------------------------------------------------------------------
    def add_machine(self, machine_id: str, wire_id: int, secret: bytes, model: str = "patu655",
                    metadata: dict[str, Any] | None = None) -> MachineInfo:
        """Register a machine.

        Args:
            machine_id: Identifier used above the wire (1..128 characters).
            wire_id: 32-bit id the machine puts in its datagrams.
            secret: HMAC key shared with the machine (≥ 16 bytes).
            model: Built-in machine name or machine description TOML text.
            metadata: JSON object (owner, site, ...).

        Raises:
            StorageError: Invalid values, or the machine id or wire id is already registered.
        """
        machines_mod.check_new(machine_id, wire_id, secret)
        row = MachineRow(machine_id=machine_id, wire_id=wire_id, model=model, secret=bytes(secret),
                         meta_json=json.dumps(metadata or {}))
        try:
            with self._session() as s, s.begin():
                s.add(row)
        except IntegrityError as exc:
            raise StorageError(f"machine {machine_id!r} or wire id {wire_id} is already "
                               "registered; choose unused ones") from exc
        return machines_mod.to_info(row)

    def get_machine(self, machine_id: str) -> MachineInfo:
        """Public info of one machine, with the version of its stored known payload and its
        late-data version (:mod:`cranetwin.storage.late_version`), read in the statement that
        reads its newest block (no round trip of their own; one snapshot for the three).

        Raises:
            UnknownMachineError: No such machine.
        """
        with self._session() as s:
            row = machines_mod.get_row(s, machine_id)
            b, m = blocks_mod.BlockRow, MachineRow
            newest = (select(func.max(b.t_end_ns)).where(b.machine_pk == m.id)
                      .correlate(m).scalar_subquery())
            t, version, late = s.execute(select(newest, payload_version.column(m.machine_id),
                                                late_version.column(m.machine_id))
                                         .where(m.id == row.id)).one()
            return machines_mod.to_info(row, None if t is None else int(t),
                                        payload_version=int(version or 0),
                                        late_version=int(late or 0))

    def machines(self) -> list[MachineInfo]:
        """Every registered machine, ordered by machine id (no secrets)."""
        with self._session() as s:
            rows = s.scalars(select(MachineRow).order_by(MachineRow.machine_id)).all()
            newest = self._newest_block_ns(s, [r.id for r in rows])
            return [machines_mod.to_info(r, newest.get(r.id)) for r in rows]

    @staticmethod
    def _newest_block_ns(s: Session, pks: Sequence[int]) -> dict[int, int]:
        """End time of each machine's newest block [ns]: one statement, one index probe per
        machine in the server (a round trip per machine cost a fleet of 1000 a second per
        listing); the write path does not update the machine row, so ingest never contends on
        it."""
        if not pks:
            return {}
        b, m = blocks_mod.BlockRow, MachineRow
        newest = (select(func.max(b.t_end_ns)).where(b.machine_pk == m.id)
                  .correlate(m).scalar_subquery())
        rows = s.execute(select(m.id, newest).where(m.id.in_(list(pks)))).all()
        return {int(pk): int(t) for pk, t in rows if t is not None}

    def machine_keys(self) -> dict[int, tuple[str, bytes]]:
        """What the ingest daemon needs to verify datagrams: wire_id → (machine_id, secret)."""
        with self._session() as s:
            rows = s.execute(select(MachineRow.wire_id, MachineRow.machine_id, MachineRow.secret))
            return {int(w): (m, bytes(k)) for w, m, k in rows}

    def update_status(self, machine_id: str, t_s: float, *, latitude_deg: float | None = None,
                      longitude_deg: float | None = None, altitude_m: float | None = None,
                      operating_hours: float | None = None) -> None:
        """Record a low-rate status report (GPS, operating hours) unless a newer one is stored.

        Raises:
            UnknownMachineError: No such machine.
        """
        t = _ns(t_s)
        with self._session() as s, s.begin():
            row = machines_mod.get_row(s, machine_id)
            if row.status_ns is not None and row.status_ns >= t:
                return
            row.status_ns = t
            row.last_seen_ns = max(row.last_seen_ns or t, t)
            for name, v in (("latitude_deg", latitude_deg), ("longitude_deg", longitude_deg),
                            ("altitude_m", altitude_m), ("operating_hours", operating_hours)):
                if v is not None:
                    setattr(row, name, float(v))

    # -- raw samples ----------------------------------------------------------------------
    def write_batch(self, blocks: Sequence[SampleBlock]) -> WriteResult:
        """Store sample blocks of any machines in one transaction, durable when this returns; one
        block that cannot be stored never fails the others.

        Per block the result says: ``stored`` (new), ``duplicate`` (the same (machine, epoch,
        seq) with the same t_start, n and period is stored: durable, may be acknowledged) or
        ``refused`` with a reason, ``seq_reused``, ``overlap``, ``unstorable`` or
        ``unknown_machine`` (see :mod:`cranetwin.storage.writes`), which a retry never changes.
        Summaries are updated from the newly stored blocks only.

        Returns:
            :class:`~cranetwin.storage.writes.WriteResult`, one outcome per input block.

        Raises:
            StorageUnavailableError: The database is unreachable, the connection was lost, or it
                stayed locked beyond the busy timeout; nothing was stored: retry with backoff.
            StorageError: Any other database failure; nothing was stored.
        """
        if not blocks:
            return WriteResult((), ())
        pks = self._machine_pks({b.machine_id for b in blocks if isinstance(b.machine_id, str)})
        return self._write(blocks, pks)

    def _write(self, blocks: Sequence[SampleBlock], pks: dict[str, int]) -> WriteResult:
        """:func:`cranetwin.storage.writes.write`, with the time partitions made first."""
        part = self._ensure_partitions(blocks)
        res = writes_mod.write(self._session, blocks, pks)
        if part is None:
            return res
        lost = [i for i, o in enumerate(res.outcomes)
                if o.reason == "unstorable"
                and any(t in o.detail for t in partitions_mod.NO_PARTITION)]
        if not lost:
            return res
        # a partition this process knew was dropped meanwhile (retention): create it again
        part.forget()
        sub = [blocks[i] for i in lost]
        self._ensure_partitions(sub)
        again = writes_mod.write(self._session, sub, pks)
        outcomes = list(res.outcomes)
        for i, o in zip(lost, again.outcomes, strict=True):
            outcomes[i] = o
        return WriteResult(res.blocks, tuple(outcomes))

    def maintain_partitions(self, now_s: float, *, ahead: int = 2, interval: str | None = None,
                            keep_days: float | None = None,
                            margin_s: float = 0.0) -> partitions_mod.RetentionResult:
        """PostgreSQL: create the time partitions ahead, apply retention
        (:func:`cranetwin.storage.partitions.maintain`); a no-op on SQLite."""
        try:
            res = partitions_mod.maintain(self.engine, now_s, ahead=ahead, interval=interval,
                                          keep_days=keep_days, margin_s=margin_s)
        except SQLAlchemyError as exc:
            if is_unavailable(exc):
                raise unavailable("partition maintenance", exc) from exc
            raise StorageError(f"partition maintenance failed: {exc}".splitlines()[0]) from exc
        if res.dropped and self._partitioner is not None:
            self._partitioner.forget()
        return res

    def _ensure_partitions(self, blocks: Sequence[SampleBlock]
                           ) -> partitions_mod.Partitioner | None:
        """PostgreSQL: create the time partitions the blocks need (usually none: cached);
        returns the partitioner, None on SQLite."""
        try:
            if self._partitioned is None:
                with self.engine.connect() as c:
                    self._partitioned = partitions_mod.is_partitioned(c)
                if self._partitioned:
                    self._partitioner = partitions_mod.Partitioner(self.engine)
            if self._partitioner is not None:
                self._partitioner.ensure(int(b.t0_ns) for b in blocks
                                         if isinstance(b.t0_ns, int | np.integer))
        except SQLAlchemyError as exc:
            if is_unavailable(exc):
                raise unavailable(f"storing {len(blocks)} block(s)", exc) from exc
            raise StorageError(f"could not create the partitions of {len(blocks)} block(s), "
                               f"nothing stored: {exc}".splitlines()[0]) from exc
        return self._partitioner

    def write_blocks(self, blocks: Sequence[SampleBlock]) -> int:
        """Like :meth:`store_blocks`, returning the number of blocks newly stored."""
        return len(self.store_blocks(blocks))

    def store_blocks(self, blocks: Sequence[SampleBlock]) -> list[SampleBlock]:
        """:meth:`write_batch` for callers that treat any refusal as an error: returns the blocks
        newly stored, in input order (duplicates are ignored).

        Raises:
            UnknownMachineError: A block names an unregistered machine (nothing stored).
            StorageError: A block was refused (the others are stored), or the database failed
                (nothing stored; :class:`StorageUnavailableError` when it is unavailable).
        """
        if not blocks:
            return []
        ids = {b.machine_id for b in blocks}
        pks = self._machine_pks({i for i in ids if isinstance(i, str)})
        unknown = sorted(str(i) for i in ids if i not in pks)
        if unknown:
            raise UnknownMachineError(f"no machine {unknown[0]!r} is registered; add it first "
                                      "(cranetwin machines add)")
        res = self._write(blocks, pks)
        bad = res.refused
        if bad:
            b, o = bad[0]
            raise StorageError(f"{len(bad)} of {len(blocks)} block(s) refused (the others are "
                               f"stored); first: {b.machine_id} epoch {b.epoch} seq {b.seq}: "
                               f"{o.reason}: {o.detail}")
        return res.new

    def _machine_pks(self, machine_ids: set[str]) -> dict[str, int]:
        """Primary keys of the registered machines among ``machine_ids`` (cached; one query
        for all machines when one is not cached yet).

        Raises:
            StorageUnavailableError: The database is unavailable.
        """
        if not machine_ids <= self._pk.keys():
            try:
                with self._session() as s:
                    rows = s.execute(select(MachineRow.machine_id, MachineRow.id)).all()
            except SQLAlchemyError as exc:
                if is_unavailable(exc):
                    raise unavailable("machine lookup", exc) from exc
                raise StorageError(f"could not look up machines: {exc}") from exc
            self._pk.update({m: int(i) for m, i in rows})
        return {m: self._pk[m] for m in machine_ids if m in self._pk}

    def read_samples(self, machine_id: str, t0_s: float, t1_s: float) -> SampleArrays:
        """Samples of one machine with t0_s ≤ t < t1_s, oldest first.

        Blocks with different channel layouts are merged on the union of their channels (NaN
        where a block lacks a channel). A timestamp stored twice (two blocks overlapping) appears
        once. Both bounds are shifted down by 1 µs (``_EPS_NS``) so that a bound given as the
        float64 seconds of a sample time (≈ 0.24 µs resolution today) includes that sample at
        ``t0_s`` and excludes it at ``t1_s``.

        Times are exact: ``t_ns`` is ``t0_ns + k · period_ns`` of each stored run, ``t_s`` is
        ``t_ns / 1e9``. ``period_ns`` is the stored period when every block contributing a
        sample has the same one; when the period changes inside the range (the machine changed
        its rate) it is None (no one period describes the range) while ``t_ns`` stays exact.
        Values are ``steps · resolution`` of the stored integer steps, bit for bit what the
        wire decoder produced.

        Returns:
            ``SampleArrays`` with t_s, t_ns shape (n,) strictly increasing, values (n, c).
        """
        t0, t1 = sample_bounds_ns(t0_s, t1_s)
        with self._session() as s:
            stored = blocks_mod.read_range(s, self._machine_pk(s, machine_id), t0, t1 - 1)
        return assemble_samples(machine_id, stored, t0, t1)


    def data_range(self, machine_id: str) -> tuple[float, float] | None:
        """Time span of the stored samples of one machine (one index probe).

        Returns:
            ``(first, last)``: start of the oldest block and end of the newest block [s since
            the epoch], or None when nothing is stored.

        Raises:
            UnknownMachineError: No such machine.
        """
        b = blocks_mod.BlockRow
        with self._session() as s:
            pk = self._machine_pk(s, machine_id)
            lo, hi = s.execute(select(func.min(b.t_start_ns), func.max(b.t_end_ns))
                               .where(b.machine_pk == pk)).one()
        return None if lo is None else (int(lo) / 1e9, int(hi) / 1e9)

    def next_block_start(self, machine_id: str, after_s: float) -> float | None:
        """Start of the oldest stored block that ends at or after ``after_s`` [s], or None.

        Raises:
            UnknownMachineError: No such machine.
        """
        b = blocks_mod.BlockRow
        with self._session() as s:
            pk = self._machine_pk(s, machine_id)
            t = _ns(after_s)
            r = s.execute(select(func.min(b.t_start_ns)).where(
                b.machine_pk == pk, b.t_end_ns >= t,
                b.t_start_ns >= blocks_mod.clamp_ns(t - blocks_mod.MAX_SPAN_NS))).scalar()
        return None if r is None else int(r) / 1e9

    def stats(self, machine_id: str | None = None) -> StorageStats:
        """Number of blocks and samples and compressed bytes stored (one machine or all)."""
        b = blocks_mod.BlockRow
        stmt = select(func.count(), func.coalesce(func.sum(b.n), 0),
                      func.coalesce(func.sum(func.length(b.data)), 0))
        with self._session() as s:
            if machine_id is not None:
                stmt = stmt.where(b.machine_pk == self._machine_pk(s, machine_id))
            nb, ns, nbytes = s.execute(stmt).one()
        return StorageStats(int(nb), int(ns), int(nbytes))

    # -- known payload --------------------------------------------------------------------
    def write_payload(self, machine_id: str, payload_kg: F64, *, t_s: F64 | None = None,
                      t_ns: npt.NDArray[np.int64] | None = None) -> PayloadWrite:
        """Store a known payload series of one machine in one transaction
        (:mod:`cranetwin.storage.payloads`): cut into runs of equal spacing, each stored once
        (writing the same series again stores nothing new).

        Args:
            machine_id: The machine.
            payload_kg: Payload [kg], shape (n,); NaN = not known (stored as such).
            t_s: Times [s since the Unix epoch], shape (n,), strictly increasing, rounded to
                the µs (float64 epoch seconds resolve ≈ 0.24 µs: rounded to the ns, a regular
                series would not be regular); or
            t_ns: the exact times [ns] instead.

        Raises:
            UnknownMachineError: No such machine.
            StorageError: Bad shapes or times, a negative or infinite payload (nothing stored).
        """
        if (t_s is None) == (t_ns is None):
            raise StorageError("write_payload: give t_s or t_ns (one of them)")
        t = (np.asarray(t_ns, dtype=np.int64) if t_ns is not None
             else np.rint(np.asarray(t_s, dtype=np.float64) * 1e6).astype(np.int64) * 1000)
        return self.write_payload_runs(machine_id, payloads_mod.runs_of(t, payload_kg))

    def write_payload_runs(self, machine_id: str, runs: Sequence[PayloadRun]) -> PayloadWrite:
        """:meth:`write_payload` of runs already cut (the importer: one per sample block, at
        the block's sample times).

        Raises:
            UnknownMachineError: No such machine.
            StorageUnavailableError: The database is unavailable (nothing stored).
            StorageError: A run cannot be stored (nothing stored).
        """
        if not runs:
            return PayloadWrite()
        try:
            with self._session() as s, s.begin():
                res = payloads_mod.write(s, self._machine_pk(s, machine_id), runs)
                new = set(res.new_starts)
                # the whole span of each new run, NaN values too: a read takes each time from
                # the earliest-starting run, so a NaN there can hide a later run's known value
                redo.request(s, machine_id, [(r.t0_ns, r.t_end_ns) for r in runs
                                             if r.t0_ns in new])
                if res.stored:
                    payload_version.bump(s, machine_id)
                return res
        except SQLAlchemyError as exc:
            if is_unavailable(exc):
                raise unavailable(f"storing {len(runs)} payload run(s)", exc) from exc
            raise StorageError(f"could not store {len(runs)} payload run(s): "
                               f"{exc}".splitlines()[0]) from exc

    def delete_payload_runs(self, machine_id: str, starts_ns: Sequence[int]) -> int:
        """Delete the stored payload runs of a machine that start at ``starts_ns`` [ns] (the
        importer: runs it stored for blocks that storage then refused); returns how many.

        Raises:
            UnknownMachineError: No such machine.
        """
        if not starts_ns:
            return 0
        with self._session() as s, s.begin():
            res = payloads_mod.delete(s, self._machine_pk(s, machine_id), starts_ns)
            redo.request(s, machine_id, res.changed_ns)
            if res.runs_deleted:
                payload_version.bump(s, machine_id)
            return res.runs_deleted

    def delete_payload(self, machine_id: str, t0_s: float, t1_s: float) -> PayloadDelete:
        """Delete the stored known payload of one machine with t0_s ≤ t < t1_s, in one
        transaction (:func:`cranetwin.storage.payloads.delete_range`: runs straddling a bound
        are cut there), and record the changed times for the twin worker to process again
        (:mod:`cranetwin.storage.redo`).

        Raises:
            UnknownMachineError: No such machine.
        """
        t0, t1 = _payload_bounds_ns(t0_s, t1_s)
        with self._session() as s, s.begin():
            res = payloads_mod.delete_range(s, self._machine_pk(s, machine_id), t0, t1)
            redo.request(s, machine_id, res.changed_ns)
            if res.runs_deleted or res.runs_cut:
                payload_version.bump(s, machine_id)
            return res

    def request_redo(self, machine_id: str, t0_s: float, t1_s: float) -> redo.RedoRequest:
        """Record an operator's request that the twin worker process again every window of
        one machine with t0_s ≤ t < t1_s [s] that holds stored samples — processed, failed or
        never processed (:func:`cranetwin.storage.redo.request_whole`; ``cranetwin worker
        redo``); returns the request as stored.

        Raises:
            UnknownMachineError: No such machine.
            StorageError: ``t1_s`` not after ``t0_s``.
        """
        t0, t1 = _ns(t0_s), _ns(t1_s)
        if not t1 > t0:
            raise StorageError(f"a redo range must end after it starts ({t0_s} s, {t1_s} s)")
        with self._session() as s, s.begin():
            self._machine_pk(s, machine_id)
            return redo.request_whole(s, machine_id, t0, t1 - 1)

    def payload_version(self, machine_id: str) -> int:
        """The version of the machine's stored known payload
        (:mod:`cranetwin.storage.payload_version`: raised by every change of it, by any
        process; 0 when it never changed), in one primary-key lookup."""
        with self._session() as s:
            return payload_version.read(s, machine_id)

    def payload_stretches(self, machine_id: str, t0_s: float | None = None,
                          t1_s: float | None = None) -> list[Stretch]:
        """The stored known payload of one machine as stretches of runs without a gap
        (:func:`cranetwin.storage.payloads.stretches`), of the runs starting in [t0_s, t1_s)
        (None: unbounded).

        Raises:
            UnknownMachineError: No such machine.
        """
        t0, t1 = _payload_bounds_ns(t0_s, t1_s)
        with self._session() as s:
            return payloads_mod.stretches(s, self._machine_pk(s, machine_id), t0, t1)

    def read_payload(self, machine_id: str, t0_s: float, t1_s: float) -> PayloadSeries:
        """The stored known payload of one machine with t0_s ≤ t < t1_s, oldest first, with
        the bounds of :meth:`read_samples` (so it covers the samples that call returns).

        Returns:
            :class:`~cranetwin.storage.payloads.PayloadSeries`: ``t_s``, ``t_ns`` and
            ``payload_kg`` [kg] shape (n,), NaN where not known; empty when none is stored.

        Raises:
            UnknownMachineError: No such machine.
        """
        t0, t1 = sample_bounds_ns(t0_s, t1_s)
        with self._session() as s:
            return payloads_mod.read(s, machine_id, self._machine_pk(s, machine_id), t0, t1)

    # -- summaries ------------------------------------------------------------------------
    def summaries(self, machine_id: str, channels: Iterable[str], t0_s: float, t1_s: float,
                  max_points: int = 1000) -> Summaries:
        """Min/max/mean per bucket of [t0_s, t1_s), at most ``max_points`` buckets per channel.

        Reads only the summaries table (1-s buckets for spans up to ``max_points`` seconds,
        1-min buckets, merged into wider ones, beyond), never raw samples.
        """
        with self._session() as s:
            pk = self._machine_pk(s, machine_id)
            return summaries_mod.query(s, pk, machine_id, channels, t0_s, t1_s, max_points)

    def rollup(self, before_s: float | None = None) -> int:
        """Recompute stale 1-min summaries of raw channels (an optimisation: queries are exact
        without it). The ingest daemon calls it periodically and on shutdown.

        One bad row never stops it: a block whose per-second summary cannot be decoded is left
        out (counted in :attr:`corrupt_summaries`), a minute that cannot be rolled up is logged,
        dropped from ``summary_dirty`` and counted in :attr:`rollup_skipped`; the others roll up.

        Args:
            before_s: Only minutes ending at or before this time [s since the epoch]; None = all.

        Returns:
            Number of machine-minutes rolled up.

        Raises:
            StorageUnavailableError: The database is unavailable (nothing written; retry later).
            StorageError: Another database failure.
        """
        got = summaries_mod.rollup(self._session, before_s)
        self.rollup_skipped += got.skipped
        self.corrupt_summaries += got.corrupt
        return got.rolled

    def write_summaries(self, machine_id: str, t_s: F64, channels: Sequence[str],
                        values: F64) -> int:
        """Store summaries of derived channels (e.g. ``force:lift``) computed by the twin.

        The 1-s and 1-min buckets that ``t_s`` touches are overwritten (idempotent re-runs);
        write whole minutes to keep the 1-min buckets complete.

        Args:
            machine_id: Machine identifier.
            t_s: Sample times, shape (n,) [s], non-decreasing.
            channels: Derived channel names, length c.
            values: Shape (n, c) [channel units]; NaN = missing.

        Returns:
            Number of 1-s bucket rows written.
        """
        t = np.asarray(t_s, dtype=np.float64)
        v = np.asarray(values, dtype=np.float64)
        if t.ndim != 1 or v.shape != (t.size, len(channels)):
            raise StorageError(f"values shape {v.shape} must be (len(t_s), len(channels)) = "
                               f"({t.size}, {len(channels)})")
        if t.size == 0:
            return 0
        if np.any(np.diff(t) < 0):
            raise StorageError("t_s must be non-decreasing")
        t_ns = np.rint(t * 1e9).astype(np.int64)
        with self._session() as s, s.begin():
            pk = self._machine_pk(s, machine_id)
            return summaries_mod.replace(s, pk, channels, t_ns, v)

    # -- events ---------------------------------------------------------------------------
    def add_events(self, events: Sequence[Event]) -> int:
        """Store events; one already stored (same machine, time, kind) is ignored.

        Returns:
            Number of events newly stored.
        """
        for e in events:
            if e.severity not in events_mod.SEVERITIES:
                raise StorageError(f"event severity {e.severity!r} must be one of "
                                   f"{events_mod.SEVERITIES}")
        if not events:
            return 0
        with self._session() as s, s.begin():
            rows = [{"machine_pk": self._machine_pk(s, e.machine_id), "t_ns": _ns(e.t_s),
                     "kind": e.kind, "severity": e.severity,
                     "evidence_json": json.dumps(e.evidence)} for e in events]
            stmt = events_mod.insert_ignoring_stored(self.dialect)
            return len(s.execute(stmt, rows).all())

    def events(self, machine_id: str, t0_s: float, t1_s: float, kinds: Iterable[str] | None = None,
               limit: int | None = None) -> list[Event]:
        """Events of one machine with t0_s ≤ t < t1_s, oldest first (optionally of some kinds)."""
        with self._session() as s:
            pk = self._machine_pk(s, machine_id)
            stmt = (select(EventRow).where(EventRow.machine_pk == pk,
                                           EventRow.t_ns >= _ns(t0_s), EventRow.t_ns < _ns(t1_s))
                    .order_by(EventRow.t_ns, EventRow.id))
            if kinds is not None:
                stmt = stmt.where(EventRow.kind.in_(list(kinds)))
            if limit is not None:
                stmt = stmt.limit(limit)
            return [events_mod.to_event(machine_id, r) for r in s.scalars(stmt)]


def sample_bounds_ns(t0_s: float, t1_s: float) -> tuple[int, int]:
    """The bounds [ns] :meth:`Store.read_samples` reads (blocks overlapping [t0, t1 − 1])."""
    return (blocks_mod.clamp_ns(_ns(t0_s) - _EPS_NS), blocks_mod.clamp_ns(_ns(t1_s) - _EPS_NS))


def _payload_bounds_ns(t0_s: float | None, t1_s: float | None) -> tuple[int, int]:
    """The bounds [ns] of :meth:`Store.read_payload` for [t0_s, t1_s) (None: unbounded), so
    a delete removes exactly what that read returns."""
    return sample_bounds_ns(-np.inf if t0_s is None else t0_s,
                            np.inf if t1_s is None else t1_s)


def assemble_samples(machine_id: str, stored: list[blocks_mod.StoredBlock], t0: int,
                     t1: int) -> SampleArrays:
    """The samples of ``stored`` (read for :func:`sample_bounds_ns` ``t0``, ``t1``) with
    t0 ≤ t < t1, as :meth:`Store.read_samples` returns them."""
    chans: dict[str, int] = {}
    for b in stored:
        for c in b.channels:
            chans.setdefault(c, len(chans))
    if not stored:
        return SampleArrays(machine_id, np.zeros(0), (), np.zeros((0, 0)),
                            t_ns=np.zeros(0, dtype=np.int64))
    t_all = np.concatenate([b.times_ns() for b in stored])
    vals: F64 = np.full((t_all.size, len(chans)), np.nan)
    keep = (t_all >= t0) & (t_all < t1)
    periods: set[int] = set()
    row = 0
    for b in stored:
        cols = [chans[c] for c in b.channels]
        vals[row:row + b.n, cols] = b.values
        if keep[row:row + b.n].any():
            periods.add(b.period_ns)
        row += b.n
    t_all, vals = t_all[keep], vals[keep]
    t_u, first = np.unique(t_all, return_index=True)  # sorted, first occurrence kept
    period = next(iter(periods)) if len(periods) == 1 else None
    return SampleArrays(machine_id, t_u.astype(np.float64) / 1e9, tuple(chans), vals[first],
                        period_ns=period, t_ns=t_u)
