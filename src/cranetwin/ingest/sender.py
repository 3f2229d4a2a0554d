"""Machine-side sender: the asyncio/socket shell around :class:`cranetwin.protocol.Sender`.

The protocol core decides what to send and when; this module owns the UDP socket, the clock, the
journal and the sample sources:

* The journal (:class:`~cranetwin.ingest.journal.FileJournal`): every datagram is on disk, synced,
  before it is sent, and stays there until the server acknowledges (or refuses) it. A sender
  killed at any moment loses nothing it sent; the next start with the same journal directory
  sends what was not acknowledged first, with the same epoch and the following sequence numbers.
* Sample sources (pluggable, :class:`SampleSource`): :class:`SyntheticSource` (smooth motion +
  sensor noise, stateless, no simulator needed) and :class:`RecordingSource` (a simulator
  :class:`~cranetwin.sim.Recording`, replayed cyclically; :func:`simulator_source` runs the
  simulator for a scenario). Row ``r`` of a source is the sample taken at ``r × period`` since
  the Unix epoch, so what a sender produced can be recomputed from the stored timestamps.
* :func:`run_sender` streams one machine in real time (or ``speed`` × real time);
  :func:`run_fleet` runs many over one event loop.

Keys are never logged: :class:`~cranetwin.protocol.MachineKey` hides its secret in ``repr``.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.ingest.journal import FileJournal, SenderError
from cranetwin.protocol import (
    TYPE_DATA,
    TYPE_STATUS,
    DatagramError,
    Journal,
    MachineKey,
    Sender,
    StatusReport,
    decode_data,
    decode_status,
    peek_header,
)
from cranetwin.samples import SampleArrays

log = logging.getLogger(__name__)
F64 = npt.NDArray[np.float64]

__all__ = [
    "FileRecording", "RecordingSource", "SampleSource", "SenderError", "SenderStats",
    "SyntheticSource", "SimulatorStream", "file_source", "journal_owner", "parse_host",
    "resume_row", "run_fleet", "run_sender", "simulator_source", "simulator_stream",
]


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
        anchored: Count rows from the first row read instead of the sender's absolute sample
            clock, so the first sample sent is row ``offset`` (a user's file starts with its
            first row).
    """

    def __init__(self, values: F64, offset: int = 0, anchored: bool = False) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] < 1:
            raise SenderError("a recording source needs at least one row of samples")
        self.values = values
        self.offset = offset
        self.anchored = anchored
        self._first: int | None = None

    def read(self, i0: int, m: int) -> F64:
        if self.anchored:
            if self._first is None:
                self._first = i0
            i0 -= self._first
        idx = (self.offset + i0 + np.arange(m)) % self.values.shape[0]
        out: F64 = self.values[idx]
        return out


class SimulatorStream:
    """A simulator :class:`~cranetwin.sim.Session` advanced as rows are read: continuous,
    physically possible motion for as long as the scenario lasts (its commands hold their last
    values afterwards), never a jump back to the start as a replayed loop makes.

    The first row read is the session's t = 0; later reads must not go back further than the
    ``keep`` newest rows (the sender re-reads only its last row, for status datagrams). A read
    ahead of what was produced simulates through the gap.

    Args:
        session: The simulation (its sample period is ``period_s``).
        columns: Column of each layout channel in the session's samples.
        period_s: Sample period of the session's sensors [s].
        keep: Rows kept for re-reading.
    """

    def __init__(self, session: Any, columns: Sequence[int], period_s: float = 0.01,
                 keep: int = 1024) -> None:
        self.session = session
        self.columns = list(columns)
        self.period_s = period_s
        self.keep = max(1, keep)
        self._row0: int | None = None  # absolute row of self._buf[0]
        self._buf: F64 = np.zeros((0, len(self.columns)))

    def read(self, i0: int, m: int) -> F64:
        if self._row0 is None:
            self._row0 = i0
        if i0 < self._row0:
            raise SenderError(f"row {i0} is older than the {self.keep} rows kept by the "
                              "simulator stream")
        end = i0 + m
        parts = [self._buf]
        have = self._row0 + self._buf.shape[0]
        while have < end:
            # at least 0.1 s per call: the compiled loop's overhead stays small
            n = max(end - have, int(round(0.1 / self.period_s)))
            got = self.session.advance(n * self.period_s).values[:, self.columns]
            parts.append(got)
            have += got.shape[0]
        buf = np.concatenate(parts) if len(parts) > 1 else self._buf
        out: F64 = buf[i0 - self._row0:end - self._row0].copy()
        drop = max(0, buf.shape[0] - self.keep)
        self._buf = buf[drop:]
        self._row0 += drop
        return out


