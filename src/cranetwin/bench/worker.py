"""``cranetwin bench worker``: CPU per machine and pass of the twin worker on PostgreSQL, at the
fleet bench's settings.

Input: ``machines`` machines of the fleet senders' data (:class:`cranetwin.ingest.sender.
SyntheticSource` over the built-in crane's layout, 2-quantum noise, seeded by the wire id),
stored as the ingest daemon stores them (blocks of ``batch_samples`` samples) in a fresh
database ``h_fleetbench_worker_…`` (dropped at the end). One :class:`~cranetwin.service.worker.
TwinWorker` with the fleet bench's settings (windows of 4 s, settle 1 s, replay margin 1 s,
``worker_threads``, no roll-up; ``window_s``, ``settle_s``, ``margin_s`` change them: the
settings' defaults are 60, 2 and 2 s) first catches up ``history_s`` of data (not timed: smoothing
choices, kernels and caches are warm after it). Then, for each step size of ``steps_s``,
``passes`` times: every machine gets ``step_s`` more seconds of data (not timed), and one
:meth:`TwinWorker.run_once` is timed.

Figures per step size (``runs``): ``cpu_ms_per_machine_pass`` — median over the passes of the
process's CPU time (``time.process_time``: every thread of the worker, not PostgreSQL's) per
machine in the pass, with every pass listed; ``wall_ms_per_machine_pass`` likewise;
``statements_per_machine_pass`` (SQL statements the worker sent, counted by a
``before_cursor_execute`` hook); ``windows_per_machine_pass``; ``unreplayed`` (spans the
replay refused, summed over the passes: must be 0); ``cpu_ms_per_machine_minute`` — the
CPU time of all the step's passes per machine and minute of data added (what a worker polling
every ``step_s`` spends per machine-minute: e.g. ``--steps 1 --passes 60`` at 60-s windows is
the settings' defaults, one pass with a window ready and 59 without). With two or more step sizes,
``fixed_ms_per_machine_pass`` and ``ms_per_machine_second`` are the least-squares line through
the medians (cost = fixed + per-second × step). ``loadavg`` is the 1-min load average at the
start and the end of the timed passes (the host is shared).

Run it on the old and the new code alternately for an A/B figure: the module uses only the
worker's public interface.
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit

PG_DEFAULT = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


def _source_base(rate_hz: float, seconds: float, wire_id: int) -> Any:
    """``seconds`` of the fleet senders' data of machine ``wire_id`` as one recording."""
    from cranetwin.bench.ingest import patu_layout
    from cranetwin.ingest.sender import SyntheticSource
    from cranetwin.protocol import MachineKey
    from cranetwin.samples import SampleArrays

    layout = patu_layout()
    key = MachineKey(wire_id, f"fleet-{wire_id}", b"k" * 32, layout)
    n = int(round(seconds * rate_hz))
    values = SyntheticSource(key, 1.0 / rate_hz, seed=wire_id).read(0, n)
    return SampleArrays(key.machine_id, np.arange(n) / rate_hz,
                        tuple(ch.name for ch in layout.channels), values,
                        period_ns=int(round(1e9 / rate_hz)))


