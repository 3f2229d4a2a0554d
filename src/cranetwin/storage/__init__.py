"""Storage: machines, raw sample blocks, per-interval summaries and events (SQLite or PostgreSQL).

Entry point: ``Store.open(url)`` (migrates to the newest schema). See :class:`Store`; ingest
writes with :meth:`Store.write_batch` (:class:`WriteResult`, one :class:`BlockOutcome` per block).
"""

from __future__ import annotations

from cranetwin.errors import StorageUnavailableError
from cranetwin.storage.engine import DEFAULT_URL
from cranetwin.storage.events import Event
from cranetwin.storage.machines import MachineInfo, UnknownMachineError
from cranetwin.storage.store import StorageStats, Store
from cranetwin.storage.summaries import Summaries
from cranetwin.storage.writes import BlockOutcome, WriteResult

__all__ = ["DEFAULT_URL", "BlockOutcome", "Event", "MachineInfo", "StorageStats",
           "StorageUnavailableError", "Store", "Summaries", "UnknownMachineError", "WriteResult"]
