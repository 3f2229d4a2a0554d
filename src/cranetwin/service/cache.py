"""A thread-safe LRU cache for replay results, keyed by (machine, known-payload version,
late-data version, window, rate: :meth:`cranetwin.service.fleet.FleetService.twin_key`),
bounded by entries and by bytes.

Twin results are large (a 60-s window at 50 Hz is a few MB of JSON), so a bound on the number of
entries alone let 64 of them hold hundreds of MB. The byte bound counts what each value holds:
``len`` of ``bytes``, ``nbytes`` of numpy arrays, and the sum over the items of dicts, lists and
tuples (:func:`nbytes_of`); the least recently used entries are evicted until both bounds hold,
and a value larger than the whole byte bound is not cached at all.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, Generic, TypeVar

import numpy as np

V = TypeVar("V")


def nbytes_of(value: Any) -> int:
    """Bytes held by ``value``: ``len`` of bytes/bytearray/str, ``nbytes`` of numpy arrays, the
    sum over the keys and values of dicts and the items of lists and tuples; 8 for anything else
    (numbers, None)."""
    if isinstance(value, bytes | bytearray | memoryview):
        return len(value)
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, str):
        return len(value)
    if isinstance(value, dict):
        return sum(nbytes_of(k) + nbytes_of(v) for k, v in value.items())
    if isinstance(value, list | tuple):
        return sum(nbytes_of(v) for v in value)
    return 8


class LruCache(Generic[V]):
    """Least-recently-used cache of at most ``capacity`` entries and ``max_bytes`` bytes.

    Args:
        capacity: Most entries kept (0 disables caching).
        max_bytes: Most bytes kept, as ``sizer`` counts them (None: no byte bound).
        sizer: Size of a value [bytes] (:func:`nbytes_of` by default).

    Attributes:
        hits: Lookups answered from the cache.
        misses: Lookups that were not.
        evictions: Entries dropped to keep the bounds.
    """

    def __init__(self, capacity: int, max_bytes: int | None = None,
                 sizer: Callable[[Any], int] = nbytes_of) -> None:
        self.capacity = capacity
        self.max_bytes = max_bytes
        self.hits = 0
        self.misses = 0
        self.evictions = 0
        self._sizer = sizer
        self._data: OrderedDict[Hashable, tuple[V, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached values now."""
        return self._bytes

    def get(self, key: Hashable) -> V | None:
        """The cached value of ``key`` (marking it recently used), or None."""
        with self._lock:
            hit = self._data.get(key)
            if hit is not None:
                self._data.move_to_end(key)
                self.hits += 1
                return hit[0]
            self.misses += 1
            return None

    def put(self, key: Hashable, value: V) -> bool:
        """Store ``value``, evicting least recently used entries beyond the bounds.

        Returns:
            Whether it was stored (False: caching is off, or the value alone exceeds
            ``max_bytes``).
        """
        if self.capacity <= 0:
            return False
        size = self._sizer(value)
        if self.max_bytes is not None and size > self.max_bytes:
            return False
        with self._lock:
            old = self._data.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._data[key] = (value, size)
            self._bytes += size
            while len(self._data) > self.capacity or (
                    self.max_bytes is not None and self._bytes > self.max_bytes):
                _, (_, dropped) = self._data.popitem(last=False)
                self._bytes -= dropped
                self.evictions += 1
            return True

    def clear(self) -> None:
        """Drop every entry."""
        with self._lock:
            self._data.clear()
            self._bytes = 0

    def __len__(self) -> int:
        return len(self._data)
