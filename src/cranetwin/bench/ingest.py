"""``cranetwin bench ingest``: sender processes and the daemon on loopback into a real database.

Each sender process drives the protocol's :class:`~cranetwin.protocol.Sender` for its share of
the simulated fleet over one UDP socket (blocking loop: send due datagrams, read acks,
retransmit on timeout), through an optional :class:`LossyLink` that drops, duplicates and
reorders datagrams in both directions. The daemon runs as ``cranetwin ingest`` in its own
process. Datagrams are encoded before the clock starts; ``samples_per_second`` is all samples
over the time from the first send until the last one is acknowledged (acks come only after
commit, so this is stored-and-durable throughput). After the run, everything is read back from
the database and compared exactly with what was sent (``lost``, ``duplicated``, ``mismatched``).

Baseline in the same run and database: a row per sample inserted with ``executemany`` (one row
of 11 values per sample), as an ingest without blocks would do.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import random
import select
import socket
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import typer

from cranetwin.bench import emit
from cranetwin.bench.ingest_daemon import DaemonProcess as DaemonProcess
from cranetwin.bench.ingest_daemon import cpu_seconds
from cranetwin.bench.ingest_daemon import free_udp_port as free_udp_port
from cranetwin.bench.ingest_daemon import start_daemon as start_daemon
from cranetwin.protocol import (
    DatagramError,
    Journal,
    Layout,
    MachineKey,
    MemoryJournal,
    Sender,
    datagram_seq,
    peek_header,
)

F64 = npt.NDArray[np.float64]
DAY_NS = 86_400 * 10**9
T0_NS = (time.time_ns() // DAY_NS - 1) * DAY_NS
"""Start of the bench's sample clock: midnight (UTC) before last, so that every sample is within
the daemon's accepted window around its clock (and the same in every process of one run)."""
PERIOD_NS = 10_000_000  # 100 Hz
_cpu_seconds = cpu_seconds  # the name bench.bus imports (now in bench.ingest_daemon)


# --- a lossy link (in-process shim) -------------------------------------------------------------
@dataclass
class LossyLink:
    """Drops, duplicates and reorders datagrams (apply it to each direction separately).

    Args:
        drop: Probability a datagram is lost.
        duplicate: Probability a datagram is delivered twice.
        reorder: Probability a datagram is held back and delivered after 1..``max_hold`` later
            calls (so it overtakes nothing and is overtaken by later ones).
        seed: Random seed.
    """

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    max_hold: int = 8
    seed: int = 0
    _held: list[tuple[int, bytes]] = field(default_factory=list)
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def transmit(self, datagrams: Sequence[bytes]) -> list[bytes]:
        """What reaches the other end now, given ``datagrams`` sent now."""
        out: list[bytes] = []
        held, self._held = self._held, []
        for n, dg in held:
            if n <= 1:
                out.append(dg)
            else:
                self._held.append((n - 1, dg))
        for dg in datagrams:
            if self._rng.random() < self.drop:
                self.dropped += 1
                continue
            copies = 2 if self._rng.random() < self.duplicate else 1
            self.duplicated += copies - 1
            for _ in range(copies):
                if self._rng.random() < self.reorder:
                    self.reordered += 1
                    self._held.append((self._rng.randint(1, self.max_hold), dg))
                else:
                    out.append(dg)
        return out

    def flush(self) -> list[bytes]:
        """Deliver everything held back."""
        out = [dg for _, dg in self._held]
        self._held = []
        return out


