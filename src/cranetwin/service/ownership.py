"""Which machines a twin worker processes: machine partitions owned exclusively.

Machines are spread over ``P`` partitions by a stable hash of their id
(:func:`partition_of`: BLAKE2b of the UTF-8 id, modulo P; the same in every process and
release). ``cranetwin worker --partitions …`` chooses what a worker asks for
(:func:`parse_partitions`):

* ``auto`` (with ``--of P``, default 16): a share of the partitions, rebalanced as workers come
  and go;
* ``I/P``, ``0,3,5`` (with ``--of P``) or ``all``: exactly these partitions.

On PostgreSQL each partition is owned through a session advisory lock
(:class:`cranetwin.storage.locks.SessionLocks`), held for the worker's life on one connection,
so at most one worker processes a partition; when a worker dies its session ends and its
partitions are free for the others at their next poll. Workers in ``auto`` mode also hold a
membership lock, so every worker can count the live auto workers ``A`` and the partitions ``F``
held by fixed-list workers, and aims at ``ceil((P − F) / A)`` partitions: a worker above that
releases its highest partitions (a worker joined), one below it takes free ones
(a worker left or died). Fixed-list workers take their partitions as they become free and keep
them. Rebalancing only happens between machines (never inside a window), and a window's commit
is conditional on the watermark it started from (:mod:`cranetwin.service.worker`), so even a
hand-over that overlaps (a lost connection noticed late) never counts a window twice.

On SQLite (one worker by design) the worker owns its partitions without locks.
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass

from sqlalchemy import Engine

from cranetwin.errors import CraneTwinError
from cranetwin.storage.locks import SessionLocks

log = logging.getLogger(__name__)

DEFAULT_PARTITIONS = 16
MAX_PARTITIONS = 65536


class PartitionSpecError(CraneTwinError):
    """A ``--partitions`` / ``--of`` value that cannot be understood."""


def partition_of(machine_id: str, count: int) -> int:
    """Partition of ``machine_id`` among ``count`` (stable across processes and releases)."""
    h = hashlib.blake2b(machine_id.encode(), digest_size=8).digest()
    return int.from_bytes(h, "big") % count


@dataclass(frozen=True)
class PartitionSpec:
    """What a worker asks for.

    Attributes:
        count: Number of partitions P.
        fixed: The partitions wanted (sorted), or None for ``auto``.
    """

    count: int
    fixed: tuple[int, ...] | None

    @property
    def auto(self) -> bool:
        """Whether the worker takes a rebalanced share."""
        return self.fixed is None


def parse_partitions(text: str, of: int | None = None) -> PartitionSpec:
    """Parse ``auto``, ``all``, ``I/P`` or ``I,J,…`` (with ``of`` = P).

    Raises:
        PartitionSpecError: Malformed, out of range, or P missing or inconsistent.
    """
    t = text.strip().lower()
    if of is not None and not 1 <= of <= MAX_PARTITIONS:
        raise PartitionSpecError(f"--of {of}: expected 1..{MAX_PARTITIONS} partitions")
    if "/" in t:
        a, _, b = t.partition("/")
        try:
            idx, n = [int(x) for x in a.split(",")], int(b)
        except ValueError:
            raise PartitionSpecError(f"--partitions {text!r}: expected I/P, e.g. 0/4") from None
        if of is not None and of != n:
            raise PartitionSpecError(f"--partitions {text!r} says {n} partitions, --of {of}")
        of, t = n, ",".join(str(i) for i in idx)
    count = of if of is not None else DEFAULT_PARTITIONS
    if not 1 <= count <= MAX_PARTITIONS:
        raise PartitionSpecError(f"{count} partitions: expected 1..{MAX_PARTITIONS}")
    if t == "auto":
        return PartitionSpec(count, None)
    if t == "all":
        return PartitionSpec(count, tuple(range(count)))
    try:
        wanted = sorted({int(x) for x in t.split(",") if x.strip()})
    except ValueError:
        raise PartitionSpecError(f"--partitions {text!r}: expected auto, all, I/P or a list "
                                 "of partition numbers") from None
    if of is None and "/" not in text:
        raise PartitionSpecError(f"--partitions {text!r}: a list needs --of P")
    if not wanted or wanted[0] < 0 or wanted[-1] >= count:
        raise PartitionSpecError(f"--partitions {text!r}: numbers must be in 0..{count - 1}")
    return PartitionSpec(count, tuple(wanted))


class Ownership:
    """The partitions this worker owns now (see the module docstring).

    Args:
        spec: What the worker asks for.
        engine: The store's engine; PostgreSQL: locks on a connection of their own.
    """

    def __init__(self, spec: PartitionSpec, engine: Engine) -> None:
        self.spec = spec
        self._locks = SessionLocks(engine) if engine.dialect.name == "postgresql" else None
        self.owned: set[int] = set()
        self._ns_part = self._ns_member = 0
        if self._locks is None:  # SQLite: one worker, no locks
            self.owned = set(range(spec.count) if spec.fixed is None else spec.fixed)

    @property
    def locked(self) -> bool:
        """Whether ownership is enforced by advisory locks (PostgreSQL)."""
        return self._locks is not None

    def owns(self, machine_id: str) -> bool:
        """Whether this worker processes ``machine_id`` now."""
        return partition_of(machine_id, self.spec.count) in self.owned

    def refresh(self) -> set[int]:
        """Re-check the session, then take or release partitions toward this worker's share;
        returns the partitions owned (call between machines, never inside a window)."""
        lk = self._locks
        if lk is None:
            return self.owned
        if not lk.alive():
            if self.owned:
                log.warning("partitions %s lost with the lock session", sorted(self.owned))
            self.owned = set()
            lk.connect()
            n = self.spec.count
            self._ns_part = lk.namespace(f"cranetwin.worker.partition/{n}")
            self._ns_member = lk.namespace(f"cranetwin.worker.auto/{n}")
            if self.spec.auto:
                assert lk.pid is not None
                lk.try_lock(self._ns_member, lk.pid)
        before = set(self.owned)
        if self.spec.fixed is not None:
            for p in self.spec.fixed:
                if p not in self.owned and lk.try_lock(self._ns_part, p):
                    self.owned.add(p)
        else:
            self._rebalance(lk)
        if self.owned != before:
            log.info("partitions owned: %s of %d", sorted(self.owned), self.spec.count)
        return self.owned

    def _rebalance(self, lk: SessionLocks) -> None:
        n = self.spec.count
        held = lk.holders([self._ns_part, self._ns_member])
        members = sorted({h.pid for h in held if h.ns == self._ns_member} | {lk.pid or 0})
        taken = {h.key: h.pid for h in held if h.ns == self._ns_part}
        fixed_held = sum(1 for pid in taken.values() if pid not in members)
        target = math.ceil(max(0, n - fixed_held) / len(members))
        for p in sorted(self.owned, reverse=True)[:max(0, len(self.owned) - target)]:
            lk.unlock(self._ns_part, p)
            self.owned.discard(p)
        if len(self.owned) >= target:
            return
        start = members.index(lk.pid or 0) * n // len(members)  # spread first choices
        for i in range(n):
            p = (start + i) % n
            if p in taken or p in self.owned:
                continue
            if lk.try_lock(self._ns_part, p):
                self.owned.add(p)
                if len(self.owned) >= target:
                    return

    def close(self) -> None:
        """Release everything (ends the lock session)."""
        if self._locks is not None:
            self._locks.close()
        self.owned = set()
