"""Machine-side sender: the asyncio/socket shell around :class:`cranetwin.protocol.Sender`.

The protocol core decides what to send and when; this module owns the UDP socket, the clock, the
spill file and the sample sources:

* :class:`FileSpill`: the on-disk FIFO where datagrams wait while the link is down for long.
* Sample sources (pluggable, :class:`SampleSource`): :class:`SyntheticSource` (smooth motion +
  sensor noise, stateless, no simulator needed) and :class:`RecordingSource` (a simulator
  :class:`~cranetwin.sim.Recording`, replayed cyclically; :func:`simulator_source` runs the
  simulator for a scenario).
* :func:`run_sender` streams one machine in real time (or ``speed`` × real time);
  :func:`run_fleet` runs many over one event loop.

Keys are never logged: :class:`~cranetwin.protocol.MachineKey` hides its secret in ``repr``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.errors import ProtocolError
from cranetwin.protocol import DatagramError, MachineKey, Sender, StatusReport

log = logging.getLogger(__name__)
F64 = npt.NDArray[np.float64]
_LEN = struct.Struct(">I")
_OFF = struct.Struct(">Q")


class SenderError(ProtocolError):
    """The sender could not start (bad address, unusable spill file, bad key)."""


# --- spill file --------------------------------------------------------------------------------
class FileSpill:
    """FIFO of datagrams in a file: ``u64 read offset`` then records ``u32 length ‖ datagram``.

    Appends go to the end; :meth:`popleft` reads at the stored offset and advances it; when the
    reader reaches the end the file is truncated to its header. Reopening a file continues where
    it stopped, so datagrams spilled before a restart of the sender are still sent (their
    sequence numbers stay valid). Writes are flushed to the OS on every call (survive a crash of
    the process); ``fsync=True`` also survives power loss at the cost of a disk sync per call.

    Args:
        path: File to use (created if missing).
        fsync: Sync to disk after every change.
    """

    def __init__(self, path: str | os.PathLike[str], fsync: bool = False) -> None:
        self.path = Path(path)
        self.fsync = fsync
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            exists = self.path.exists() and self.path.stat().st_size >= _OFF.size
            self._f = open(self.path, "r+b" if exists else "w+b")  # noqa: SIM115
        except OSError as exc:
            raise SenderError(f"cannot open spill file {self.path}: {exc}") from exc
        if exists:
            self._read = _OFF.unpack(self._f.read(_OFF.size))[0]
            self._count = self._scan()
        else:
            self._read = _OFF.size
            self._f.write(_OFF.pack(self._read))
            self._count = 0
            self._sync()

    def _scan(self) -> int:
        """Count complete records from the read offset; cut a torn last record."""
        size = os.fstat(self._f.fileno()).st_size
        pos, n = self._read, 0
        while pos + _LEN.size <= size:
            self._f.seek(pos)
            length = _LEN.unpack(self._f.read(_LEN.size))[0]
            if pos + _LEN.size + length > size:
                break
            pos += _LEN.size + length
            n += 1
        if pos < size:
            self._f.truncate(pos)
        return n

    def _sync(self) -> None:
        self._f.flush()
        if self.fsync:
            os.fsync(self._f.fileno())

    def append(self, datagram: bytes) -> None:
        """Store ``datagram`` after all others."""
        self._f.seek(0, os.SEEK_END)
        self._f.write(_LEN.pack(len(datagram)) + datagram)
        self._count += 1
        self._sync()

    def popleft(self) -> bytes:
        """Remove and return the oldest datagram.

        Raises:
            IndexError: the spill is empty.
        """
        if not self._count:
            raise IndexError("spill file is empty")
        self._f.seek(self._read)
        length = _LEN.unpack(self._f.read(_LEN.size))[0]
        dg = self._f.read(length)
        self._count -= 1
        self._read += _LEN.size + length
        if not self._count:
            self._f.truncate(_OFF.size)
            self._read = _OFF.size
        self._f.seek(0)
        self._f.write(_OFF.pack(self._read))
        self._sync()
        return dg

    def __len__(self) -> int:
        return self._count

    def close(self) -> None:
        """Close the file (the content stays for the next run)."""
        self._f.close()


# --- sample sources ----------------------------------------------------------------------------
class SampleSource(Protocol):
    """Rows of sensor samples by index; column order = the machine's layout."""

    def read(self, i0: int, m: int) -> F64:
        """Samples i0 … i0 + m − 1, shape (m, c) [channel units]; NaN = missing."""


