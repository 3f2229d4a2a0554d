"""``cranetwin bench fleet``: the whole fleet path on PostgreSQL + NATS, with and without faults.

Every role is a real process (:mod:`cranetwin.bench.fleet_parts`): journaled sender processes
(:func:`cranetwin.ingest.sender.run_sender`, many machines per process, one journal each, not
synced to disk: the bench kills no sender), ``cranetwin ingest --processes N --bus``,
``cranetwin store-writer --partitions`` (the bus partitions split between the writers), ``cranetwin
worker --partitions auto --of P`` (M workers), a ``nats-server -js`` of the bench's own on a free
port, and a fresh database ``h_fleetbench_…`` per run (dropped at the end). Every cranetwin
process reaches PostgreSQL through a TCP proxy that the bench can cut. Three runs:

1. **direct** (the per-core baseline): one ``cranetwin ingest`` process writing straight to the
   database, the same machines, rate and datagrams, ``--direct-s`` of data;
2. **baseline**: the bus topology without faults, ``--baseline-s`` of data;
3. **faults** (``--faults``): the bus topology while, ``--fault-gap-s`` apart after
   ``--warm-s``: a daemon process is killed with SIGKILL (its group restarts it), a twin worker
   is killed with SIGKILL (the others take its partitions; a new one is started 5 s later, as a
   supervisor would), the NATS server is killed with SIGKILL and restarted at once on its port
   and store, and PostgreSQL is cut for ``--outage-s`` (the proxy closes every connection and
   refuses new ones; the server itself keeps running, it is shared).

Figures of a run:

* ``sent`` (samples the senders put in their journals), ``stored`` (samples in the database,
  doubles included), ``lost`` (sent, not stored), ``doubled`` (stored more than once),
  ``acked_not_stored`` (acknowledged to a sender, not stored; from the counts),
  ``machines_mismatched`` (a stored value differs from what was sent): every machine's samples
  are read back and compared with the sender's source;
* ``samples_per_second_per_core``: samples stored over the CPU seconds (user + system, /proc) of
  the ingest processes (the group's parent and children) and the storage writers, from the first
  sample sent until everything is stored (the direct run: of its one daemon). The 1-min summary
  rollup is left out of every path (``--rollup-interval 3600``; the workers roll up).
  ``per_core_ratio_vs_direct`` is that over the direct run's figure. NATS, PostgreSQL and the
  workers are not in it (their CPU seconds are listed);
* ``latency_p50_s``/``latency_p95_s``: sample time → twin result. For every window commit of a
  worker seen (``twin_progress`` polled once a second), the commit's wall-clock time
  (``updated_s``) minus the window's end (its newest sample's time, to one period). Sample
  times are the machines' real-time clock, so this is the age of a window's newest sample when
  its twin result became readable: it includes the sender's batching, the bus, storage, the
  worker's window (``--window-s``), settling and its pass over the machines;
* ``lag``: once a second, the largest ``now − watermark`` over the machines (how far the twin
  results are behind the machines' clock; the worker's own lag gauge is newest *stored* sample
  − watermark, which stops growing while storage is cut). Per fault: the lag before it, the
  largest after it, and ``recover_seconds`` from the fault's end until the lag is under
  ``--lag-target-s`` (null if it was not before the next fault or the end of the data).
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit
from cranetwin.bench.fleet_parts import (
    PG_DEFAULT,
    SECRET,
    NatsServer,
    Sampler,
    SenderPlan,
    Senders,
    children,
    fresh_database,
    machine_name,
    pg_target,
    register_machines,
    spawn_role,
    start_role,
    stop_proc,
    via_proxy,
    wait_ready,
)
from cranetwin.bench.ingest_daemon import free_udp_port


@dataclass(frozen=True)
class FleetConfig:
    """Settings of a bench run (printed with the figures)."""

    machines: int = 1000
    rate_hz: float = 10.0
    batch_samples: int = 10
    sender_processes: int = 2
    daemons: int = 2
    writers: int = 2
    workers: int = 2
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


def _env(cfg: FleetConfig) -> dict[str, str]:
    import cranetwin

    src = str(Path(cranetwin.__file__).resolve().parents[1])
    env = dict(os.environ)
    env.update({"PYTHONPATH": os.pathsep.join(x for x in (src, env.get("PYTHONPATH")) if x),
                "CRANETWIN_WORKER_WINDOW_S": str(cfg.window_s),
                "CRANETWIN_WORKER_SETTLE_S": str(cfg.settle_s),
                "CRANETWIN_TWIN_MARGIN_S": str(cfg.margin_s),
                "CRANETWIN_BUS_PARTITIONS": str(cfg.bus_partitions)})
    return env


def _split(n: int, k: int) -> list[str]:
    """``0..n−1`` in ``k`` contiguous ranges ``a-b``."""
    cuts = [round(i * n / k) for i in range(k + 1)]
    return [f"{a}-{b - 1}" for a, b in zip(cuts, cuts[1:], strict=False) if b > a]


def _readback(db_url: str, plan: SenderPlan, results: list[dict[str, Any]]) -> dict[str, int]:
    """Every machine's stored samples against what its sender sent (module docstring)."""
    from cranetwin.bench.ingest import patu_layout
    from cranetwin.ingest.sender import SyntheticSource
    from cranetwin.protocol import MachineKey
    from cranetwin.storage import Store

    layout = patu_layout()
    out = dict.fromkeys(("sent", "stored", "lost", "doubled", "acked", "acked_not_stored",
                         "unexpected", "machines_mismatched", "machines_reported"), 0)
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
            if rows.size:
                key = MachineKey(r["wire_id"], name, SECRET, layout)
                exp = SyntheticSource(key, period_s, seed=r["wire_id"]).read(
                    int(rows[0]), int(rows[-1] - rows[0] + 1))[rows - rows[0]]
                if not np.array_equal(exp, got.values, equal_nan=True):
                    out["machines_mismatched"] += 1
    out["machines_missing"] = plan.machines - out["machines_reported"]
    return out