def simulator_stream(key: MachineKey, model: Any, scenario: str, *,
                     duration_s: float = 86400.0, seed: int = 0) -> tuple[SimulatorStream, float]:
    """A :class:`SimulatorStream` of ``scenario`` on ``model`` in the key's layout order, and its
    sample period [s]. A built-in scenario is made ``duration_s`` long; a file keeps its own
    length. ``model`` is a machine description or its :func:`cranetwin.sim.prepare` result
    (compiled once for a fleet of senders).

    Raises:
        SenderError: the simulator is not available or a channel of the layout is not simulated.
    """
    try:
        from cranetwin.sim import (
            BUILTIN,
            Prepared,
            SensorModel,
            Session,
            builtin_scenario,
            load_scenario,
            prepare,
        )
    except ImportError as exc:  # pragma: no cover - the simulator ships with cranetwin
        raise SenderError(f"the simulator is not available: {exc}") from exc

    prep = model if isinstance(model, Prepared) else prepare(model)
    # a built-in (crane) scenario, one shipped for this machine (machines/scenarios/<name>/),
    # or a file
    sc = (builtin_scenario(scenario, seed=seed, duration_s=duration_s) if scenario in BUILTIN
          else load_scenario(scenario, machine=prep.machine.name))
    sensors = SensorModel()
    session = Session(prep, sc, sensors=sensors, seed=seed, keep_truth=False)
    try:
        cols = [session.channels.index(n) for n in key.layout.names]
    except ValueError as exc:
        raise SenderError(f"simulated channels {session.channels} lack one of "
                          f"{key.layout.names}") from exc
    period = 1.0 / sensors.rate_hz
    return SimulatorStream(session, cols, period), period


def simulator_source(key: MachineKey, model: Any, scenario: str, *, duration_s: float = 120.0,
                     seed: int = 0) -> tuple[F64, float]:
    """Simulate ``scenario`` on ``model`` (``cranetwin.sim``) and return its samples in the key's
    layout order and the sample period [s]. ``scenario`` is a built-in name, the name of a
    scenario shipped for the machine (``load_scenario(..., machine=model.name)``) or a file.

    Raises:
        SenderError: the simulator is not available or a channel of the layout is not simulated.
    """
    try:
        from cranetwin.sim import builtin_scenario, load_scenario, simulate
    except ImportError as exc:  # pragma: no cover - the simulator ships with cranetwin
        raise SenderError(f"the simulator is not available: {exc}") from exc
    from cranetwin.sim import BUILTIN

    # a built-in (crane) scenario, one shipped for this machine (machines/scenarios/<name>/),
    # or a file
    sc = (builtin_scenario(scenario, seed=seed, duration_s=duration_s) if scenario in BUILTIN
          else load_scenario(scenario, machine=getattr(model, "name", None)))
    rec = simulate(model, sc, duration_s=min(duration_s, sc.duration_s), seed=seed,
                   wrenches=False)
    return _in_layout(rec.samples, key, "simulated")