# --- the fleet driver -------------------------------------------------------------------------
class Fleet:
    """Several machines' senders over one UDP socket (blocking; one thread).

    Args:
        senders: One protocol Sender per machine (distinct wire ids).
        server: Daemon address (host, port).
        uplink, downlink: Optional lossy links for data and for acks.
    """

    def __init__(self, senders: Sequence[Sender], server: tuple[str, int],
                 uplink: LossyLink | None = None, downlink: LossyLink | None = None,
                 sources: dict[int, F64] | None = None, speed: float = 1.0) -> None:
        self.senders = {s.key.wire_id: s for s in senders}
        self.sources = sources or {}
        self.speed = speed
        self._pushed = dict.fromkeys(self.sources, 0)
        self._start: float | None = None
        self._due = dict.fromkeys(self.senders, 0)  # cached next_timer_ns (0 = look now)
        self.server = server
        self.uplink, self.downlink = uplink, downlink
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.bad_acks = 0
        self._sizes: dict[tuple[int, int], int] = {}

    @property
    def unique_bytes(self) -> int:
        """UDP payload bytes of distinct datagrams sent (retransmissions not counted)."""
        return sum(self._sizes.values())

    def _send(self, datagrams: list[bytes]) -> None:
        for dg in datagrams:
            try:
                self.sock.sendto(dg, self.server)
            except (BlockingIOError, ConnectionRefusedError):
                pass  # like a loss: retransmitted later

    def step(self, timeout_s: float = 0.01) -> None:
        """Push samples whose time has come, send what is due, read acks for ≤ ``timeout_s``."""
        self._feed()
        now = time.time_ns()
        out: list[bytes] = []
        for w, s in self.senders.items():
            if self._due[w] > now:
                continue
            due = s.datagrams_to_send(now)
            for dg in due:
                self._sizes[(w, datagram_seq(dg))] = len(dg)
            out.extend(due)
            nxt = s.next_timer_ns()
            self._due[w] = (now + 10**12) if nxt is None else nxt
        if self.uplink is not None:
            out = self.uplink.transmit(out)
        self._send(out)
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        acks: list[bytes] = []
        while ready:
            try:
                acks.append(self.sock.recv(2048))
            except (BlockingIOError, ConnectionRefusedError):
                break
        if self.downlink is not None:
            acks = self.downlink.transmit(acks)
        now = time.time_ns()
        for a in acks:
            try:
                w = peek_header(a).wire_id
                self.senders[w].receive(a, now)
                self._due[w] = 0  # acks free window space and may reset timers
            except (DatagramError, KeyError):
                self.bad_acks += 1

    def _feed(self) -> None:
        """Real-time sources: push each machine's samples up to (elapsed × speed)."""
        if not self.sources:
            return
        if self._start is None:
            self._start = time.monotonic()
        elapsed = (time.monotonic() - self._start) * self.speed
        for w, vals in self.sources.items():
            done = self._pushed[w]
            if done >= vals.shape[0]:
                continue
            s = self.senders[w]
            due = vals.shape[0] if self.speed <= 0 else min(
                vals.shape[0], int(elapsed / (s.period_ns * 1e-9)) + 1)
            if due > done:
                s.push(T0_NS + done * s.period_ns, vals[done:due])
                self._pushed[w] = due
                self._due[w] = 0
                if due == vals.shape[0]:
                    s.flush()

    def idle(self) -> bool:
        """True when every source is pushed and every datagram acknowledged."""
        return (all(self._pushed[w] >= v.shape[0] for w, v in self.sources.items())
                and all(s.idle for s in self.senders.values()))

    def run(self, timeout_s: float, until: Callable[[], bool] | None = None) -> bool:
        """Step until idle (or ``until()``), at most ``timeout_s``; True if it got there."""
        end = time.monotonic() + timeout_s
        cond = until or self.idle
        while time.monotonic() < end:
            if cond():
                return True
            self.step()
            if self.uplink is not None and cond() is False and self.idle():
                self._send(self.uplink.flush())
        return cond()

    def close(self) -> None:
        self.sock.close()


def grid_values(layout: Layout, n: int, seed: int) -> F64:
    """Random-walk samples on the resolution grid inside each channel's range, shape (n, c)."""
    rng = np.random.default_rng(seed)
    res = np.asarray(layout.resolutions)
    lo = np.ceil(np.array([c.min for c in layout.channels]) / res)
    hi = np.floor(np.array([c.max for c in layout.channels]) / res)
    k = (lo + hi) // 2 + np.cumsum(rng.integers(-20, 21, size=(n, res.size)), axis=0)
    k = np.clip(k, lo, hi)
    return np.asarray(k * res, dtype=np.float64)


def patu_layout() -> Layout:
    """Channel layout of the built-in crane."""
    from cranetwin.model import load_machine

    return Layout.from_channels(load_machine("patu655").channels)


def make_sender(key: MachineKey, values: F64, *, first_seq: int = 1, rto_s: float = 0.2,
                max_unacked: int = 16, max_burst: int = 16, batch_samples: int = 50,
                journal: Journal | None = None) -> Sender:
    """A sender with ``values`` (100 Hz from :data:`T0_NS`) already batched into datagrams.

    Args:
        rto_s: Lower bound (and initial value) of the retransmission timeout [s].
        journal: Where the datagrams are journaled (default: in memory, from ``first_seq``).
    """
    s = Sender(key, PERIOD_NS, journal=journal or MemoryJournal(first_seq=first_seq),
               max_unacked=max_unacked, max_burst=max_burst, min_rto_ns=int(rto_s * 1e9),
               max_rto_ns=int(max(4 * rto_s, 1.0) * 1e9), batch_samples=batch_samples)
    s.push(T0_NS, values)
    s.flush()
    return s


