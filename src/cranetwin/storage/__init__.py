"""Storage: machines, raw sample blocks, per-interval summaries and events (SQLite or PostgreSQL).

Entry point: ``open_store(url or StoreSpec)`` (migrates to the newest schema; a spec with a
shard map gives a :class:`ShardedStore`, see :mod:`cranetwin.storage.shards`), or
``Store.open(url)`` for one database. See :class:`Store`; ingest
writes with :meth:`Store.write_batch` (:class:`WriteResult`, one :class:`BlockOutcome` per block).
"""

from __future__ import annotations

from cranetwin.errors import StorageUnavailableError
from cranetwin.storage.engine import DEFAULT_URL
from cranetwin.storage.events import Event
from cranetwin.storage.machines import MachineInfo, UnknownMachineError
from cranetwin.storage.shardmap import StoreSpec, store_spec
from cranetwin.storage.shards import ShardedStore, open_store
from cranetwin.storage.store import StorageStats, Store
from cranetwin.storage.summaries import Summaries
from cranetwin.storage.writes import BlockOutcome, WriteResult

__all__ = ["DEFAULT_URL", "BlockOutcome", "Event", "MachineInfo", "ShardedStore",
           "StorageStats", "StorageUnavailableError", "Store", "StoreSpec", "Summaries",
           "UnknownMachineError", "WriteResult", "open_store", "store_spec"]
