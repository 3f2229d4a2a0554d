"""Storage: machines, raw sample blocks, per-interval summaries and events (SQLite or PostgreSQL).

Entry point: ``Store.open(url)`` (migrates to the newest schema). See :class:`Store`.
"""

from __future__ import annotations

from cranetwin.storage.engine import DEFAULT_URL
from cranetwin.storage.events import Event
from cranetwin.storage.machines import MachineInfo, UnknownMachineError
from cranetwin.storage.store import StorageStats, Store
from cranetwin.storage.summaries import Summaries

__all__ = ["DEFAULT_URL", "Event", "MachineInfo", "StorageStats", "Store", "Summaries",
           "UnknownMachineError"]