# --- the benchmark ----------------------------------------------------------------------------
def _sender_proc(wire_ids: list[int], secret: bytes, samples: int, server: tuple[str, int],
                 speed: float, batch_samples: int, start: Any, result: Any) -> None:
    layout = patu_layout()
    senders = [Sender(MachineKey(w, f"bench-{w}", secret, layout), PERIOD_NS,
                      journal=MemoryJournal(first_seq=1), batch_samples=batch_samples,
                      max_unacked=64, max_burst=16, min_rto_ns=1_000_000_000,
                      max_rto_ns=20_000_000_000)
               for w in wire_ids]
    fleet = Fleet(senders, server, sources={w: grid_values(layout, samples, w)
                                            for w in wire_ids}, speed=speed)
    start.wait()
    t0 = time.time()
    ok = fleet.run(timeout_s=600)
    result.put({"t0": t0, "t1": time.time(), "ok": ok, "wire_bytes": fleet.unique_bytes,
                "sent": sum(s.sent_datagrams for s in senders),
                "retransmissions": sum(s.retransmissions for s in senders),
                "refused": sum(s.refused for s in senders)})
    fleet.close()


def _group_cpu_seconds(daemon: DaemonProcess) -> float | None:
    """CPU time of the daemon and of its ``--processes`` children so far [s], or None."""
    pids = [daemon.pid, *(int(c["pid"]) for c in daemon.info.get("children", []))]
    times = [cpu_seconds(p) for p in pids]
    return None if any(t is None for t in times) else sum(t for t in times if t is not None)


def _baseline(db_url: str, n: int) -> float:
    """Row-per-sample executemany into the same database: samples/s."""
    from sqlalchemy import text

    from cranetwin.storage.engine import make_engine

    eng = make_engine(db_url)
    cols = ", ".join(f"c{j} DOUBLE PRECISION" for j in range(11))
    vals = grid_values(patu_layout(), n, 1)
    rows = [{"m": 1, "t": T0_NS + i * PERIOD_NS, **{f"c{j}": float(v[j]) for j in range(11)}}
            for i, v in enumerate(vals)]
    with eng.begin() as c:
        c.execute(text("DROP TABLE IF EXISTS baseline_samples"))
        c.execute(text(f"CREATE TABLE baseline_samples (machine_id INTEGER, t_ns BIGINT, {cols}, "
                       "PRIMARY KEY (machine_id, t_ns))"))
    ins = text("INSERT INTO baseline_samples VALUES (:m, :t, " +
               ", ".join(f":c{j}" for j in range(11)) + ")")
    t = time.perf_counter()
    for i in range(0, n, 5000):  # a transaction per 100 datagrams' worth, as a daemon would
        with eng.begin() as c:
            c.execute(ins, rows[i:i + 5000])
    rate = n / (time.perf_counter() - t)
    with eng.begin() as c:
        c.execute(text("DROP TABLE baseline_samples"))
    eng.dispose()
    return rate


