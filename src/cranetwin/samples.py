"""The unit of sensor data that moves between the wire, the database and the twin.

A :class:`SampleBlock` is what one datagram carries once decoded: a run of regularly spaced
samples of one machine. ``protocol`` decodes datagrams into blocks, ``ingest`` hands them to
``storage``, and ``storage`` returns :class:`SampleArrays` for a time range to ``twin``.
Only numpy here, so every layer may import it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


@dataclass(frozen=True)
class SampleBlock:
    """A run of samples of one machine, as sent in one datagram.

    Attributes:
        machine_id: Machine identifier (as registered in storage).
        seq: Datagram sequence number, unique and increasing within the sender's epoch;
            storage writes are idempotent on (machine_id, epoch, seq).
        t0_ns: Timestamp of the first sample [ns since the Unix epoch, machine clock].
        period_ns: Sample period [ns] (10_000_000 at 100 Hz).
        channels: Channel names, in column order (names from the machine description).
        resolution: Quantisation step per channel, in the channel's unit.
        values: Samples, shape (n, len(channels)) [channel units]; NaN = missing (dropout,
            or optional channel not sent). Values are multiples of ``resolution``.
        epoch: The sender's epoch (boot id, 1 … 2**63 − 1; 0 for protocol version 1): a
            sender that lost its durable log starts a new epoch, so its sequence numbers never
            collide with an earlier run's.
        steps: The integer steps the wire carried, shape (n, len(channels)), 0 where ``values``
            is NaN, with ``values == steps · resolution`` elsewhere; or None (then storage
            quantises ``values``). The protocol decoder sets it, and storage stores it as it
            is: no float round trip, no second quantisation.
    """

    machine_id: str
    seq: int
    t0_ns: int
    period_ns: int
    channels: tuple[str, ...]
    resolution: tuple[float, ...]
    values: F64
    epoch: int = 0
    steps: I64 | None = None

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.values.shape[0])

    @property
    def t_end_ns(self) -> int:
        """Timestamp of the last sample [ns]."""
        return self.t0_ns + (self.n - 1) * self.period_ns

    def times_ns(self) -> I64:
        """Sample timestamps, shape (n,) [ns]."""
        return self.t0_ns + np.arange(self.n, dtype=np.int64) * self.period_ns


@dataclass(frozen=True)
class SampleArrays:
    """Samples of one machine over a time range, as the twin consumes them.

    Attributes:
        machine_id: Machine identifier.
        t_s: Sample times, shape (n,) [s since the Unix epoch], strictly increasing.
        channels: Channel names, in column order.
        values: Shape (n, len(channels)) [channel units]; NaN = missing.
        period_ns: The sample period the source carried [ns] (the wire's and storage's
            ``period_ns``), or None where the source has none (a file of bare timestamps) or
            where it changes inside the range (storage: blocks of different periods): readers
            take the period from here and estimate it from ``t_s`` only when None.
        t_ns: Exact sample times, shape (n,) [ns since the Unix epoch], where the source has
            them (storage: ``t0_ns + k · period_ns`` of each stored run), else None; ``t_s`` is
            ``t_ns / 1e9``.
    """

    machine_id: str
    t_s: F64
    channels: tuple[str, ...]
    values: F64
    period_ns: int | None = None
    t_ns: I64 | None = None

    def column(self, name: str) -> F64:
        """One channel's samples, shape (n,)."""
        return self.values[:, self.channels.index(name)]

    def take(self, rows: slice | npt.NDArray[np.bool_] | npt.NDArray[np.intp]) -> SampleArrays:
        """The samples at ``rows`` (a slice, a boolean mask of shape (n,) or indices), with the
        carried period and exact times kept."""
        return SampleArrays(self.machine_id, self.t_s[rows], self.channels, self.values[rows],
                            self.period_ns, None if self.t_ns is None else self.t_ns[rows])
