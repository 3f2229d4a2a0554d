"""``cranetwin bench fleet``: the whole fleet path on PostgreSQL + NATS, with and without faults.

Every role is a real process (:mod:`cranetwin.bench.fleet_parts`): journaled sender processes
(:func:`cranetwin.ingest.sender.run_sender`, many machines per process, one journal each, not
synced to disk: the bench kills no sender), ``cranetwin ingest --processes N --bus``,
``cranetwin store-writer --partitions`` (the bus partitions split between the writers), ``cranetwin
worker --partitions auto --of P`` (M workers), a ``nats-server -js`` of the bench's own on a free
port, and a fresh database ``h_fleetbench_…`` per run (dropped at the end). Every cranetwin
process of a bus run reaches PostgreSQL through a TCP proxy that the bench can cut. The three
runs' processes are started side by side before the first one streams
(:mod:`cranetwin.bench.fleet_setup`); then, one after the other:

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
  rollup runs where a deployment runs it (the daemon or the storage writer, every 30 s); left
  out, every twin worker's pass began by rolling up all machines and got to no window.
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

import contextlib
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit
from cranetwin.bench.fleet_parts import PG_DEFAULT, Sampler, children
from cranetwin.bench.fleet_setup import BusEnv, DirectEnv, FleetConfig, readback


def _pct(x: list[float], q: float) -> float | None:
    return None if not x else round(float(np.percentile(x, q)), 2)


def _direct(e: DirectEnv) -> dict[str, Any]:
    """Run 1: the single-process direct path."""
    assert e.senders is not None
    plan = e.cfg.plan(e.seconds)
    e.register()
    sampler = Sampler(e.db, e.cfg.machines, time.time())
    sampler.track("ingest", e.daemon.pid)
    sampler.poll_cpu()
    cpu0 = sampler.cpu_seconds("ingest")
    t0 = time.monotonic()
    e.senders.go()
    drained = e.senders.wait(e.seconds + plan.drain_s + 60)  # acked = committed: all stored
    sampler.poll_cpu()
    cpu = sampler.cpu_seconds("ingest") - cpu0
    seconds = time.monotonic() - t0
    e.close_processes()
    counts = readback(e.db, plan, e.senders.results())
    return {"data_seconds": e.seconds, "seconds": round(seconds, 1), "drained": drained,
            "ingest_cpu_seconds": round(cpu, 2),
            "samples_per_second_per_core": round(counts["stored"] / cpu) if cpu > 0 else None,
            **counts}


def _faults(e: BusEnv, sampler: Sampler, t0: float) -> list[dict[str, Any]]:
    """The fault schedule (module docstring); each fault's name, how, start and end
    (monotonic)."""
    cfg = e.cfg
    assert e.nats is not None

    def at(t: float) -> float:
        time.sleep(max(0.0, t0 + t - time.monotonic()))
        return time.monotonic()

    out: list[dict[str, Any]] = []
    t = cfg.warm_s
    start = at(t)
    kids = children(e.ingest.pid)
    if kids:
        os.kill(kids[0], 9)
    out.append({"fault": "daemon", "how": f"SIGKILL of ingest process 1 of {cfg.daemons} "
                "(cranetwin ingest --processes restarts it on its socket)",
                "start": start, "end": time.monotonic(), "done": bool(kids)})
    t += cfg.fault_gap_s
    start = at(t)
    victim = e.workers[0]
    victim.kill()
    victim.wait(10)
    end = time.monotonic()
    at(t + 5)
    sampler.track("worker", e.start_worker().pid)
    out.append({"fault": "worker", "how": f"SIGKILL of twin worker 1 of {cfg.workers} (the "
                "others take its partitions); a new worker process started 5 s later",
                "start": start, "end": end, "done": True})
    t += cfg.fault_gap_s
    start = at(t)
    e.nats.kill()
    e.nats.start()
    sampler.track("nats", e.nats.pids[-1])
    out.append({"fault": "nats", "how": "SIGKILL of the private nats-server -js, restarted at "
                "once on its port and store directory", "start": start,
                "end": time.monotonic(), "done": True})
    t += cfg.fault_gap_s
    start = at(t)
    e.proxy.cut()
    at(t + cfg.outage_s)
    e.proxy.restore()
    out.append({"fault": "postgresql", "how": f"every cranetwin process reaches PostgreSQL "
                f"through a TCP proxy; for {cfg.outage_s:g} s it closed every connection and "
                "refused new ones (the shared server itself kept running)",
                "start": start, "end": time.monotonic(), "done": True})
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
        out.append({"fault": f["fault"], "how": f["how"], "injected": f["done"],
                    "at_s": round(f["start"] - t0, 1),
                    "duration_s": round(f["end"] - f["start"], 1),
                    "lag_before_s": round(before[-1], 1) if before else None,
                    "lag_max_s": round(max(v for _, v in after), 1) if after else None,
                    "recover_seconds": None if rec is None else round(rec, 1),
                    "observed_s": round((after[-1][0] if after else f["end"]) - f["end"], 1)})
    return out


def _bus_run(e: BusEnv, faults: bool) -> dict[str, Any]:
    """Runs 2 and 3."""
    assert e.senders is not None and e.nats is not None
    plan = e.cfg.plan(e.seconds)
    e.register()
    sampler = Sampler(e.db, e.cfg.machines, time.time())
    sampler.track("ingest", e.ingest.pid)
    for w in e.writers:
        sampler.track("storage", w.pid)
    for w in e.workers:
        sampler.track("worker", w.pid)
    sampler.track("nats", e.nats.pids[0])
    fault_log: list[dict[str, Any]] = []
    try:
        sampler.poll_cpu()
        cpu0 = {r: sampler.cpu_seconds(r) for r in ("ingest", "storage", "worker", "nats")}
        t0 = time.monotonic()
        sampler.stream_start_s = time.time()
        sampler.lag_until_s = sampler.stream_start_s + e.seconds
        e.senders.go()
        sampler.start()
        if faults:
            fault_log = _faults(e, sampler, t0)
        drained = e.senders.wait(e.seconds + plan.drain_s + 60)
        sent = sum(r["samples"] for r in e.senders.results())
        end = time.monotonic() + 120
        while sampler.stored < sent and time.monotonic() < end:
            time.sleep(0.5)
        t_stored = time.monotonic()
    finally:
        sampler.stop()
        e.stop_processes()
    cpu = {r: round(sampler.cpu_seconds(r) - cpu0[r], 2) for r in cpu0}
    counts = readback(e.db, plan, e.senders.results())
    io_cpu = cpu["ingest"] + cpu["storage"]
    lat = sampler.latencies
    res: dict[str, Any] = {
        "data_seconds": e.seconds, "drained": drained,
        "seconds_to_stored": round(t_stored - t0, 1), **counts, "cpu_seconds": cpu,
        "samples_per_second_per_core": round(counts["stored"] / io_cpu) if io_cpu > 0 else None,
        "latency_p50_s": _pct(lat, 50), "latency_p95_s": _pct(lat, 95),
        "latency_windows_seen": len(lat),
        "lag_max_s": round(max((v for _, v in sampler.lag), default=0.0), 1),
        "lag_p50_s": _pct([v for _, v in sampler.lag], 50),
    }
    if faults:
        res["faults"] = _fault_figures(e.cfg, fault_log, sampler.lag, t0)
    return res


def run_fleet(cfg: FleetConfig, with_faults: bool, pg: str = PG_DEFAULT,
              baseline: bool = True) -> dict[str, Any]:
    """The runs (module docstring); returns the figures. ``baseline`` False leaves run 2 out
    when run 3 is made (tests on a slow host; the command always makes it)."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        work = Path(tmp)
        t = time.monotonic()
        baseline = baseline or not with_faults
        envs: list[DirectEnv | BusEnv] = [DirectEnv(cfg, pg, work / "direct", cfg.direct_s)]
        if baseline:
            envs.append(BusEnv(cfg, pg, work / "base", cfg.baseline_s, "base"))
        if with_faults:
            envs.append(BusEnv(cfg, pg, work / "faults", cfg.faults_s, "faults"))
        with ThreadPoolExecutor(len(envs)) as pool:
            futures = [pool.submit(x.open) for x in envs]
        for x, f in zip(envs, futures, strict=True):
            if f.exception() is None:
                stack.callback(x.close)
        for f in futures:
            f.result()  # raises the first failure (the others are closed on the way out)
        setup_s = time.monotonic() - t
        assert isinstance(envs[0], DirectEnv)
        direct = _direct(envs[0])
        runs = [_bus_run(e, faults=e.tag == "faults") for e in envs[1:] if isinstance(e, BusEnv)]
        base: dict[str, Any] | None = runs[0] if baseline else None
        main = runs[-1]
        total_s = time.monotonic() - t
    d = direct["samples_per_second_per_core"]

    def ratio(run: dict[str, Any]) -> float | None:
        r = run["samples_per_second_per_core"]
        return None if not (r and d) else round(r / d, 3)

    if base is not None:
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
        "settings": {**cfg.__dict__, "faults_data_s": cfg.faults_s},
        "targets": {"lost": 0, "doubled": 0, "lag_below_s": cfg.lag_target_s,
                    "recover_within_s": 60.0, "per_core_ratio_vs_direct_min": 0.7},
        "setup_seconds": round(setup_s, 1), "seconds": round(total_s, 1),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    if with_faults:
        out["faults_run"] = {k: v for k, v in main.items() if k != "faults"}
    return out


def fleet(
    machines: int = typer.Option(1000, help="Simulated machines (11 channels each)."),
    faults: bool = typer.Option(False, "--faults", help="Add the run with faults."),
    rate_hz: float = typer.Option(10.0, help="Samples per second per machine."),
    batch_samples: int = typer.Option(20, help="Samples per datagram."),
    sender_processes: int = typer.Option(2, min=1, help="Sender processes."),
    daemons: int = typer.Option(2, min=1, help="Ingest processes (--processes N)."),
    writers: int = typer.Option(2, min=1, help="Storage writers (bus partitions split)."),
    workers: int = typer.Option(2, min=1, help="Twin workers (--partitions auto)."),
    worker_threads: int = typer.Option(4, min=1, max=32,
                                       help="Machines each twin worker replays at once."),
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
                      workers=workers, worker_threads=worker_threads, window_s=window_s,
                      direct_s=direct_s,
                      baseline_s=baseline_s, warm_s=warm_s, fault_gap_s=fault_gap_s,
                      outage_s=outage_s, tail_s=tail_s)
    emit(run_fleet(cfg, faults, pg), as_json)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("fleet")(fleet)
