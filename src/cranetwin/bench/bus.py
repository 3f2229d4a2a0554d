"""``cranetwin bench bus``: samples stored per CPU core through the fleet bus, against the
direct path, in the same run.

Two runs of the same simulated fleet (sender processes driving the protocol's ``Sender`` over
UDP, as ``cranetwin bench ingest``), each into a fresh database (a fresh schema of the
PostgreSQL database given, or a fresh SQLite file):

* **direct**: ``cranetwin ingest`` writes to the database (acks after commit);
* **bus**: ``cranetwin ingest --bus`` publishes to JetStream (acks after the PubAck) and
  ``cranetwin store-writer`` consumes into the database (acks on the bus after commit). The
  run ends when every sample is in the database.

CPU time (user + system, from ``/proc``) of the daemon, of the storage writer and, when the
bench starts its own ``nats-server`` (no ``--bus`` given), of the NATS server is counted from
the moment each is ready (start-up imports excluded) to the moment every sample is stored. The
1-min summary rollup is left out of both paths (it is the same work on either, done once per
machine-minute): the periodic rollups of the daemons and the storage writer are set beyond
the run (``--rollup-interval 3600``). ``*_samples_per_cpu_second`` is
the samples stored over the CPU seconds of the cranetwin processes of the path (daemon; daemon
+ storage writer); ``per_core_ratio_vs_direct`` is bus over direct, and
``per_core_ratio_with_nats`` counts the NATS server's CPU too. The database server's CPU is in
neither. Every sample is read back and compared exactly.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit
from cranetwin.bench.ingest import (
    _cpu_seconds,
    _sender_proc,
    free_udp_port,
    grid_values,
    patu_layout,
    start_daemon,
)
from cranetwin.errors import MissingExtraError

SECRET = b"bench-secret-0123456789abcdef"


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def _private_nats(workdir: Path) -> Iterator[tuple[str, int]]:
    """A ``nats-server -js`` of the bench's own on a free port: (url, pid)."""
    exe = shutil.which("nats-server")
    if exe is None:
        raise typer.BadParameter("nats-server is not installed; give --bus nats://HOST:PORT")
    port = _free_tcp_port()
    proc = subprocess.Popen([exe, "-a", "127.0.0.1", "-p", str(port), "-js", "-sd",
                             str(workdir / "js")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 20
        while time.monotonic() < end:
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                time.sleep(0.05)
        time.sleep(0.3)  # JetStream ready after the listener
        yield f"nats://127.0.0.1:{port}", proc.pid
    finally:
        proc.terminate()
        proc.wait(20)


@contextlib.contextmanager
def _fresh_db(db_url: str | None, tag: str, workdir: Path) -> Iterator[str]:
    """A fresh database: a new schema of ``db_url`` (PostgreSQL; dropped after) or a SQLite
    file in ``workdir``."""
    if db_url is None or db_url.startswith("sqlite"):
        yield f"sqlite:///{workdir / f'{tag}.db'}"
        return
    try:
        import psycopg
    except ImportError as exc:
        raise MissingExtraError("postgres", "cranetwin bench bus on PostgreSQL") from exc

    conninfo = db_url.replace("postgresql+psycopg://", "postgresql://", 1)
    schema = f"bench_{tag}_{uuid.uuid4().hex[:8]}"
    with psycopg.connect(conninfo, autocommit=True) as c:
        c.execute(f'CREATE SCHEMA "{schema}"')
    sep = "&" if "?" in db_url else "?"
    try:
        yield f"{db_url}{sep}options=-csearch_path%3D{schema}"
    finally:
        with psycopg.connect(conninfo, autocommit=True) as c:
            c.execute(f'DROP SCHEMA "{schema}" CASCADE')


def _start_writer(db_url: str, bus_url: str, workdir: Path) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "store-writer",
           "--bus", bus_url, "--db", db_url, "--log-level", "WARNING", "--rollup-interval",
           "3600"]
    with open(workdir / "store-writer.stderr", "ab") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err)
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    if not ready or not proc.stdout.readline().startswith(b'{"event": "ready"'):
        proc.kill()
        proc.wait(10)
        raise RuntimeError("store-writer did not start: "
                           + (workdir / "store-writer.stderr").read_text()[-2000:])
    return proc


