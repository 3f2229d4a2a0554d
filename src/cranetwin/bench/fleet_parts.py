"""The moving parts of ``cranetwin bench fleet``: a private NATS server that can be killed and
restarted, a fresh PostgreSQL database, the journaled sender processes, the cranetwin role
processes (ingest group, storage writers, twin workers) and the sampler that polls CPU time,
twin progress and stored samples while a run goes on. The schedule is in
:mod:`cranetwin.bench.fleet`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cranetwin.bench.ingest_daemon import cpu_seconds, wait_ready
from cranetwin.errors import MissingExtraError

SECRET = b"fleet-secret-0123456789abcdef!!"
PG_DEFAULT = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def machine_name(wire_id: int) -> str:
    return f"fleet-{wire_id}"


# --- NATS ---------------------------------------------------------------------------------------
class NatsServer:
    """A ``nats-server -js`` of the bench's own: its port and store directory stay the same
    across :meth:`kill` and :meth:`start`, so a restart finds its streams again."""

    def __init__(self, workdir: Path) -> None:
        exe = shutil.which("nats-server") or next(
            (p for p in ("/usr/sbin/nats-server", "/usr/bin/nats-server") if Path(p).exists()),
            None)
        if exe is None:
            raise RuntimeError("nats-server is not installed")
        self.exe = exe
        self.port = free_tcp_port()
        self.store = workdir / "js"
        self.url = f"nats://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None
        self.pids: list[int] = []

    def start(self) -> None:
        self.proc = subprocess.Popen([self.exe, "-a", "127.0.0.1", "-p", str(self.port), "-js",
                                      "-sd", str(self.store)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        self.pids.append(self.proc.pid)
        end = time.monotonic() + 20
        while time.monotonic() < end:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.2).close()
                break
            except OSError:
                time.sleep(0.05)
        time.sleep(0.3)  # JetStream is ready a moment after the listener

    def kill(self) -> None:
        """SIGKILL (no shutdown of its streams) and reap."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


# --- PostgreSQL ---------------------------------------------------------------------------------
def _conninfo(url: str) -> str:
    return url.replace("postgresql+psycopg://", "postgresql://", 1)


_MIGRATING = threading.Lock()


def create_database(pg_url: str, tag: str) -> str:
    """A new database ``h_fleetbench_<tag>_<random>`` on the server of ``pg_url``, its schema
    made (:meth:`Store.open` migrates): its SQLAlchemy URL."""
    try:
        import psycopg
    except ImportError as exc:
        raise MissingExtraError("postgres", "cranetwin bench fleet") from exc
    from cranetwin.storage import Store

    name = f"h_fleetbench_{tag}_{uuid.uuid4().hex[:8]}"
    with psycopg.connect(_conninfo(pg_url), autocommit=True) as c:
        c.execute(f'CREATE DATABASE "{name}"')
    url = f"{pg_url.rpartition('/')[0]}/{name}"
    try:
        with _MIGRATING:  # Alembic's module state is not thread-safe
            Store.open(url).close()
    except BaseException:
        drop_database(pg_url, url)
        raise
    return url


def drop_database(pg_url: str, url: str) -> None:
    """Drop the database of ``url`` (made by :func:`create_database`), ending its sessions."""
    try:
        import psycopg
    except ImportError as exc:
        raise MissingExtraError("postgres", "cranetwin bench fleet") from exc

    name = url.rpartition("/")[2]
    with psycopg.connect(_conninfo(pg_url), autocommit=True) as c:
        c.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def via_proxy(url: str, port: int) -> str:
    """``url`` with its host:port replaced by 127.0.0.1:``port`` (the cuttable TCP proxy)."""
    scheme, _, rest = url.partition("://")
    cred, _, hostpart = rest.rpartition("@")
    _, _, path = hostpart.partition("/")
    return f"{scheme}://{cred + '@' if cred else ''}127.0.0.1:{port}/{path}"


def pg_target(url: str) -> tuple[str, int]:
    hostpart = url.partition("://")[2].rpartition("@")[2].partition("/")[0]
    h, _, p = hostpart.partition(":")
    return h or "127.0.0.1", int(p or 5432)


def register_machines(db_url: str, machines: int) -> None:
    from cranetwin.storage import Store

    with Store.open(db_url) as store:
        for w in range(1, machines + 1):
            store.add_machine(machine_name(w), w, SECRET)


# --- senders ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SenderPlan:
    """What the sender processes send: ``machines`` at ``rate_hz`` for ``duration_s`` of
    real-time data, ``batch_samples`` per datagram, ``processes`` processes."""

    machines: int
    rate_hz: float
    duration_s: float
    batch_samples: int
    processes: int
    drain_s: float = 90.0

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.rate_hz))