def run(machines: int = 100, rate_hz: float = 10.0, history_s: float = 70.0,
        steps_s: tuple[float, ...] = (8.0,), passes: int = 9, window_s: float = 4.0,
        settle_s: float = 1.0, margin_s: float = 1.0, threads: int = 4, batch_samples: int = 20,
        pg: str = PG_DEFAULT, profile: str | None = None) -> dict[str, Any]:
    """Run the benchmark; return its figures (see the module docstring).

    Args:
        profile: Write a cProfile of the timed passes (CPU time, the worker's own thread:
            use ``threads=1``) to this file.
    """
    import cProfile

    from sqlalchemy import event

    from cranetwin.bench.fleet_parts import create_database, drop_database
    from cranetwin.model import load_machine
    from cranetwin.service.backend import Backend
    from cranetwin.service.metrics import Metrics
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import tiled_blocks

    machine = load_machine("patu655")
    total_s = history_s + passes * sum(steps_s) + 10.0
    block_s = batch_samples / rate_hz
    t_origin = float(np.floor(time.time() / 60.0) * 60.0) - total_s - 60.0
    ids = [f"fleet-{w}" for w in range(1, machines + 1)]
    bases = {mid: _source_base(rate_hz, total_s, w) for w, mid in enumerate(ids, start=1)}
    seq = dict.fromkeys(ids, 0)
    url = create_database(pg, "worker")
    try:
        backend = Backend.open(url)
        for w, mid in enumerate(ids, start=1):
            backend.store.add_machine(mid, w, b"k" * 32)
        filled = 0.0

        def fill(seconds: float) -> None:
            nonlocal filled
            for mid in ids:
                bl = list(tiled_blocks(mid, machine, t_origin + filled, seconds, block_s,
                                       base=bases[mid], seq0=seq[mid], origin_s=t_origin))
                seq[mid] += len(bl)
                backend.store.write_blocks(bl)
            filled += seconds

        settings = Settings(database_url=url, worker_in_process=False,
                            worker_window_s=window_s, worker_settle_s=settle_s,
                            twin_margin_s=margin_s, worker_threads=threads, worker_rollup_s=0)
        metrics = Metrics()
        worker = TwinWorker(backend, settings, metrics)
        fill(history_s)
        while worker.run_once():
            pass
        statements = [0]

        def count(*_: Any) -> None:
            statements[0] += 1

        event.listen(backend.store.engine, "before_cursor_execute", count)
        prof = cProfile.Profile(time.process_time) if profile else None
        load0 = os.getloadavg()[0]
        runs: list[dict[str, Any]] = []
        for step in steps_s:
            cpu, wall, stmts, wins = [], [], [], []
            unreplayed0 = _errors(metrics)
            for _ in range(passes):
                fill(step)
                statements[0] = 0
                c0, w0 = time.process_time(), time.perf_counter()
                if prof is not None:
                    prof.enable()
                n = worker.run_once()
                if prof is not None:
                    prof.disable()
                cpu.append((time.process_time() - c0) * 1e3 / machines)
                wall.append((time.perf_counter() - w0) * 1e3 / machines)
                stmts.append(statements[0] / machines)
                wins.append(n / machines)
            runs.append({
                "step_s": step,
                "cpu_ms_per_machine_pass": round(statistics.median(cpu), 2),
                "cpu_ms_per_machine_pass_runs": [round(x, 2) for x in cpu],
                "wall_ms_per_machine_pass": round(statistics.median(wall), 2),
                "statements_per_machine_pass": round(statistics.median(stmts), 2),
                "windows_per_machine_pass": round(statistics.median(wins), 2),
                "unreplayed": int(_errors(metrics) - unreplayed0),
                "cpu_ms_per_machine_minute": round(sum(cpu) * 60.0 / (passes * step), 2),
            })
        load1 = os.getloadavg()[0]
        if prof is not None and profile:
            prof.dump_stats(profile)
        event.remove(backend.store.engine, "before_cursor_execute", count)
        lag = max(filled - (p.watermark_s - t_origin) for p in
                  (backend.progress(m) for m in ids) if p is not None)
        backend.close()
    finally:
        drop_database(pg, url)
    out: dict[str, Any] = {
        "machines": machines, "rate_hz": rate_hz, "window_s": window_s, "settle_s": settle_s,
        "margin_s": margin_s, "worker_threads": threads, "passes": passes,
        "history_s": history_s, "runs": runs, "lag_at_end_s": round(lag, 1),
        "loadavg": [round(load0, 2), round(load1, 2)],
    }
    if len(steps_s) >= 2:
        x = np.array([r["step_s"] for r in runs])
        y = np.array([r["cpu_ms_per_machine_pass"] for r in runs])
        slope, icept = np.polyfit(x, y, 1)
        out["fixed_ms_per_machine_pass"] = round(float(icept), 2)
        out["ms_per_machine_second"] = round(float(slope), 3)
    return out


def _errors(metrics: Any) -> float:
    """Spans the worker could not replay so far (the ``worker_errors`` counter, all machines)."""
    total = 0.0
    for fam in metrics.worker_errors.collect():
        for s in fam.samples:
            if s.name.endswith("_total"):
                total += s.value
    return total


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("worker")
    def worker_cmd(
        machines: int = typer.Option(100, min=1, help="Machines the worker processes."),
        rate_hz: float = typer.Option(10.0, help="Samples per second per machine."),
        history_s: float = typer.Option(70.0, help="Seconds of data caught up before timing."),
        steps: str = typer.Option("8", help="Seconds of data added per machine before each "
                                            "timed pass; several (comma-separated) give the "
                                            "fixed and per-second cost."),
        passes: int = typer.Option(9, min=1, help="Timed passes per step size."),
        window_s: float = typer.Option(4.0, help="Worker window [s] (the fleet bench's; "
                                                 "the default setting is 60)."),
        settle_s: float = typer.Option(1.0, help="worker_settle_s (the fleet bench's; the "
                                                 "default setting is 2)."),
        margin_s: float = typer.Option(1.0, help="twin_margin_s (the fleet bench's; the "
                                                 "default setting is 2)."),
        threads: int = typer.Option(4, min=1, help="worker_threads (the fleet bench's)."),
        batch_samples: int = typer.Option(20, min=1, help="Samples per stored block (the "
                                                          "daemon's batch)."),
        pg: str = typer.Option(PG_DEFAULT, help="PostgreSQL server (a database is made)."),
        profile: str = typer.Option("", help="Write a cProfile (CPU time) of the timed passes "
                                             "to this file (use --threads 1)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    ) -> None:
        """CPU per machine and pass of the twin worker on PostgreSQL (fleet bench settings)."""
        out = run(machines, rate_hz, history_s, tuple(float(s) for s in steps.split(",")),
                  passes, window_s, settle_s, margin_s, threads=threads,
                  batch_samples=batch_samples, pg=pg,
                  profile=profile or None)
        emit(out, as_json)
