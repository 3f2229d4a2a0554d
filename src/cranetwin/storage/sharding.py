"""Which partition a machine belongs to: one function for every partitioned role.

The fleet bus's subjects (:mod:`cranetwin.bus.subjects`) and the twin workers' ownership
(:mod:`cranetwin.service.ownership`) spread machines over P partitions with the same
:func:`partition_of`, so that with equal P a worker that owns partition p finds exactly the
machines whose blocks arrive on bus partition p.
"""

from __future__ import annotations

import zlib


def partition_of(machine_id: str, partitions: int) -> int:
    """The partition of a machine, 0 … partitions − 1: CRC-32 of its UTF-8 id modulo
    ``partitions`` (stable across processes, hosts and releases)."""
    return zlib.crc32(machine_id.encode()) % partitions