def sender_main() -> None:  # pragma: no cover - runs in a subprocess
    """Entry of one sender process: argv[1] is a JSON object of its settings. Streams its
    machines with :func:`cranetwin.ingest.sender.run_sender` (one journal per machine) and
    writes one JSON object per machine: its counters and its first sample row. (This is
    :func:`~cranetwin.ingest.sender.run_fleet` spelled out: each machine gets its own clock
    function, whose first reading is the start of its sample rows.)"""
    from cranetwin.bench.ingest import patu_layout
    from cranetwin.ingest.sender import SyntheticSource, run_sender
    from cranetwin.protocol import MachineKey

    cfg = json.loads(sys.argv[1])
    layout = patu_layout()
    period_ns = int(cfg["period_ns"])
    keys = [MachineKey(w, machine_name(w), SECRET, layout) for w in cfg["wire_ids"]]
    sources = [SyntheticSource(k, period_ns / 1e9, seed=k.wire_id) for k in keys]
    firsts: dict[int, int] = {}
    stop = asyncio.Event()

    def clock_for(w: int) -> Any:
        def clock() -> int:  # the first reading is the sender's start: row0 follows from it
            now = time.time_ns()
            firsts.setdefault(w, now)
            return now
        return clock

    async def main() -> list[Any]:
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        jobs = [run_sender(k, tuple(cfg["server"]), src,
                           journal_dir=Path(cfg["journal"]) / k.machine_id, fsync=False,
                           period_ns=period_ns, duration_s=cfg["duration_s"],
                           batch_samples=cfg["batch_samples"], status_every_s=0.0,
                           drain_timeout_s=cfg["drain_s"], min_rto_s=1.0, max_rto_s=5.0,
                           tick_s=0.25, stop=stop, clock_ns=clock_for(k.wire_id))
                for k, src in zip(keys, sources, strict=True)]
        return list(await asyncio.gather(*jobs))

    sys.stdout.write("ready\n")  # imports done, sources built; stream on "go" (stdin)
    sys.stdout.flush()
    if sys.stdin.readline().strip() != "go":
        return
    stats = asyncio.run(main())
    with open(cfg["out"], "w") as out:
        for k, st in zip(keys, stats, strict=True):
            out.write(json.dumps({"wire_id": k.wire_id,
                                  "row0": -(-firsts.get(k.wire_id, 0) // period_ns),
                                  "samples": st.samples, "acked": st.acked_samples,
                                  "unacked": st.unacked, "datagrams": st.datagrams,
                                  "retransmissions": st.retransmissions}) + "\n")


class Senders:
    """The sender processes of one run (machines dealt round-robin), started and loaded
    (their ready lines waited for); they stream on :meth:`go`."""

    def __init__(self, plan: SenderPlan, server: tuple[str, int], workdir: Path,
                 env: dict[str, str]) -> None:
        self.plan = plan
        self.outs: list[Path] = []
        self.procs: list[subprocess.Popen[bytes]] = []
        ids = list(range(1, plan.machines + 1))
        for i in range(plan.processes):
            out = workdir / f"senders-{i}.jsonl"
            cfg = {"wire_ids": ids[i::plan.processes], "server": list(server),
                   "journal": str(workdir / "journals"), "period_ns": plan.period_ns,
                   "duration_s": plan.duration_s, "batch_samples": plan.batch_samples,
                   "drain_s": plan.drain_s, "out": str(out)}
            with open(workdir / f"senders-{i}.stderr", "ab") as err:
                self.procs.append(subprocess.Popen(
                    [sys.executable, "-c", "from cranetwin.bench.fleet_parts import sender_main;"
                     " sender_main()", json.dumps(cfg)], stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE, stderr=err, env=env))
            self.outs.append(out)
        for i, p in enumerate(self.procs):
            wait_ready(p, workdir / f"senders-{i}.stderr", b"ready")

    def go(self) -> None:
        for p in self.procs:
            assert p.stdin is not None
            p.stdin.write(b"go\n")
            p.stdin.close()

    def wait(self, timeout_s: float) -> bool:
        """Wait for the senders to stream and drain; True if all did within ``timeout_s``.
        Those still running then get SIGTERM: they stop, keep what is unacknowledged in their
        journals and write their counters."""
        end = time.monotonic() + timeout_s
        for p in self.procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.1, end - time.monotonic()))
        drained = all(p.poll() == 0 for p in self.procs)
        stop_procs(self.procs, 60.0)
        return drained

    def results(self) -> list[dict[str, Any]]:
        rows: list[dict[str, Any]] = []
        for out in self.outs:
            if out.exists():
                rows.extend(json.loads(x) for x in out.read_text().splitlines() if x.strip())
        return rows

    def kill(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)