class _Senders:
    """Sender processes, spawned (and loaded) before the daemon starts, so the daemon's CPU
    window holds the run only; :meth:`run` starts them and waits for the results."""

    def __init__(self, machines: int, samples: int, processes: int, port: int, speed: float,
                 batch_samples: int) -> None:
        ctx = mp.get_context("spawn")
        self.start, self.result = ctx.Event(), ctx.Queue()
        ids = list(range(1, machines + 1))
        self.procs = [ctx.Process(target=_sender_proc, args=(
            ids[i::processes], SECRET, samples, ("127.0.0.1", port), speed, batch_samples,
            self.start, self.result)) for i in range(processes)]
        for p in self.procs:
            p.start()

    def run(self) -> list[dict[str, Any]]:
        time.sleep(1.0)  # the children have built their senders by now (they wait on start)
        self.start.set()
        res = [self.result.get(timeout=900) for _ in self.procs]
        for p in self.procs:
            p.join()
        return res


def _register(db_url: str, machines: int) -> None:
    from cranetwin.storage import Store

    with Store.open(db_url) as store:
        for w in range(1, machines + 1):
            store.add_machine(f"bench-{w}", w, SECRET)


def _check(db_url: str, machines: int, samples: int) -> dict[str, int]:
    from cranetwin.storage import Store

    layout = patu_layout()
    stored = lost = dup = mismatched = 0
    with Store.open(db_url) as store:
        for w in range(1, machines + 1):
            got = store.read_samples(f"bench-{w}", 0, 4e9)
            nst = store.stats(f"bench-{w}").samples
            stored += nst
            dup += max(0, nst - got.t_s.size)
            lost += max(0, samples - got.t_s.size)
            exp = grid_values(layout, samples, w)
            if got.values.shape != exp.shape or not np.array_equal(got.values, exp):
                mismatched += 1
    return {"stored": stored, "lost": lost, "duplicated": dup, "machines_mismatched": mismatched}


def _run_direct(db_url: str, machines: int, samples: int, processes: int, speed: float,
                batch_samples: int, workdir: Path) -> dict[str, Any]:
    _register(db_url, machines)
    port = free_udp_port()
    senders = _Senders(machines, samples, processes, port, speed, batch_samples)
    daemon = start_daemon(db_url, port, workdir, "--rollup-interval", "3600")
    try:
        cpu0 = _cpu_seconds(daemon.pid) or 0.0
        res = senders.run()
        cpu = (_cpu_seconds(daemon.pid) or 0.0) - cpu0
        daemon.stop(timeout_s=120)
    finally:
        if daemon.poll() is None:
            daemon.kill()
    t0, t1 = min(r["t0"] for r in res), max(r["t1"] for r in res)
    return {"seconds": round(t1 - t0, 3), "daemon_cpu_seconds": round(cpu, 3),
            "all_acked": all(r["ok"] for r in res), **_check(db_url, machines, samples)}


def _run_bus(db_url: str, bus_url: str, nats_pid: int | None, machines: int, samples: int,
             processes: int, speed: float, batch_samples: int,
             workdir: Path) -> dict[str, Any]:
    from cranetwin.storage import Store

    _register(db_url, machines)
    tag = uuid.uuid4().hex[:8]
    os.environ.update({"CRANETWIN_BUS_STREAM": f"BENCH_{tag}",
                       "CRANETWIN_BUS_PREFIX": f"bench{tag}.blocks"})
    port = free_udp_port()
    senders = _Senders(machines, samples, processes, port, speed, batch_samples)
    writer = _start_writer(db_url, bus_url, workdir)
    daemon = start_daemon(db_url, port, workdir, "--bus", bus_url, "--rollup-interval", "3600")
    total = machines * samples
    try:
        cpu0 = {"daemon": _cpu_seconds(daemon.pid) or 0.0, "writer": _cpu_seconds(writer.pid)
                or 0.0, "nats": (_cpu_seconds(nats_pid) or 0.0) if nats_pid else 0.0}
        res = senders.run()
        t_acked = max(r["t1"] for r in res)
        with Store.open(db_url) as store:
            end = time.monotonic() + 300
            while store.stats().samples < total and time.monotonic() < end:
                time.sleep(0.05)
        t_stored = time.time()
        cpu_daemon = (_cpu_seconds(daemon.pid) or 0.0) - cpu0["daemon"]
        cpu_writer = (_cpu_seconds(writer.pid) or 0.0) - cpu0["writer"]
        cpu_nats = ((_cpu_seconds(nats_pid) or 0.0) - cpu0["nats"]) if nats_pid else None
        daemon.stop(timeout_s=120)
        writer.send_signal(signal.SIGTERM)
        out, _ = writer.communicate(timeout=120)
    finally:
        for p in (daemon.proc, writer):
            if p.poll() is None:
                p.kill()
                p.wait(10)
    stopped = [json.loads(x) for x in out.decode().splitlines() if '"stopped"' in x]
    t0 = min(r["t0"] for r in res)
    return {"seconds": round(t_stored - t0, 3), "seconds_to_last_ack": round(t_acked - t0, 3),
            "daemon_cpu_seconds": round(cpu_daemon, 3),
            "store_writer_cpu_seconds": round(cpu_writer, 3),
            "nats_server_cpu_seconds": None if cpu_nats is None else round(cpu_nats, 3),
            "all_acked": all(r["ok"] for r in res),
            "store_writer": stopped[0] if stopped else None,
            **_check(db_url, machines, samples)}