def _in_layout(s: SampleArrays, key: MachineKey, what: str) -> tuple[F64, float]:
    """``s``'s values in the key's layout order, shape (n, c), and its median period [s]."""
    try:
        cols = [s.channels.index(n) for n in key.layout.names]
    except ValueError as exc:
        raise SenderError(f"{what} channels {s.channels} lack one of {key.layout.names}") \
            from exc
    period = float(np.median(np.diff(s.t_s))) if s.t_s.size > 1 else 0.01
    return np.ascontiguousarray(s.values[:, cols]), period


@dataclass(frozen=True)
class FileRecording:
    """A user's recording read for sending (:func:`file_source`).

    Attributes:
        values: Samples in the key's layout order, shape (n, c) [channel units]; NaN = missing.
        period_s: The recording's median sample period [s], the sender's period.
        gaps: Number of places where the recording's time jumps by more than 1.5 periods.
        gap_s: Recording time those jumps skip in all [s] (the sender's clock does not skip it:
            the live time base is the sender's, rows are sent back to back).
        payload_column: The mapping's payload column, if any (not sent: the wire carries
            sensor channels only; ``cranetwin import`` stores it).
    """

    values: F64
    period_s: float
    gaps: int
    gap_s: float
    payload_column: str | None


def file_source(key: MachineKey, samples: SampleArrays, name: str,
                payload_column: str | None = None) -> FileRecording:
    """A user's recording, already read and converted (``cranetwin send --file`` reads it with
    :func:`cranetwin.importer.read_file`, the same checks as ``cranetwin import``), as rows to
    send.

    Args:
        key: The machine key whose layout orders the channels.
        samples: The recording, times shape (n,) [s], values shape (n, c) [channel units].
        name: The file's name, for messages.
        payload_column: The mapping's payload column, if any (reported as not sent).

    Raises:
        SenderError: A layout channel the recording does not have.
    """
    values, period = _in_layout(samples, key, f"{name}'s")
    dt = np.diff(samples.t_s)
    jumps = dt > 1.5 * period
    return FileRecording(values, period, int(jumps.sum()), float((dt[jumps] - period).sum()),
                         payload_column)


# --- the asyncio shell -------------------------------------------------------------------------
@dataclass
class SenderStats:
    """What one machine's sender did (this run).

    Attributes:
        machine_id: Machine identifier.
        epoch: Sender epoch (the journal's).
        journal: Journal directory ("" for an in-memory journal).
        resumed: Datagrams left unacknowledged by an earlier run, sent first by this one.
        samples: Samples pushed into the protocol by this run.
        acked_samples: Samples acknowledged by the server (durable), earlier runs' included.
        datagrams: Datagrams sent (including retransmissions).
        retransmissions: Retransmitted datagrams.
        timeouts: Retransmission timer expiries (each resends only the oldest datagram).
        bytes_sent: UDP payload bytes sent.
        bad_acks: Server datagrams rejected (forged, corrupted, foreign).
        refused: Datagrams the server refused for good (refusals received for a datagram still
            pending); each one is kept in the journal's ``rejected.log``.
        refused_samples: Samples in those datagrams.
        fsyncs: Disk syncs of the journal (one per batch of new datagrams, plus segment rolls,
            watermark writes and refusals).
        unacked: Datagrams still unacknowledged at the end, kept in the journal for the next
            start (0 after a full drain).
        max_spilled: Largest number of datagrams waiting in the journal, not in memory.
    """

    machine_id: str
    epoch: int = 0
    journal: str = ""
    resumed: int = 0
    samples: int = 0
    acked_samples: int = 0
    datagrams: int = 0
    retransmissions: int = 0
    timeouts: int = 0
    bytes_sent: int = 0
    bad_acks: int = 0
    refused: int = 0
    refused_samples: int = 0
    fsyncs: int = 0
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


def journal_owner(key: MachineKey) -> str:
    """The identity a journal is bound to: machine id, wire id and a fingerprint of the secret
    (HMAC of a fixed text: the secret cannot be recovered from it). A journal written under
    another key holds datagrams the server would never accept."""
    fp = hmac.new(key.secret, b"cranetwin send journal owner", hashlib.sha256).hexdigest()[:16]
    return f"{key.machine_id} wire {key.wire_id} key {fp}"