def _pct(x: list[float], q: float) -> float | None:
    return None if not x else round(float(np.percentile(x, q)), 2)


def _direct(cfg: FleetConfig, pg: str, work: Path) -> dict[str, Any]:
    """The single-process direct path (run 1)."""
    env = _env(cfg)
    plan = SenderPlan(cfg.machines, cfg.rate_hz, cfg.direct_s, cfg.batch_samples,
                      cfg.sender_processes)
    with fresh_database(pg, "direct") as url:
        register_machines(url, cfg.machines)
        port = free_udp_port()
        daemon = start_role(["ingest", "--bind", f"127.0.0.1:{port}", "--db", url,
                                "--metrics-bind", "0", "--log-level", "WARNING",
                                "--rollup-interval", "3600"], work / "direct-ingest.stderr",
                               env, b'{"event": "ready"')
        sampler = Sampler(url, cfg.machines, time.time())
        sampler.track("ingest", daemon.pid)
        senders = None
        try:
            sampler.poll_cpu()
            cpu0 = sampler.cpu_seconds("ingest")
            t0 = time.monotonic()
            (work / "senders").mkdir(parents=True)
            senders = Senders(plan, ("127.0.0.1", port), work / "senders", env)
            drained = senders.wait(cfg.direct_s + plan.drain_s + 60)
            sampler.poll_cpu()
            cpu = sampler.cpu_seconds("ingest") - cpu0
            seconds = time.monotonic() - t0
            stop_proc(daemon)
        finally:
            if senders is not None:
                senders.kill()
            if daemon.poll() is None:
                daemon.kill()
                daemon.wait(10)
        counts = _readback(url, plan, senders.results())
    return {"seconds": round(seconds, 1), "drained": drained, "ingest_cpu_seconds": round(cpu, 2),
            "samples_per_second_per_core": round(counts["stored"] / cpu) if cpu > 0 else None,
            **counts}


@dataclass
class _Topology:
    """The processes of a bus run."""

    nats: NatsServer
    db: str
    writers: list[Any]
    workers: list[Any]
    ingest: Any
    port: int

    def all_procs(self) -> list[Any]:
        return [self.ingest, *self.writers, *self.workers]