class SyntheticSource:
    """Smooth crane-like motion plus sensor noise, for senders without the simulator.

    Each channel is a sum of three slow sinusoids (periods 6–40 s) inside 10–90 % of its range,
    plus Gaussian noise of ``noise_quanta`` resolution steps, quantised to the resolution; each
    sample is missing with probability ``dropout``. Stateless: :meth:`read` of the same rows gives
    the same values.

    Args:
        key: Machine key (layout: ranges and resolutions).
        period_s: Sample period [s].
        seed: Varies phases and noise between machines.
        noise_quanta: Noise standard deviation [resolution steps].
        dropout: Probability of a missing sample.
    """

    def __init__(self, key: MachineKey, period_s: float = 0.01, seed: int = 0,
                 noise_quanta: float = 2.0, dropout: float = 1e-3) -> None:
        self.layout = key.layout
        self.period_s = period_s
        self.seed = seed
        self.noise_quanta = noise_quanta
        self.dropout = dropout
        rng = np.random.default_rng(seed)
        c = len(self.layout.channels)
        self._periods = rng.uniform(6.0, 40.0, (3, c))
        self._phases = rng.uniform(0, 2 * np.pi, (3, c))

    def read(self, i0: int, m: int) -> F64:
        lo = np.array([ch.min for ch in self.layout.channels])
        hi = np.array([ch.max for ch in self.layout.channels])
        res = np.asarray(self.layout.resolutions)
        t = (i0 + np.arange(m))[:, None] * self.period_s
        wave = np.zeros((m, lo.size))
        for h in range(3):
            wave += np.sin(2 * np.pi * t / self._periods[h] + self._phases[h]) / 3
        x = (lo + hi) / 2 + (hi - lo) * 0.4 * wave
        noise, lost = self._random(i0, m, lo.size)
        x = x + noise * self.noise_quanta * res
        v: F64 = np.clip(np.round(x / res), np.ceil(lo / res), np.floor(hi / res)) * res
        v[lost < self.dropout] = np.nan
        return v

    def _random(self, i0: int, m: int, c: int) -> tuple[F64, F64]:
        """Standard normal noise and uniforms for rows i0 … i0 + m − 1, the same whatever the
        chunking (drawn per block of 1024 rows from a generator seeded by (seed, block))."""
        b0, b1 = i0 // 1024, (i0 + m - 1) // 1024 + 1
        parts = []
        for b in range(b0, b1):
            rng = np.random.default_rng([self.seed, b])
            parts.append(np.concatenate([rng.standard_normal((1024, c)),
                                         rng.random((1024, c))], axis=1))
        block = np.concatenate(parts)[i0 - b0 * 1024:i0 - b0 * 1024 + m]
        return block[:, :c], block[:, c:]


class RecordingSource:
    """A recorded stream (e.g. simulator output) replayed cyclically from ``offset``.

    Args:
        values: Samples, shape (n, c), layout column order [channel units].
        offset: Row to start from (shifts machines of a fleet against each other).
    """

    def __init__(self, values: F64, offset: int = 0) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] < 1:
            raise SenderError("a recording source needs at least one row of samples")
        self.values = values
        self.offset = offset

    def read(self, i0: int, m: int) -> F64:
        idx = (self.offset + i0 + np.arange(m)) % self.values.shape[0]
        out: F64 = self.values[idx]
        return out


def simulator_source(key: MachineKey, model: Any, scenario: str, *, duration_s: float = 120.0,
                     seed: int = 0) -> tuple[F64, float]:
    """Simulate ``scenario`` on ``model`` (``cranetwin.sim``) and return its samples in the key's
    layout order and the sample period [s].

    Raises:
        SenderError: the simulator is not available or a channel of the layout is not simulated.
    """
    try:
        from cranetwin.sim import builtin_scenario, load_scenario, simulate
    except ImportError as exc:  # pragma: no cover - the simulator ships with cranetwin
        raise SenderError(f"the simulator is not available: {exc}") from exc
    from cranetwin.sim import BUILTIN

    sc = (builtin_scenario(scenario, seed=seed, duration_s=duration_s) if scenario in BUILTIN
          else load_scenario(scenario))
    rec = simulate(model, sc, duration_s=min(duration_s, sc.duration_s), seed=seed,
                   wrenches=False)
    s = rec.samples
    try:
        cols = [s.channels.index(n) for n in key.layout.names]
    except ValueError as exc:
        raise SenderError(f"simulated channels {s.channels} lack one of {key.layout.names}") \
            from exc
    period = float(np.median(np.diff(s.t_s))) if s.t_s.size > 1 else 0.01
    return np.ascontiguousarray(s.values[:, cols]), period