def run_bench(db_url: str | None, bus_url: str | None, machines: int, samples: int,
              processes: int, speed: float, batch_samples: int) -> dict[str, Any]:
    """Both runs (direct first, then bus); returns the figures (module docstring)."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        work = Path(tmp)
        nats_pid: int | None = None
        if bus_url is None:
            bus_url, nats_pid = stack.enter_context(_private_nats(work))
        with _fresh_db(db_url, "direct", work) as url:
            direct = _run_direct(url, machines, samples, processes, speed, batch_samples, work)
            dialect = url.split(":", 1)[0]
        with _fresh_db(db_url, "bus", work) as url:
            bus = _run_bus(url, bus_url, nats_pid, machines, samples, processes, speed,
                           batch_samples, work)
    total = machines * samples
    d_cpu = direct["daemon_cpu_seconds"]
    b_cpu = bus["daemon_cpu_seconds"] + bus["store_writer_cpu_seconds"]
    if d_cpu <= 0 or b_cpu <= 0:
        raise RuntimeError("no CPU time measured: run more samples")
    d_rate = total / d_cpu
    b_rate = total / b_cpu
    n_cpu = bus["nats_server_cpu_seconds"]
    return {
        "database": dialect, "machines": machines, "samples_per_machine": samples,
        "samples_sent": total, "speed": speed, "batch_samples": batch_samples,
        "direct": direct, "bus": bus,
        "direct_samples_per_cpu_second": round(d_rate),
        "bus_samples_per_cpu_second": round(b_rate),
        "per_core_ratio_vs_direct": round(b_rate / d_rate, 3),
        "per_core_ratio_with_nats": None if n_cpu is None else round(
            (total / (b_cpu + n_cpu)) / d_rate, 3),
        "direct_samples_per_second": round(total / direct["seconds"]),
        "bus_samples_per_second": round(total / bus["seconds"]),
        "lost": direct["lost"] + bus["lost"], "duplicated": direct["duplicated"]
        + bus["duplicated"],
        "load_average_1min": os.getloadavg()[0],
        "target_per_core_ratio": 0.7,
    }


def bus(
    db: str | None = typer.Option(None, "--db", help="PostgreSQL URL (each run gets a fresh "
                                  "schema, dropped after); default: SQLite files."),
    bus_url: str | None = typer.Option(None, "--bus", help="NATS server (default: a private "
                                       "nats-server started by the bench, its CPU measured)."),
    machines: int = typer.Option(500, help="Simulated machines (100 Hz, 11 channels each)."),
    samples: int = typer.Option(2000, help="Samples per machine."),
    processes: int = typer.Option(2, help="Sender processes."),
    speed: float = typer.Option(1.0, help="Time scale of the senders (1 = real time)."),
    batch_samples: int = typer.Option(100, help="Samples per datagram."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Samples per CPU core: daemon → JetStream → store-writer → DB vs daemon → DB."""
    emit(run_bench(db, bus_url, machines, samples, processes, speed, batch_samples), as_json)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("bus")(bus)