def run_bench(db_url: str, machines: int, samples: int, processes: int,
              baseline_samples: int, speed: float = 1.0,
              batch_samples: int = 100, daemon_processes: int = 1) -> dict[str, Any]:
    """Run the benchmark; returns the figures (see module docstring). ``daemon_processes`` > 1
    runs ``cranetwin ingest --processes N``; its CPU time is the parent's plus the children's.
    """
    from cranetwin.storage import Store

    secret = b"bench-secret-0123456789abcdef"
    with Store.open(db_url) as store:
        known = {m.machine_id for m in store.machines()}
        for w in range(1, machines + 1):
            if f"bench-{w}" not in known:
                store.add_machine(f"bench-{w}", w, secret)
        before = {f"bench-{w}": store.stats(f"bench-{w}").samples for w in range(1, machines + 1)}
    if any(before.values()):
        raise typer.BadParameter("the database already holds bench samples; use a fresh one")
    port = free_udp_port()
    with tempfile.TemporaryDirectory() as tmp:
        daemon = start_daemon(db_url, port, Path(tmp), *(
            ("--processes", str(daemon_processes)) if daemon_processes > 1 else ()))
        try:
            ctx = mp.get_context("spawn")
            start, result = ctx.Event(), ctx.Queue()
            ids = list(range(1, machines + 1))
            procs = [ctx.Process(target=_sender_proc, args=(ids[i::processes], secret, samples,
                                                            ("127.0.0.1", port), speed,
                                                            batch_samples, start, result))
                     for i in range(processes)]
            for p in procs:
                p.start()
            time.sleep(0.5)
            start.set()
            res = [result.get(timeout=900) for _ in procs]
            for p in procs:
                p.join()
            daemon_cpu = _group_cpu_seconds(daemon)
            stats = daemon.stop(timeout_s=120)
        finally:
            if daemon.poll() is None:
                daemon.kill()
    t0, t1 = min(r["t0"] for r in res), max(r["t1"] for r in res)
    sent = machines * samples
    stored = lost = dup = mismatched = 0
    layout = patu_layout()
    with Store.open(db_url) as store:
        for w in range(1, machines + 1):
            got = store.read_samples(f"bench-{w}", 0, 4e9)
            exp = grid_values(layout, samples, w)
            nst = store.stats(f"bench-{w}").samples
            stored += nst
            dup += max(0, nst - got.t_s.size)
            lost += max(0, samples - got.t_s.size)
            if got.values.shape != exp.shape or not np.array_equal(got.values, exp):
                mismatched += 1
        data_bytes = store.stats().data_bytes
        dialect = store.dialect
    rate = sent / (t1 - t0)
    base = _baseline(db_url, baseline_samples)
    return {
        "database": dialect, "machines": machines, "samples_per_machine": samples,
        "sender_processes": processes, "daemon_processes": daemon_processes, "speed": speed,
        "batch_samples": batch_samples,
        "offered_samples_per_second": round(machines * 100 * speed) if speed > 0 else None,
        "samples_sent": sent, "samples_stored": stored,
        "lost": lost, "duplicated": dup, "machines_mismatched": mismatched,
        "all_acked": all(r["ok"] for r in res), "seconds": round(t1 - t0, 3),
        "samples_per_second": round(rate),
        "bytes_per_sample": round(sum(r["wire_bytes"] for r in res) / sent, 2),
        "db_blob_bytes_per_sample": round(data_bytes / max(stored, 1), 2),
        "daemon_cpu_seconds": daemon_cpu,
        "daemon_cpu_us_per_sample": None if daemon_cpu is None else round(daemon_cpu / sent * 1e6,
                                                                           2),
        "samples_per_daemon_cpu_second": None if not daemon_cpu else round(sent / daemon_cpu),
        "load_average_1min": os.getloadavg()[0],
        "datagrams_sent": sum(r["sent"] for r in res),
        "retransmissions": sum(r["retransmissions"] for r in res),
        "refused_datagrams": sum(r["refused"] for r in res),
        "daemon": {k: stats.get(k) for k in ("received", "stored_blocks", "duplicates", "dropped",
                                         "batches", "write_seconds")},
        "baseline": "row-per-sample executemany, same database",
        "baseline_samples_per_second": round(base),
        "ratio_vs_baseline": round(rate / base, 2),
        "target_samples_per_second": 100_000,
    }


def ingest(
    db: str | None = typer.Option(None, "--db", help="Database URL (default: a temp SQLite)."),
    machines: int = typer.Option(1000, help="Simulated machines (100 Hz, 11 channels each)."),
    samples: int = typer.Option(1000, help="Samples per machine."),
    processes: int = typer.Option(2, help="Sender processes."),
    speed: float = typer.Option(1.0, help="Time scale of the senders (1 = real time, 100 Hz per "
                                "machine; 0 = as fast as possible)."),
    batch_samples: int = typer.Option(100, help="Samples per datagram (1 s at 100 Hz)."),
    daemon_processes: int = typer.Option(1, min=1, max=64,
                                         help="Daemon processes (cranetwin ingest --processes)."),
    baseline_samples: int = typer.Option(100_000, help="Samples for the row-per-sample baseline."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Fleet → UDP → daemon → database throughput, with exact read-back and a baseline."""
    with tempfile.TemporaryDirectory() as tmp:
        url = db or f"sqlite:///{Path(tmp) / 'bench.db'}"
        out = run_bench(url, machines, samples, processes, baseline_samples, speed,
                        batch_samples, daemon_processes)
        if db is None:
            out["db_file_bytes_per_sample"] = round(
                sum(f.stat().st_size for f in Path(tmp).glob("bench.db*")) / out["samples_sent"],
                2)
    emit(out, as_json)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("ingest")(ingest)


if __name__ == "__main__":  # pragma: no cover
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
