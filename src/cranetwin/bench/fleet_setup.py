"""The environments of ``cranetwin bench fleet`` (:mod:`cranetwin.bench.fleet`): the settings
record, a fresh database with its processes and loaded senders per run, opened side by side
before the first run (starting a cranetwin process takes most of a minute on a loaded host),
closed at the end; and the read-back of what a run stored.

Machines are registered just before a run streams (the processes of the other runs idle on an
empty machine table meanwhile; a daemon reloads its keys on the first unknown machine).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cranetwin.bench.fleet_parts import (
    SECRET,
    NatsServer,
    SenderPlan,
    Senders,
    create_database,
    drop_database,
    machine_name,
    pg_target,
    spawn_role,
    stop_procs,
    via_proxy,
)
from cranetwin.bench.ingest_daemon import free_udp_port, wait_ready

READY = b'{"event": "ready"'


@dataclass(frozen=True)
class FleetConfig:
    """Settings of a bench run (printed with the figures)."""

    machines: int = 1000
    rate_hz: float = 10.0
    batch_samples: int = 20
    sender_processes: int = 2
    daemons: int = 2
    writers: int = 2
    workers: int = 2
    worker_threads: int = 4
    worker_partitions: int = 8
    bus_partitions: int = 16
    window_s: float = 4.0
    settle_s: float = 1.0
    margin_s: float = 1.0
    direct_s: float = 20.0
    baseline_s: float = 40.0
    warm_s: float = 25.0
    fault_gap_s: float = 30.0
    outage_s: float = 30.0
    tail_s: float = 45.0
    lag_target_s: float = 10.0

    @property
    def faults_s(self) -> float:
        """Data time of the faults run."""
        return self.warm_s + 3 * self.fault_gap_s + self.outage_s + self.tail_s

    def plan(self, seconds: float) -> SenderPlan:
        return SenderPlan(self.machines, self.rate_hz, seconds, self.batch_samples,
                          self.sender_processes)


def child_env(cfg: FleetConfig) -> dict[str, str]:
    """The environment of every process the bench starts (this source tree first)."""
    import cranetwin

    src = str(Path(cranetwin.__file__).resolve().parents[1])
    env = dict(os.environ)
    env.update({"PYTHONPATH": os.pathsep.join(x for x in (src, env.get("PYTHONPATH")) if x),
                "CRANETWIN_WORKER_WINDOW_S": str(cfg.window_s),
                "CRANETWIN_WORKER_SETTLE_S": str(cfg.settle_s),
                "CRANETWIN_TWIN_MARGIN_S": str(cfg.margin_s),
                "CRANETWIN_BUS_PARTITIONS": str(cfg.bus_partitions),
                "CRANETWIN_WORKER_THREADS": str(cfg.worker_threads),
                # the storage writers roll the raw 1-min summaries up, as deployed
                "CRANETWIN_WORKER_ROLLUP_S": "0"})
    return env


def split(n: int, k: int) -> list[str]:
    """``0..n−1`` in ``k`` contiguous ranges ``a-b``."""
    cuts = [round(i * n / k) for i in range(k + 1)]
    return [f"{a}-{b - 1}" for a, b in zip(cuts, cuts[1:], strict=False) if b > a]


def worker_args(cfg: FleetConfig, db: str) -> list[str]:
    return ["worker", "--db", db, "--partitions", "auto", "--of", str(cfg.worker_partitions),
            "--interval", "0.5", "--log-level", "warning"]


def _register(db_url: str, machines: int) -> None:
    from cranetwin.storage import Store

    with Store.open(db_url) as store:
        for w in range(1, machines + 1):
            store.add_machine(machine_name(w), w, SECRET)


@dataclass
class DirectEnv:
    """Run 1: one ``cranetwin ingest`` writing straight to its database."""

    cfg: FleetConfig
    pg: str
    work: Path
    seconds: float
    db: str = ""
    port: int = 0
    daemon: Any = None
    senders: Senders | None = None

    def open(self) -> DirectEnv:
        env = child_env(self.cfg)
        self.work.mkdir(parents=True)
        self.db = create_database(self.pg, "direct")
        try:
            self.port = free_udp_port()
            log = self.work / "ingest.stderr"
            self.daemon = spawn_role(["ingest", "--bind", f"127.0.0.1:{self.port}", "--db",
                                      self.db, "--metrics-bind", "0", "--log-level", "WARNING"],
                                     log, env)
            (self.work / "senders").mkdir()
            self.senders = Senders(self.cfg.plan(self.seconds), ("127.0.0.1", self.port),
                                   self.work / "senders", env)
            wait_ready(self.daemon, log, READY)
        except BaseException:
            self.close()
            raise
        return self

    def register(self) -> None:
        _register(self.db, self.cfg.machines)

    def close_processes(self) -> None:
        if self.senders is not None:
            self.senders.kill()
        if self.daemon is not None:
            stop_procs([self.daemon], 60)

    def close(self) -> None:
        self.close_processes()
        if self.db:
            drop_database(self.pg, self.db)
            self.db = ""


@dataclass
class BusEnv:
    """Runs 2 and 3: NATS, storage writers, twin workers, the ingest group, a cuttable proxy to
    the database, loaded senders."""

    cfg: FleetConfig
    pg: str
    work: Path
    seconds: float
    tag: str
    db: str = ""
    db_proxied: str = ""
    port: int = 0
    proxy: Any = None
    nats: NatsServer | None = None
    writers: list[Any] = field(default_factory=list)
    workers: list[Any] = field(default_factory=list)
    ingest: Any = None
    senders: Senders | None = None

    def open(self) -> BusEnv:
        from cranetwin.bench.chaos import TcpProxy

        env = child_env(self.cfg)
        self.work.mkdir(parents=True)
        self.db = create_database(self.pg, self.tag)
        try:
            self.proxy = TcpProxy(pg_target(self.db))
            self.db_proxied = via_proxy(self.db, self.proxy.port)
            self.nats = NatsServer(self.work)
            self.nats.start()
            self.port = free_udp_port()
            self._spawn(env)
        except BaseException:
            self.close()
            raise
        return self

    def _spawn(self, env: dict[str, str]) -> None:
        """Every process at once, then each one's ready line."""
        assert self.nats is not None
        waits = []
        for i, parts in enumerate(split(self.cfg.bus_partitions, self.cfg.writers)):
            log = self.work / f"writer-{i}.stderr"
            self.writers.append(spawn_role(
                ["store-writer", "--bus", self.nats.url, "--db", self.db_proxied, "--partitions",
                 parts, "--log-level", "WARNING"], log, env))
            waits.append((self.writers[-1], log, READY))
        for i in range(self.cfg.workers):
            log = self.work / f"worker-{i}.stderr"
            self.workers.append(spawn_role(worker_args(self.cfg, self.db_proxied), log, env))
            waits.append((self.workers[-1], log, b"cranetwin worker ready"))
        log = self.work / "ingest.stderr"
        self.ingest = spawn_role(
            ["ingest", "--bind", f"127.0.0.1:{self.port}", "--db", self.db_proxied, "--bus",
             self.nats.url, "--processes", str(self.cfg.daemons), "--metrics-bind", "0",
             "--log-level", "WARNING"], log, env)
        waits.append((self.ingest, log, READY))
        (self.work / "senders").mkdir()
        self.senders = Senders(self.cfg.plan(self.seconds), ("127.0.0.1", self.port),
                               self.work / "senders", env)
        for proc, log, ready in waits:
            wait_ready(proc, log, ready)

    def register(self) -> None:
        _register(self.db, self.cfg.machines)

    def start_worker(self) -> Any:
        """One more twin worker (after a kill), not waited for: it joins when it is loaded,
        as one restarted by a supervisor would."""
        log = self.work / f"worker-{len(self.workers)}.stderr"
        proc = spawn_role(worker_args(self.cfg, self.db_proxied), log, child_env(self.cfg))
        self.workers.append(proc)
        return proc

    def stop_processes(self) -> None:
        if self.senders is not None:
            self.senders.kill()
        stop_procs([p for p in [self.ingest, *self.writers, *self.workers] if p is not None])
        if self.nats is not None:
            self.nats.close()

    def close(self) -> None:
        self.stop_processes()
        if self.proxy is not None:
            self.proxy.close()
            self.proxy = None
        if self.db:
            drop_database(self.pg, self.db)
            self.db = ""