def _worker_args(cfg: FleetConfig, db: str) -> list[str]:
    return ["worker", "--db", db, "--partitions", "auto", "--of", str(cfg.worker_partitions),
            "--interval", "0.5", "--log-level", "warning"]


def _start(cfg: FleetConfig, db: str, work: Path, env: dict[str, str]) -> _Topology:
    """NATS, then the writers, workers and the ingest group, started together (each waited
    for until its ready line)."""
    nats = NatsServer(work)
    nats.start()
    topo = _Topology(nats, db, [], [], None, free_udp_port())
    ok = b'{"event": "ready"'
    try:
        waits = []
        for i, parts in enumerate(_split(cfg.bus_partitions, cfg.writers)):
            log = work / f"writer-{i}.stderr"
            topo.writers.append(spawn_role(
                ["store-writer", "--bus", nats.url, "--db", db, "--partitions", parts,
                 "--log-level", "WARNING", "--rollup-interval", "3600"], log, env))
            waits.append((topo.writers[-1], log, ok))
        for i in range(cfg.workers):
            log = work / f"worker-{i}.stderr"
            topo.workers.append(spawn_role(_worker_args(cfg, db), log, env))
            waits.append((topo.workers[-1], log, b"cranetwin worker ready"))
        log = work / "ingest.stderr"
        topo.ingest = spawn_role(
            ["ingest", "--bind", f"127.0.0.1:{topo.port}", "--db", db, "--bus", nats.url,
             "--processes", str(cfg.daemons), "--metrics-bind", "0", "--log-level", "WARNING",
             "--rollup-interval", "3600"], log, env)
        waits.append((topo.ingest, log, ok))
        for proc, log, ready in waits:
            wait_ready(proc, log, ready)
    except BaseException:
        _stop(topo)
        raise
    return topo


def _stop(topo: _Topology) -> None:
    for p in topo.all_procs():
        if p is not None:
            stop_proc(p, 60)
    topo.nats.close()


def _faults(cfg: FleetConfig, topo: _Topology, proxy: Any, work: Path, env: dict[str, str],
            at: Callable[[float], float]) -> list[dict[str, Any]]:
    """Run the fault schedule; each fault's name, how, start and end (monotonic)."""
    out: list[dict[str, Any]] = []
    t = cfg.warm_s
    t_start = at(t)
    kids = children(topo.ingest.pid)
    if kids:
        os.kill(kids[0], 9)
    out.append({"fault": "daemon", "how": f"SIGKILL of ingest process 1 of {cfg.daemons} "
                "(cranetwin ingest --processes restarts it on its socket)",
                "start": t_start, "end": time.monotonic()})
    t += cfg.fault_gap_s
    t_start = at(t)
    victim = topo.workers.pop(0)
    victim.kill()
    victim.wait(10)
    t_end = time.monotonic()
    at(t + 5)
    topo.workers.append(start_role(_worker_args(cfg, topo.db),
                                   work / "worker-new.stderr", env,
                                   b"cranetwin worker ready"))
    out.append({"fault": "worker", "how": f"SIGKILL of twin worker 1 of {cfg.workers} (the "
                "others take its partitions); a new worker started 5 s later",
                "start": t_start, "end": t_end})
    t += cfg.fault_gap_s
    t_start = at(t)
    topo.nats.kill()
    topo.nats.start()
    out.append({"fault": "nats", "how": "SIGKILL of the private nats-server -js, restarted at "
                "once on its port and store directory", "start": t_start,
                "end": time.monotonic()})
    t += cfg.fault_gap_s
    t_start = at(t)
    proxy.cut()
    at(t + cfg.outage_s)
    proxy.restore()
    out.append({"fault": "postgresql", "how": f"every cranetwin process reaches PostgreSQL "
                f"through a TCP proxy; for {cfg.outage_s:g} s it closed every connection and "
                "refused new ones (the shared server itself kept running)",
                "start": t_start, "end": time.monotonic()})
    return out