# --- cranetwin role processes -------------------------------------------------------------------
def cranetwin_cmd(*args: str) -> list[str]:
    return [sys.executable, "-c", "from cranetwin.cli import main; main()", *args]


def spawn_role(args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    """Start ``cranetwin ARGS`` (its log to ``log``, stdout piped for its ready line)."""
    with open(log, "ab") as err:
        return subprocess.Popen(cranetwin_cmd(*args), stdout=subprocess.PIPE, stderr=err,
                                env=env)


def start_role(args: list[str], log: Path, env: dict[str, str],
               ready: bytes) -> subprocess.Popen[bytes]:
    """:func:`spawn_role` and :func:`wait_ready`."""
    proc = spawn_role(args, log, env)
    wait_ready(proc, log, ready)
    return proc


def children(pid: int) -> list[int]:
    """Child process ids of ``pid`` (Linux /proc)."""
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(x) for x in text.split()]


def stop_procs(procs: list[subprocess.Popen[bytes]], grace_s: float = 20.0) -> None:
    """SIGTERM to all at once, wait up to ``grace_s`` together, then SIGKILL what is left."""
    live = [p for p in procs if p.poll() is None]
    for p in live:
        p.send_signal(signal.SIGTERM)
    end = time.monotonic() + grace_s
    for p in live:
        try:
            p.wait(max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


# --- the sampler --------------------------------------------------------------------------------
@dataclass
class Sampler:
    """Polls, once a second, from its own direct connection to PostgreSQL (never through the
    proxy): every machine's twin progress and the samples stored; and the CPU time of the
    ingest and storage processes (killed ones keep their last reading).

    ``lag`` holds (monotonic time, lag [s]): the largest ``now − watermark`` over the machines
    (a machine without progress yet counts from ``stream_start_s``), i.e. how far the twin
    results are behind the machines' real-time sample clock. ``latencies`` holds one
    ``updated_s − watermark_s`` per window commit seen (see :mod:`cranetwin.bench.fleet`).
    """

    db_url: str
    machines: int
    stream_start_s: float
    cpu_pids: dict[str, list[int]] = field(default_factory=dict)
    cpu: dict[int, tuple[str, float]] = field(default_factory=dict)
    lag: list[tuple[float, float]] = field(default_factory=list)
    latencies: list[float] = field(default_factory=list)
    stored: int = 0
    lag_until_s: float = math.inf

    def __post_init__(self) -> None:
        self._seen: dict[str, tuple[float, int]] = {}
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="fleet-sampler", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def track(self, role: str, pid: int) -> None:
        with self._lock:
            self.cpu_pids.setdefault(role, []).append(pid)

    def cpu_seconds(self, role: str) -> float:
        with self._lock:
            return sum(c for r, c in self.cpu.values() if r == role)

    def poll_cpu(self) -> None:
        with self._lock:
            roles = {r: list(p) for r, p in self.cpu_pids.items()}
        for role, pids in roles.items():
            for pid in pids:
                for p in (pid, *children(pid)):
                    c = cpu_seconds(p)
                    if c is not None:
                        with self._lock:
                            self.cpu[p] = (role, max(c, self.cpu.get(p, (role, 0.0))[1]))

    def _run(self) -> None:
        try:
            import psycopg
        except ImportError as exc:
            raise MissingExtraError("postgres", "cranetwin bench fleet") from exc

        conn: Any = None
        while not self._stop.wait(1.0):
            self.poll_cpu()
            try:
                if conn is None:
                    conn = psycopg.connect(_conninfo(self.db_url), autocommit=True)
                self._poll_db(conn)
            except psycopg.Error:
                conn = None

    def _poll_db(self, conn: Any) -> None:
        now = time.time()
        rows = conn.execute("SELECT machine_id, watermark_s, windows, updated_s "
                            "FROM twin_progress").fetchall()
        got = conn.execute("SELECT coalesce(sum(n), 0) FROM sample_blocks").fetchone()
        self.stored = int(got[0])
        marks = {str(m): float(wm) for m, wm, _, _ in rows}
        for m, wm, windows, upd in rows:
            prev = self._seen.get(m)
            if prev is not None and int(windows) > prev[1] and float(wm) > prev[0]:
                self.latencies.append(float(upd) - float(wm))
            self._seen[m] = (float(wm), int(windows))
        if now <= self.lag_until_s:
            oldest = min([*marks.values(), *([self.stream_start_s] * (self.machines
                                                                       - len(marks)))])
            self.lag.append((time.monotonic(), max(0.0, now - oldest)))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.poll_cpu()