# --- the asyncio shell -------------------------------------------------------------------------
@dataclass
class SenderStats:
    """What one machine's sender did.

    Attributes:
        machine_id: Machine identifier.
        samples: Samples pushed into the protocol.
        acked_samples: Samples acknowledged by the server (durable).
        datagrams: Datagrams sent (including retransmissions).
        retransmissions: Retransmitted datagrams.
        bytes_sent: UDP payload bytes sent.
        bad_acks: Ack datagrams rejected (forged, corrupted, foreign).
        unacked: Datagrams still unacknowledged at the end (0 after a full drain).
        max_spilled: Largest number of datagrams waiting in the spill at once.
    """

    machine_id: str
    samples: int = 0
    acked_samples: int = 0
    datagrams: int = 0
    retransmissions: int = 0
    bytes_sent: int = 0
    bad_acks: int = 0
    unacked: int = 0
    max_spilled: int = 0

    @property
    def bytes_per_sample(self) -> float:
        """UDP payload bytes sent per sample (retransmissions included)."""
        return self.bytes_sent / self.samples if self.samples else math.nan


class _AckProtocol(asyncio.DatagramProtocol):
    def __init__(self, on_ack: Callable[[bytes], None]) -> None:
        self.on_ack = on_ack
        self.wake = asyncio.Event()

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.on_ack(data)
        self.wake.set()

    def error_received(self, exc: Exception) -> None:  # ICMP port unreachable: server down
        log.debug("send error (server unreachable?): %s", exc)


def parse_host(host: str) -> tuple[str, int]:
    """``HOST:PORT`` → (host, port); IPv6 as ``[::1]:5005``.

    Raises:
        SenderError: not HOST:PORT.
    """
    h, sep, p = host.rpartition(":")
    if not sep or not p.isdigit() or not h or not 0 < int(p) < 65536:
        raise SenderError(f"--host must be HOST:PORT (e.g. 127.0.0.1:5005), got {host!r}")
    return h.strip("[]"), int(p)