def _fault_figures(cfg: FleetConfig, faults: list[dict[str, Any]],
                   lag: list[tuple[float, float]], t0: float) -> list[dict[str, Any]]:
    out = []
    for i, f in enumerate(faults):
        horizon = faults[i + 1]["start"] if i + 1 < len(faults) else np.inf
        before = [v for t, v in lag if t < f["start"]]
        after = [(t, v) for t, v in lag if f["start"] <= t < horizon]
        rec = next((t - f["end"] for t, v in after if t >= f["end"] and v < cfg.lag_target_s),
                   None)
        out.append({"fault": f["fault"], "how": f["how"],
                    "at_s": round(f["start"] - t0, 1),
                    "duration_s": round(f["end"] - f["start"], 1),
                    "lag_before_s": round(before[-1], 1) if before else None,
                    "lag_max_s": round(max(v for _, v in after), 1) if after else None,
                    "recover_seconds": None if rec is None else round(rec, 1),
                    "observed_s": round(min(horizon, after[-1][0] if after else f["end"])
                                        - f["end"], 1)})
    return out


def _bus_run(cfg: FleetConfig, pg: str, work: Path, faults: bool) -> dict[str, Any]:
    """A bus run (runs 2 and 3)."""
    from cranetwin.bench.chaos import TcpProxy

    env = _env(cfg)
    seconds = cfg.faults_s if faults else cfg.baseline_s
    plan = SenderPlan(cfg.machines, cfg.rate_hz, seconds, cfg.batch_samples,
                      cfg.sender_processes)
    with fresh_database(pg, "faults" if faults else "base") as url:
        register_machines(url, cfg.machines)
        proxy = TcpProxy(pg_target(url))
        purl = via_proxy(url, proxy.port)
        topo = _start(cfg, purl, work, env)
        sampler = Sampler(url, cfg.machines, time.time())
        senders = None
        fault_log: list[dict[str, Any]] = []
        try:
            sampler.track("ingest", topo.ingest.pid)
            for w in topo.writers:
                sampler.track("storage", w.pid)
            for w in topo.workers:
                sampler.track("worker", w.pid)
            sampler.track("nats", topo.nats.pids[0])
            (work / "senders").mkdir()
            sampler.poll_cpu()
            cpu0 = {r: sampler.cpu_seconds(r) for r in ("ingest", "storage", "worker", "nats")}
            senders = Senders(plan, ("127.0.0.1", topo.port), work / "senders", env)
            t0 = time.monotonic()  # every sender is streaming (its ready line)
            sampler.stream_start_s = time.time()
            sampler.lag_until_s = sampler.stream_start_s + seconds
            sampler.start()

            def at(t: float) -> float:
                time.sleep(max(0.0, t0 + t - time.monotonic()))
                return time.monotonic()

            if faults:
                fault_log = _faults(cfg, topo, proxy, work, env, at)
                sampler.track("worker", topo.workers[-1].pid)
                sampler.track("nats", topo.nats.pids[-1])
            drained = senders.wait(seconds + plan.drain_s + 60)
            sent = sum(r["samples"] for r in senders.results())
            end = time.monotonic() + 120
            while sampler.stored < sent and time.monotonic() < end:
                time.sleep(0.5)
            t_stored = time.monotonic()
            sampler.stop()
            cpu = {r: round(sampler.cpu_seconds(r) - cpu0[r], 2) for r in cpu0}
        finally:
            if senders is not None:
                senders.kill()
            _stop(topo)
            proxy.close()
            sampler.stop()
        counts = _readback(url, plan, senders.results())
    io_cpu = cpu["ingest"] + cpu["storage"]
    lat = sampler.latencies
    res: dict[str, Any] = {
        "data_seconds": seconds, "drained": drained,
        "seconds_to_stored": round(t_stored - t0, 1), **counts,
        "cpu_seconds": cpu,
        "samples_per_second_per_core": round(counts["stored"] / io_cpu) if io_cpu > 0 else None,
        "latency_p50_s": _pct(lat, 50), "latency_p95_s": _pct(lat, 95),
        "latency_windows_seen": len(lat),
        "lag_max_s": round(max((v for _, v in sampler.lag), default=0.0), 1),
        "lag_p50_s": _pct([v for _, v in sampler.lag], 50),
    }
    if faults:
        res["faults"] = _fault_figures(cfg, fault_log, sampler.lag, t0)
    return res