async def run_sender(key: MachineKey, server: tuple[str, int], source: SampleSource | None, *,
                     journal_dir: str | os.PathLike[str] | None = None,
                     journal: Journal | None = None, fsync: bool = True,
                     period_ns: int = 10_000_000, speed: float = 1.0,
                     duration_s: float | None = None, batch_samples: int = 50,
                     max_unacked: int = 512, status_every_s: float = 60.0,
                     position_deg: tuple[float, float] = (61.0, 25.0),
                     stop: asyncio.Event | None = None, drain_timeout_s: float = 30.0,
                     min_rto_s: float = 1.0, max_rto_s: float = 10.0, tick_s: float = 0.05,
                     clock_ns: Callable[[], int] = time.time_ns) -> SenderStats:
    """Stream ``source`` as one machine to ``server`` until ``duration_s`` or ``stop``.

    The datagrams left unacknowledged in the journal by an earlier run go out first. When
    streaming ends (``duration_s`` reached, or ``source`` None: nothing new is produced) the
    sender waits up to ``drain_timeout_s`` for the last acks; when ``stop`` is set (SIGINT,
    SIGTERM) it stops at once. Either way the batch in progress is journaled and synced, and
    whatever is not acknowledged stays in the journal (``unacked``) for the next start: nothing
    is ever discarded.

    Args:
        key: Machine identity, secret and layout.
        server: (host, port) of the ingest daemon.
        source: Where samples come from (layout column order); row ``r`` is sent with time
            ``r × period_ns`` [ns since the Unix epoch]. None: only send what the journal holds.
        journal_dir: Directory of the durable journal (:class:`FileJournal`, created if
            missing; bound to this key, see :func:`journal_owner`).
        journal: A journal to use instead (e.g. :class:`cranetwin.protocol.MemoryJournal` in
            tests; the caller closes it). One of ``journal_dir`` and ``journal`` is required.
        fsync: Sync the journal to disk (False only for tests: survives a crash of the process,
            not of the machine).
        period_ns: Sample period [ns].
        speed: Samples produced per wall-clock second, × 1/period (2 = twice real time).
        duration_s: Data time to stream [s] (None: until ``stop`` is set).
        batch_samples: Samples per data datagram.
        max_unacked: Datagrams held in memory; the rest wait in the journal.
        status_every_s: Status datagram interval [s of data time]; 0 = none. A status carries
            GPS, the operating-hours counter and the latest values of the layout's optional
            channels (declared ``optional`` in the machine description).
        position_deg: GPS latitude, longitude reported in status [deg].
        stop: Set to stop streaming and return (after a journal sync, without waiting for acks).
        drain_timeout_s: How long to wait for the last acks after streaming ended [s].
        min_rto_s: Lower bound and initial value of the retransmission timeout [s].
        max_rto_s: Upper bound of the backed-off retransmission timeout [s].
        tick_s: Wall-clock interval between pushes [s].
        clock_ns: Wall clock [ns since the Unix epoch] (injectable for tests).

    Returns:
        Counters; ``unacked`` is 0 when everything was acknowledged.

    Raises:
        SenderError: no journal, the journal cannot be opened or synced, or no UDP socket.
    """
    loop = asyncio.get_running_loop()
    stop = stop or asyncio.Event()
    owned: FileJournal | None = None
    if journal is not None:
        jr: Journal = journal
    elif journal_dir is not None:
        jr = owned = FileJournal(journal_dir, fsync=fsync, owner=journal_owner(key))
    else:
        raise SenderError("run_sender needs a journal directory (journal_dir) or a journal")
    stats = SenderStats(key.machine_id, epoch=jr.epoch,
                        journal="" if journal_dir is None else str(journal_dir))
    fs0 = _fsyncs(jr)
    try:
        await _stream(key, server, source, jr, stats, loop, stop, period_ns=period_ns,
                      speed=speed, duration_s=duration_s, batch_samples=batch_samples,
                      max_unacked=max_unacked, status_every_s=status_every_s,
                      position_deg=position_deg, drain_timeout_s=drain_timeout_s,
                      min_rto_s=min_rto_s, max_rto_s=max_rto_s, tick_s=tick_s,
                      clock_ns=clock_ns)
    except BaseException:
        if owned is not None:
            with contextlib.suppress(SenderError):
                owned.close()
        raise
    if owned is not None:
        owned.close()
    stats.fsyncs = _fsyncs(jr) - fs0
    log.info("%s: %d samples, %d acked, %d datagrams (%d retransmitted), %.2f bytes/sample, "
             "%d refused, %d fsyncs, %d unacked (kept in the journal)", key.machine_id,
             stats.samples, stats.acked_samples, stats.datagrams, stats.retransmissions,
             stats.bytes_per_sample, stats.refused, stats.fsyncs, stats.unacked)
    return stats