def readback(db_url: str, plan: SenderPlan, results: list[dict[str, Any]]) -> dict[str, int]:
    """Every machine's stored samples against what its sender sent: sent, stored (doubles
    included), lost, doubled, acked, acked_not_stored, unexpected (stored, never sent),
    machines_mismatched (a stored value differs from the sender's source), machines_missing
    (no report from the sender)."""
    from cranetwin.bench.ingest import patu_layout
    from cranetwin.ingest.sender import SyntheticSource
    from cranetwin.protocol import MachineKey
    from cranetwin.storage import Store

    layout = patu_layout()
    out = dict.fromkeys(("sent", "stored", "lost", "doubled", "acked", "acked_not_stored",
                         "unexpected", "machines_mismatched", "machines_reported",
                         "unacked_datagrams_in_journals"), 0)
    period_s = plan.period_ns / 1e9
    with Store.open(db_url) as store:
        for r in results:
            name = machine_name(r["wire_id"])
            got = store.read_samples(name, 0, 4e9)
            n_stored = store.stats(name).samples
            rows = np.rint(got.t_s / period_s).astype(np.int64)
            want = np.arange(r["row0"], r["row0"] + r["samples"], dtype=np.int64)
            have = np.isin(want, rows)
            out["sent"] += int(want.size)
            out["stored"] += n_stored
            out["lost"] += int((~have).sum())
            out["doubled"] += max(0, n_stored - int(rows.size))
            out["unexpected"] += int((~np.isin(rows, want)).sum())
            out["acked"] += int(r["acked"])
            out["acked_not_stored"] += max(0, int(r["acked"]) - int(have.sum()))
            out["machines_reported"] += 1
            out["unacked_datagrams_in_journals"] += int(r["unacked"])
            if rows.size:
                key = MachineKey(r["wire_id"], name, SECRET, layout)
                exp = SyntheticSource(key, period_s, seed=r["wire_id"]).read(
                    int(rows[0]), int(rows[-1] - rows[0] + 1))[rows - rows[0]]
                if not np.array_equal(exp, got.values, equal_nan=True):
                    out["machines_mismatched"] += 1
    out["machines_missing"] = plan.machines - out["machines_reported"]
    return out