async def run_sender(key: MachineKey, server: tuple[str, int], source: SampleSource, *,
                     period_ns: int = 10_000_000, speed: float = 1.0,
                     duration_s: float | None = None, batch_samples: int = 50,
                     spill_path: str | os.PathLike[str] | None = None, max_unacked: int = 512,
                     first_seq: int | None = None, status_every_s: float = 60.0,
                     position_deg: tuple[float, float] = (61.0, 25.0),
                     stop: asyncio.Event | None = None, drain_timeout_s: float = 30.0,
                     rto_s: float = 1.0, tick_s: float = 0.05,
                     clock_ns: Callable[[], int] = time.time_ns) -> SenderStats:
    """Stream ``source`` as one machine to ``server`` until ``duration_s`` or ``stop``, then drain.

    Args:
        key: Machine identity, secret and layout.
        server: (host, port) of the ingest daemon.
        source: Where samples come from (layout column order).
        period_ns: Sample period [ns].
        speed: Samples produced per wall-clock second, × 1/period (2 = twice real time).
        duration_s: Data time to stream [s] (None: until ``stop`` is set).
        batch_samples: Samples per data datagram.
        spill_path: Spill file (default: an in-memory spill, unbounded).
        max_unacked: Datagrams kept in memory.
        first_seq: First sequence number (default: Unix time in ms, ahead of any earlier run).
        status_every_s: Status datagram interval [s of data time]; 0 = none. A status carries
            GPS, the operating-hours counter and the latest values of the layout's optional
            channels (declared ``optional`` in the machine description).
        position_deg: GPS latitude, longitude reported in status [deg].
        stop: Set to stop streaming (then the sender drains).
        drain_timeout_s: How long to wait for the last acks after streaming ends [s].
        rto_s: Initial retransmission timeout [s].
        tick_s: Wall-clock interval between pushes [s].
        clock_ns: Wall clock [ns since the Unix epoch] (injectable for tests).

    Returns:
        Counters; ``unacked`` is 0 when everything sent was acknowledged.
    """
    loop = asyncio.get_running_loop()
    stop = stop or asyncio.Event()
    spill = FileSpill(spill_path) if spill_path is not None else None
    seq0 = first_seq if first_seq is not None else clock_ns() // 1_000_000
    core = Sender(key, period_ns, first_seq=seq0, batch_samples=batch_samples,
                  max_unacked=max_unacked, spill=spill, rto_ns=int(rto_s * 1e9),
                  max_rto_ns=max(int(rto_s * 1e9), 30_000_000_000))
    stats = SenderStats(key.machine_id)

    def on_ack(data: bytes) -> None:
        try:
            core.receive(data, clock_ns())
        except DatagramError as err:
            stats.bad_acks += 1
            log.debug("%s: ack dropped (%s)", key.machine_id, err.reason)

    try:
        transport, proto = await loop.create_datagram_endpoint(
            lambda: _AckProtocol(on_ack), remote_addr=server)
    except OSError as exc:
        raise SenderError(f"cannot open a UDP socket to {server[0]}:{server[1]}: {exc}") from exc
    start_wall = clock_ns()
    t0 = start_wall
    n_total = None if duration_s is None else int(round(duration_s * 1e9 / period_ns))
    pushed = 0
    next_status = 0.0
    hours0 = 1000.0 + (key.wire_id % 997)
    log.info("%s: streaming to %s:%d (wire id %d, seq from %d)", key.machine_id, server[0],
             server[1], key.wire_id, seq0)

    def send_due(now: int) -> None:
        for dg in core.datagrams_to_send(now):
            transport.sendto(dg)
        stats.max_spilled = max(stats.max_spilled, core.spilled)

    try:
        while not stop.is_set() and (n_total is None or pushed < n_total):
            now = clock_ns()
            due = int((now - start_wall) * speed / period_ns) + 1
            if n_total is not None:
                due = min(due, n_total)
            if due > pushed:
                core.push(t0 + pushed * period_ns, source.read(pushed, due - pushed))
                stats.samples += due - pushed
                pushed = due
            data_s = pushed * period_ns / 1e9
            if status_every_s > 0 and data_s >= next_status and pushed:
                next_status += status_every_s
                last = source.read(pushed - 1, 1)[0]
                low_rate = {c.name: float(last[j]) for j, c in enumerate(key.layout.channels)
                            if c.optional and not math.isnan(last[j])}
                core.push_status(StatusReport(
                    key.machine_id, 0, t0 + (pushed - 1) * period_ns, position_deg[0],
                    position_deg[1], 120.0, hours0 + data_s / 3600.0, low_rate))
            send_due(now)
            proto.wake.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(_wait_any(stop, proto.wake), tick_s)
        core.flush()
        deadline = clock_ns() + int(drain_timeout_s * 1e9)
        while not core.idle and clock_ns() < deadline:
            now = clock_ns()
            send_due(now)
            nxt = core.next_timer_ns()
            wait = 0.05 if nxt is None else min(max((nxt - now) / 1e9, 0.001), 0.25)
            proto.wake.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(proto.wake.wait(), wait)
    finally:
        transport.close()
        if spill is not None:
            spill.close()
    stats.acked_samples = core.acked_samples
    stats.datagrams = core.sent_datagrams
    stats.retransmissions = core.retransmissions
    stats.bytes_sent = core.sent_bytes
    stats.unacked = core.in_memory + core.spilled
    log.info("%s: %d samples, %d acked, %d datagrams (%d retransmitted), %.2f bytes/sample, "
             "%d unacked", key.machine_id, stats.samples, stats.acked_samples, stats.datagrams,
             stats.retransmissions, stats.bytes_per_sample, stats.unacked)
    return stats


async def _wait_any(a: asyncio.Event, b: asyncio.Event) -> None:
    tasks = [asyncio.ensure_future(a.wait()), asyncio.ensure_future(b.wait())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()


async def run_fleet(keys: Sequence[MachineKey], server: tuple[str, int],
                    sources: Sequence[SampleSource], **kwargs: Any) -> list[SenderStats]:
    """:func:`run_sender` for several machines at once (one socket each, one event loop).

    ``spill_path`` in ``kwargs``, if given, is a directory: machine ``m`` spills to
    ``<dir>/<m>.spill``.
    """
    spill_dir = kwargs.pop("spill_path", None)
    jobs = []
    for key, src in zip(keys, sources, strict=True):
        sp = None if spill_dir is None else Path(spill_dir) / f"{key.machine_id}.spill"
        jobs.append(run_sender(key, server, src, spill_path=sp, **kwargs))
    return list(await asyncio.gather(*jobs))