def resume_row(journal: Journal, key: MachineKey, period_ns: int) -> int | None:
    """The row after the newest sample time in ``journal`` (data or status datagram), or None.

    A restarted sender continues its sample clock there when that is ahead of the wall clock
    (``speed`` > 1 runs ahead of real time), so a new run never produces samples for times an
    earlier run already journaled.
    """
    last = getattr(journal, "last", None)
    if callable(last):
        dg = last()
    else:
        dg = journal.read(journal.end - 1, 1)[0] if len(journal) else None
    if not isinstance(dg, bytes):
        return None
    try:
        kind = peek_header(dg).type
        if kind == TYPE_DATA:
            return decode_data(dg, key).t_end_ns // period_ns + 1
        if kind == TYPE_STATUS:
            return decode_status(dg, key).t_ns // period_ns + 1
    except DatagramError:
        log.warning("%s: the journal's newest datagram does not decode with this key",
                    key.machine_id)
    return None


def _fsyncs(j: Journal) -> int:
    return int(getattr(j, "fsyncs", getattr(j, "syncs", 0)))


async def _stream(key: MachineKey, server: tuple[str, int], source: SampleSource | None,
                  jr: Journal, stats: SenderStats, loop: asyncio.AbstractEventLoop,
                  stop: asyncio.Event, *, period_ns: int, speed: float, duration_s: float | None,
                  batch_samples: int, max_unacked: int, status_every_s: float,
                  position_deg: tuple[float, float], drain_timeout_s: float, min_rto_s: float,
                  max_rto_s: float, tick_s: float, clock_ns: Callable[[], int]) -> None:
    core = Sender(key, period_ns, journal=jr, batch_samples=batch_samples,
                  max_unacked=max_unacked, min_rto_ns=max(1, int(min_rto_s * 1e9)),
                  max_rto_ns=max(int(min_rto_s * 1e9), int(max_rto_s * 1e9), 1))
    stats.resumed = core.unacked
    failed: list[SenderError] = []

    def on_ack(data: bytes) -> None:
        try:
            core.receive(data, clock_ns())
        except DatagramError as err:
            stats.bad_acks += 1
            log.debug("%s: server datagram dropped (%s)", key.machine_id, err.reason)
        except SenderError as exc:  # the journal failed (disk): stop, raise below
            failed.append(exc)
            stop.set()

    try:
        transport, proto = await loop.create_datagram_endpoint(
            lambda: _AckProtocol(on_ack), remote_addr=server)
    except OSError as exc:
        raise SenderError(f"cannot open a UDP socket to {server[0]}:{server[1]}: {exc}") from exc
    log.info("%s: streaming to %s:%d (wire id %d, epoch %d, seq from %d, %d unacknowledged "
             "from an earlier run)", key.machine_id, server[0], server[1], key.wire_id,
             core.epoch, core.next_seq, stats.resumed)

    def send_due(now: int) -> None:
        while True:  # the core hands out at most max_burst at a time
            out = core.datagrams_to_send(now)
            for dg in out:
                transport.sendto(dg)
            stats.max_spilled = max(stats.max_spilled, core.spilled)
            if len(out) < core.max_burst:
                return

    def wait_s(now: int, cap: float) -> float:
        nxt = core.next_timer_ns()
        return cap if nxt is None else min(max((nxt - now) / 1e9, 0.001), cap)

    try:
        start_wall = clock_ns()
        row0 = -(-start_wall // period_ns)  # the first sample on the period grid after now
        after = resume_row(jr, key, period_ns)
        if after is not None and after > row0:  # an earlier run got ahead of the wall clock
            row0 = after
        n_total = None if duration_s is None else int(round(duration_s * 1e9 / period_ns))
        if source is None:
            n_total = 0
        pushed = 0
        next_status = 0.0
        hours0 = 1000.0 + (key.wire_id % 997)
        while not stop.is_set() and (n_total is None or pushed < n_total):
            assert source is not None
            now = clock_ns()
            due = int((now - start_wall) * speed / period_ns) + 1
            if n_total is not None:
                due = min(due, n_total)
            if due > pushed:
                core.push((row0 + pushed) * period_ns, source.read(row0 + pushed, due - pushed))
                stats.samples += due - pushed
                pushed = due
            data_s = pushed * period_ns / 1e9
            if status_every_s > 0 and data_s >= next_status and pushed:
                next_status += status_every_s
                last = source.read(row0 + pushed - 1, 1)[0]
                low_rate = {c.name: float(last[j]) for j, c in enumerate(key.layout.channels)
                            if c.optional and not math.isnan(last[j])}
                core.push_status(StatusReport(
                    key.machine_id, 0, (row0 + pushed - 1) * period_ns, position_deg[0],
                    position_deg[1], 120.0, hours0 + data_s / 3600.0, low_rate))
            send_due(now)
            proto.wake.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(_wait_any(stop, proto.wake), wait_s(now, tick_s))
        if failed:
            raise failed[0]
        core.flush()
        if stop.is_set():
            jr.sync()  # stopped by a signal: the last batch is journaled, no waiting for acks
        else:
            deadline = clock_ns() + int(drain_timeout_s * 1e9)
            while not core.idle and clock_ns() < deadline and not stop.is_set():
                now = clock_ns()
                send_due(now)
                proto.wake.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(_wait_any(stop, proto.wake), wait_s(now, 0.25))
            if failed:
                raise failed[0]
            jr.sync()
    finally:
        transport.close()
        stats.acked_samples = core.acked_samples
        stats.datagrams = core.sent_datagrams
        stats.retransmissions = core.retransmissions
        stats.timeouts = core.timeouts
        stats.bytes_sent = core.sent_bytes
        stats.refused = core.refused
        stats.refused_samples = core.refused_samples
        stats.unacked = core.unacked


async def _wait_any(a: asyncio.Event, b: asyncio.Event) -> None:
    tasks = [asyncio.ensure_future(a.wait()), asyncio.ensure_future(b.wait())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()


async def run_fleet(keys: Sequence[MachineKey], server: tuple[str, int],
                    sources: Sequence[SampleSource | None], *,
                    journal_dir: str | os.PathLike[str] | None = None,
                    **kwargs: Any) -> list[SenderStats]:
    """:func:`run_sender` for several machines at once (one socket each, one event loop).

    ``journal_dir`` is a directory holding one journal per machine: ``<journal_dir>/<machine
    id>``. Without it each machine gets a :class:`~cranetwin.protocol.MemoryJournal` (tests).
    """
    from cranetwin.protocol import MemoryJournal

    jobs = []
    for key, src in zip(keys, sources, strict=True):
        if journal_dir is None:
            jobs.append(run_sender(key, server, src, journal=MemoryJournal(), **kwargs))
        else:
            jobs.append(run_sender(key, server, src, journal_dir=Path(journal_dir) /
                                   key.machine_id, **kwargs))
    return list(await asyncio.gather(*jobs))
