"""Machines sharded across several databases by a partition map: :class:`ShardedStore`.

A shard map sends each of P machine partitions to one database URL; a machine's partition is
:func:`cranetwin.storage.sharding.partition_of` (the function the fleet bus and the twin workers
use), so with equal P a bus partition, a worker partition and a shard partition hold the same
machines. Every shard is an ordinary :class:`~cranetwin.storage.Store` with the full schema.

:class:`ShardedStore` is a :class:`~cranetwin.storage.Store`: per-machine calls go to the
machine's shard; fleet-wide calls (machine list, machine keys, storage statistics, rollup,
partition maintenance) go to every shard and are merged (the machine list and keys of a shard
that is unavailable are the ones last read from it, so a daemon keeps verifying its machines);
:meth:`ShardedStore.write_batch` splits a batch by shard. A shard that fails with
:class:`StorageUnavailableError` only holds back its own machines: their blocks come back
``unavailable`` (neither acknowledged nor refused) while the other shards' blocks are stored,
and the shard is skipped for a short, growing pause (0.25 s doubling up to 5 s) before it is
tried again, so a dead server costs one connection timeout per pause, not one per batch. A shard
unreachable at start is migrated on its first successful use.

The shard of partition 0 is the *home* shard: :attr:`Store.engine` is its engine, so the
tables that belong to no machine (API keys, service state) live there.

:func:`open_store` is the one constructor every process uses (ingest daemon, storage writer,
twin worker, API, command line): a :class:`StoreSpec` without shards opens one plain
:class:`~cranetwin.storage.Store`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from typing import Any, TypeVar

from sqlalchemy import Engine

from cranetwin.errors import StorageError, StorageUnavailableError
from cranetwin.samples import F64, SampleArrays, SampleBlock
from cranetwin.storage.dberrors import unavailable, unavailable_in_chain
from cranetwin.storage.engine import BUSY_TIMEOUT_S, display_url, make_engine, migrate
from cranetwin.storage.events import Event
from cranetwin.storage.machines import MachineInfo
from cranetwin.storage.partitions import RetentionResult
from cranetwin.storage.payloads import (
    PayloadDelete,
    PayloadRun,
    PayloadSeries,
    PayloadWrite,
    Stretch,
)
from cranetwin.storage.redo import RedoRequest
from cranetwin.storage.shardmap import ShardMap, ShardMapError, StoreSpec, store_spec
from cranetwin.storage.store import StorageStats, Store
from cranetwin.storage.summaries import Summaries
from cranetwin.storage.writes import BlockOutcome, WriteResult, unavailable_outcome

__all__ = ["ShardMap", "ShardMapError", "ShardedStore", "StoreSpec", "open_store", "store_spec"]

log = logging.getLogger(__name__)

T = TypeVar("T")
PAUSE_MIN_S = 0.25
PAUSE_MAX_S = 5.0


def open_store(target: str | StoreSpec, *, echo: bool = False,
               busy_timeout_s: float = BUSY_TIMEOUT_S) -> Store:
    """Open the store of ``target``: a plain :class:`Store` (migrated) for a URL or a spec
    without shards, else a :class:`ShardedStore` over every shard.

    Raises:
        StorageUnavailableError: The (unsharded) database is unreachable.
        StorageError: Bad URL, bad shard map or failed migration.
    """
    spec = StoreSpec(target) if isinstance(target, str) else target
    m = spec.shard_map()
    if m is None:
        return Store.open(spec.url, echo=echo, busy_timeout_s=busy_timeout_s)
    return ShardedStore.open_map(m, echo=echo, busy_timeout_s=busy_timeout_s)


class ShardedStore(Store):
    """A :class:`Store` over the shards of a :class:`ShardMap` (see the module docstring).

    Args:
        shards: One store per shard, in the map's order (migrated or not: see ``ready``).
        shard_map: The partition map.
        ready: Per shard, whether its schema is known to be migrated (default: all).
    """

    def __init__(self, shards: Sequence[Store], shard_map: ShardMap,
                 ready: Sequence[bool] | None = None) -> None:
        if len(shards) != len(shard_map.urls):
            raise ShardMapError(f"{len(shards)} stores for {len(shard_map.urls)} shards")
        super().__init__(shards[shard_map.owner[0]].engine)
        self.shards = list(shards)
        self.map = shard_map
        self.ready = list(ready) if ready is not None else [True] * len(shards)
        self._pause = [0.0] * len(shards)
        self._until = [0.0] * len(shards)
        self._keys: list[dict[int, tuple[str, bytes]]] = [{} for _ in shards]
        self._machines: list[list[MachineInfo]] = [[] for _ in shards]
        self._lock = threading.Lock()

    @classmethod
    def open_map(cls, shard_map: ShardMap, *, echo: bool = False,
                 busy_timeout_s: float = BUSY_TIMEOUT_S) -> ShardedStore:
        """Engines for every shard, each migrated now or, if unreachable, on first use."""
        stores: list[Store] = []
        ready: list[bool] = []
        for url in shard_map.urls:
            st = Store(make_engine(url, echo=echo, busy_timeout_s=busy_timeout_s))
            try:
                migrate(st.engine)
                ready.append(True)
            except StorageUnavailableError as exc:
                log.error("shard %s unavailable at start (migrated on first use): %s",
                          display_url(url), exc)
                ready.append(False)
            stores.append(st)
        log.info("storage sharded over %d database(s): %s", len(stores),
                 "; ".join(shard_map.describe()))
        return cls(stores, shard_map, ready)

    def close(self) -> None:
        for s in self.shards:
            s.close()

    # -- routing --------------------------------------------------------------------------------
    def shard_of(self, machine_id: str) -> int:
        """The shard index of a machine."""
        return self.map.shard_of(machine_id)

    def engine_for(self, machine_id: str) -> Engine:
        return self.shards[self.shard_of(machine_id)].engine

    def engines_of(self, machine_ids: Iterable[str]) -> list[tuple[Engine, list[str]]]:
        groups: dict[int, list[str]] = {}
        for m in machine_ids:
            groups.setdefault(self.shard_of(m), []).append(m)
        return [(self.shards[i].engine, ids) for i, ids in sorted(groups.items())]

    @property
    def engines(self) -> list[Engine]:
        return [s.engine for s in self.shards]

    def _call(self, i: int, fn: Callable[[Store], T]) -> T:
        """``fn(shard i)``, unless the shard is pausing after a failure; an unavailable shard
        starts (or lengthens) its pause.

        Raises:
            StorageUnavailableError: The shard is pausing or just failed.
        """
        url = display_url(self.map.urls[i])
        now = time.monotonic()
        with self._lock:
            if now < self._until[i]:
                raise StorageUnavailableError(f"shard {i} ({url}) is unavailable; tried again "
                                              f"in {self._until[i] - now:.1f} s")
        try:
            if not self.ready[i]:
                migrate(self.shards[i].engine)
                self.ready[i] = True
            out = fn(self.shards[i])
        except Exception as exc:
            if not unavailable_in_chain(exc):
                raise
            with self._lock:
                self._pause[i] = min(max(2 * self._pause[i], PAUSE_MIN_S), PAUSE_MAX_S)
                self._until[i] = time.monotonic() + self._pause[i]
            if isinstance(exc, StorageUnavailableError):
                raise
            raise unavailable(f"shard {i} ({url})", exc) from exc
        if self._pause[i]:
            with self._lock:
                self._pause[i], self._until[i] = 0.0, 0.0
            log.warning("shard %d (%s) available again", i, url)
        return out

    def _one(self, machine_id: str, fn: Callable[[Store], T]) -> T:
        return self._call(self.shard_of(machine_id), fn)

    def _all(self, fn: Callable[[Store], T]) -> list[T]:
        return [self._call(i, fn) for i in range(len(self.shards))]

    # -- machines -------------------------------------------------------------------------------
    def add_machine(self, machine_id: str, wire_id: int, secret: bytes, model: str = "patu655",
                    metadata: dict[str, Any] | None = None) -> MachineInfo:
        """Register a machine on its shard; a wire id must be unused on every shard (checked
        first; two registrations racing on two shards are not caught)."""
        if wire_id in self.machine_keys():
            raise StorageError(f"machine {machine_id!r} or wire id {wire_id} is already "
                               "registered; choose unused ones")
        i = self.shard_of(machine_id)
        info = self._call(i, lambda s: s.add_machine(machine_id, wire_id, secret, model,
                                                     metadata))
        self._keys[i][int(wire_id)] = (machine_id, bytes(secret))
        self._machines[i].append(info)
        return info

    def get_machine(self, machine_id: str) -> MachineInfo:
        return self._one(machine_id, lambda s: s.get_machine(machine_id))

    def machines(self) -> list[MachineInfo]:
        """Every machine of every shard, by machine id; an unavailable shard contributes the
        machines last read from it (none if it was never read), with a warning."""
        out: list[MachineInfo] = []
        for i in range(len(self.shards)):
            try:
                self._machines[i] = self._call(i, lambda s: s.machines())
            except StorageUnavailableError as exc:
                log.warning("machines of shard %d not reloaded (last known listed): %s", i, exc)
            out.extend(self._machines[i])
        return sorted(out, key=lambda m: m.machine_id)

    def machine_keys(self) -> dict[int, tuple[str, bytes]]:
        """Every shard's keys; an unavailable shard contributes the keys last read from it (its
        machines' blocks are then held back by the write, not dropped as unknown)."""
        out: dict[int, tuple[str, bytes]] = {}
        for i in range(len(self.shards)):
            try:
                self._keys[i] = self._call(i, lambda s: s.machine_keys())
            except StorageUnavailableError as exc:
                log.warning("machine keys of shard %d not reloaded: %s", i, exc)
            for w, v in self._keys[i].items():
                if w in out and out[w][0] != v[0]:
                    log.error("wire id %d is registered on two shards (%s, %s): keeping the "
                              "first", w, out[w][0], v[0])
                    continue
                out[w] = v
        return out

    def update_status(self, machine_id: str, t_s: float, *, latitude_deg: float | None = None,
                      longitude_deg: float | None = None, altitude_m: float | None = None,
                      operating_hours: float | None = None) -> None:
        self._one(machine_id, lambda s: s.update_status(
            machine_id, t_s, latitude_deg=latitude_deg, longitude_deg=longitude_deg,
            altitude_m=altitude_m, operating_hours=operating_hours))

    # -- raw samples ----------------------------------------------------------------------------
    def write_batch(self, blocks: Sequence[SampleBlock]) -> WriteResult:
        """:meth:`Store.write_batch` split by shard, one transaction per shard; the blocks of a
        shard that is unavailable come back ``unavailable`` (the others are stored).

        Raises:
            StorageError: A shard failed for another reason than unavailability (blocks of the
                shards written before it are stored: a retry finds them ``duplicate``).
        """
        blocks = list(blocks)
        groups: dict[int, list[int]] = {}
        for k, b in enumerate(blocks):
            i = self.shard_of(b.machine_id) if isinstance(b.machine_id, str) else 0
            groups.setdefault(i, []).append(k)
        outcomes: list[BlockOutcome | None] = [None] * len(blocks)
        for i, idx in sorted(groups.items()):
            sub = [blocks[k] for k in idx]
            try:
                got = list(self._call(i, partial(_write_batch, blocks=sub)).outcomes)
            except StorageUnavailableError as exc:
                detail = " ".join(str(exc).split())[:300]
                got = [unavailable_outcome(detail)] * len(sub)
            for k, o in zip(idx, got, strict=True):
                outcomes[k] = o
        return WriteResult(tuple(blocks), tuple(o for o in outcomes if o is not None))

    def store_blocks(self, blocks: Sequence[SampleBlock]) -> list[SampleBlock]:
        """:meth:`Store.store_blocks` per shard.

        Raises:
            StorageUnavailableError: A shard is unavailable (the other shards' blocks are stored).
        """
        groups: dict[int, list[SampleBlock]] = {}
        for b in blocks:
            groups.setdefault(self.shard_of(str(b.machine_id)), []).append(b)
        new: set[int] = set()
        for i, sub in sorted(groups.items()):
            new.update(id(b) for b in self._call(i, partial(_store_blocks, blocks=sub)))
        return [b for b in blocks if id(b) in new]

    def maintain_partitions(self, now_s: float, *, ahead: int = 2, interval: str | None = None,
                            keep_days: float | None = None,
                            margin_s: float = 0.0) -> RetentionResult:
        """Time partitions ahead and retention on every shard (names prefixed ``shard<i>:``)."""
        dropped: list[str] = []
        kept: list[tuple[str, str]] = []
        runs = 0
        for i, r in enumerate(self._all(lambda s: s.maintain_partitions(
                now_s, ahead=ahead, interval=interval, keep_days=keep_days,
                margin_s=margin_s))):
            dropped.extend(f"shard{i}:{n}" for n in r.dropped)
            kept.extend((f"shard{i}:{n}", why) for n, why in r.kept)
            runs += r.payload_runs
        return RetentionResult(dropped, kept, runs)

    def read_samples(self, machine_id: str, t0_s: float, t1_s: float) -> SampleArrays:
        return self._one(machine_id, lambda s: s.read_samples(machine_id, t0_s, t1_s))

    def data_range(self, machine_id: str) -> tuple[float, float] | None:
        return self._one(machine_id, lambda s: s.data_range(machine_id))

    def next_block_start(self, machine_id: str, after_s: float) -> float | None:
        return self._one(machine_id, lambda s: s.next_block_start(machine_id, after_s))

    def stats(self, machine_id: str | None = None) -> StorageStats:
        if machine_id is not None:
            return self._one(machine_id, lambda s: s.stats(machine_id))
        parts = self._all(lambda s: s.stats())
        return StorageStats(sum(p.blocks for p in parts), sum(p.samples for p in parts),
                            sum(p.data_bytes for p in parts))

    # -- known payload --------------------------------------------------------------------------
    def write_payload_runs(self, machine_id: str, runs: Sequence[PayloadRun]) -> PayloadWrite:
        """:meth:`Store.write_payload_runs` on the machine's shard (:meth:`Store.write_payload`
        cuts the series and comes here)."""
        return self._one(machine_id, lambda s: s.write_payload_runs(machine_id, runs))

    def delete_payload_runs(self, machine_id: str, starts_ns: Sequence[int]) -> int:
        return self._one(machine_id, lambda s: s.delete_payload_runs(machine_id, starts_ns))

    def read_payload(self, machine_id: str, t0_s: float, t1_s: float) -> PayloadSeries:
        return self._one(machine_id, lambda s: s.read_payload(machine_id, t0_s, t1_s))

    def delete_payload(self, machine_id: str, t0_s: float, t1_s: float) -> PayloadDelete:
        return self._one(machine_id, lambda s: s.delete_payload(machine_id, t0_s, t1_s))

    def request_redo(self, machine_id: str, t0_s: float, t1_s: float) -> RedoRequest:
        return self._one(machine_id, lambda s: s.request_redo(machine_id, t0_s, t1_s))

    def payload_version(self, machine_id: str) -> int:
        return self._one(machine_id, lambda s: s.payload_version(machine_id))

    def payload_stretches(self, machine_id: str, t0_s: float | None = None,
                          t1_s: float | None = None) -> list[Stretch]:
        return self._one(machine_id, lambda s: s.payload_stretches(machine_id, t0_s, t1_s))

    # -- summaries ------------------------------------------------------------------------------
    def summaries(self, machine_id: str, channels: Iterable[str], t0_s: float, t1_s: float,
                  max_points: int = 1000) -> Summaries:
        chans = list(channels)
        return self._one(machine_id, lambda s: s.summaries(machine_id, chans, t0_s, t1_s,
                                                           max_points))

    def rollup(self, before_s: float | None = None) -> int:
        """Roll up every available shard; an unavailable one is skipped (retried next time)
        unless every shard is.

        Raises:
            StorageUnavailableError: No shard is available.
        """
        rolled, failed = 0, None
        for i in range(len(self.shards)):
            try:
                rolled += self._call(i, lambda s: s.rollup(before_s))
            except StorageUnavailableError as exc:
                failed = exc
        self.rollup_skipped = sum(s.rollup_skipped for s in self.shards)
        self.corrupt_summaries = sum(s.corrupt_summaries for s in self.shards)
        if failed is not None and rolled == 0 and all(
                time.monotonic() < u for u in self._until):
            raise failed
        return rolled

    def write_summaries(self, machine_id: str, t_s: F64, channels: Sequence[str],
                        values: F64) -> int:
        return self._one(machine_id, lambda s: s.write_summaries(machine_id, t_s, channels,
                                                                 values))

    # -- events ---------------------------------------------------------------------------------
    def add_events(self, events: Sequence[Event]) -> int:
        groups: dict[int, list[Event]] = {}
        for e in events:
            groups.setdefault(self.shard_of(e.machine_id), []).append(e)
        return sum(self._call(i, partial(_add_events, events=ev))
                   for i, ev in sorted(groups.items()))

    def events(self, machine_id: str, t0_s: float, t1_s: float, kinds: Iterable[str] | None = None,
               limit: int | None = None) -> list[Event]:
        ks = None if kinds is None else list(kinds)
        return self._one(machine_id, lambda s: s.events(machine_id, t0_s, t1_s, ks, limit))


def _write_batch(s: Store, blocks: Sequence[SampleBlock]) -> WriteResult:
    return s.write_batch(blocks)


def _store_blocks(s: Store, blocks: Sequence[SampleBlock]) -> list[SampleBlock]:
    return s.store_blocks(blocks)


def _add_events(s: Store, events: Sequence[Event]) -> int:
    return s.add_events(events)