def run_fleet(cfg: FleetConfig, with_faults: bool, pg: str = PG_DEFAULT) -> dict[str, Any]:
    """The three runs; returns the figures (module docstring)."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        t = time.monotonic()
        (work / "direct").mkdir()
        direct = _direct(cfg, pg, work / "direct")
        (work / "base").mkdir()
        base = _bus_run(cfg, pg, work / "base", faults=False)
        main = base
        if with_faults:
            (work / "faults").mkdir()
            main = _bus_run(cfg, pg, work / "faults", faults=True)
        total_s = time.monotonic() - t
    d = direct["samples_per_second_per_core"]

    def ratio(run: dict[str, Any]) -> float | None:
        r = run["samples_per_second_per_core"]
        return None if not (r and d) else round(r / d, 3)

    base["per_core_ratio_vs_direct"] = ratio(base)
    faults = main.get("faults", [])
    recs = [f["recover_seconds"] for f in faults]
    out: dict[str, Any] = {
        "machines": cfg.machines, "faults_injected": with_faults,
        **{k: main[k] for k in ("sent", "stored", "lost", "doubled", "acked_not_stored",
                                "machines_mismatched")},
        "samples_per_second_per_core": main["samples_per_second_per_core"],
        "per_core_ratio_vs_direct": ratio(main),
        "direct_samples_per_second_per_core": d,
        "latency_p50_s": main["latency_p50_s"], "latency_p95_s": main["latency_p95_s"],
        "recover_seconds_max": (None if any(r is None for r in recs) else
                                max(recs, default=0.0)),
        "faults": faults,
        "baseline": base, "direct": direct,
        "settings": asdict(cfg) | {"faults_data_s": cfg.faults_s},
        "targets": {"lost": 0, "doubled": 0, "lag_below_s": cfg.lag_target_s,
                    "recover_within_s": 60.0, "per_core_ratio_vs_direct_min": 0.7},
        "seconds": round(total_s, 1), "load_average_1min": round(os.getloadavg()[0], 2),
    }
    if with_faults:
        out["faults_run"] = {k: v for k, v in main.items() if k != "faults"}
    return out


def fleet(
    machines: int = typer.Option(1000, help="Simulated machines (11 channels each)."),
    faults: bool = typer.Option(False, "--faults", help="Add the run with faults."),
    rate_hz: float = typer.Option(10.0, help="Samples per second per machine."),
    batch_samples: int = typer.Option(10, help="Samples per datagram."),
    sender_processes: int = typer.Option(2, min=1, help="Sender processes."),
    daemons: int = typer.Option(2, min=1, help="Ingest processes (--processes N)."),
    writers: int = typer.Option(2, min=1, help="Storage writers (bus partitions split)."),
    workers: int = typer.Option(2, min=1, help="Twin workers (--partitions auto)."),
    window_s: float = typer.Option(4.0, help="Twin worker window [s]."),
    direct_s: float = typer.Option(20.0, help="Data seconds of the direct run."),
    baseline_s: float = typer.Option(40.0, help="Data seconds of the run without faults."),
    warm_s: float = typer.Option(25.0, help="Seconds before the first fault."),
    fault_gap_s: float = typer.Option(30.0, help="Seconds between fault starts."),
    outage_s: float = typer.Option(30.0, help="Seconds PostgreSQL is cut off."),
    tail_s: float = typer.Option(45.0, help="Data seconds after the last fault."),
    pg: str = typer.Option(PG_DEFAULT, help="PostgreSQL server (a database is made per run)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """The fleet path (senders → ingest → JetStream → storage writers → PostgreSQL → twin
    workers) with faults: lost/doubled, per-core vs the direct path, latency, lag, recovery."""
    cfg = FleetConfig(machines=machines, rate_hz=rate_hz, batch_samples=batch_samples,
                      sender_processes=sender_processes, daemons=daemons, writers=writers,
                      workers=workers, window_s=window_s, direct_s=direct_s,
                      baseline_s=baseline_s, warm_s=warm_s, fault_gap_s=fault_gap_s,
                      outage_s=outage_s, tail_s=tail_s)
    emit(run_fleet(cfg, faults, pg), as_json)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("fleet")(fleet)
