"""``cranetwin bench analytics``: a 30-day load-history report of one crane.

Input: 30 days of 8-hour shifts at 100 Hz (240 h, 86.4 M samples per channel) of synthetic load
histories (:mod:`cranetwin.testing.histories`: 3 cylinder forces, 4 joint moments, 4 joint
positions and velocities, payload, reach, height, 3 rod positions and velocities, 6 pressures),
generated one hour at a time; generation is timed separately and not counted.
Timed (``wall_seconds``, ``cpu_seconds``): :meth:`AnalyticsState.update` on every chunk — rainflow
of the 7 load channels, events, work cycles, usage — and the final :meth:`~AnalyticsState.report`
(spectra, Miner damage, classification, duty record). ``report_pdf_seconds``: writing the PDF
(null with ``--no-pdf``).
``samples_per_second``: samples per channel / wall_seconds.
Baseline in the same run: a pure-Python rainflow in the style of the ``rainflow`` package
(per-sample reversal generator with the same classes, then a stack count), and fatpack's own
``find_reversals`` + ``find_rainflow_cycles`` (pure-Python cycle loop), both on the 7 load channels
of ``baseline_hours`` of the same data, scaled to the full period, in CPU seconds (the machine
is shared, so wall time depends on the load). ``speedup`` = scaled pure-Python rainflow of the
load channels alone / CPU seconds of our whole analysis.
"""

from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.analytics import AnalyticsState, LoadHistory, load_channels
from cranetwin.analytics.state import default_class_widths
from cranetwin.bench import emit
from cranetwin.errors import MissingExtraError
from cranetwin.model import Machine, load_machine
from cranetwin.testing.histories import SyntheticCrane


def _peak_rss_mib() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def _fatpack() -> Any:
    """The fatpack module (the baseline), or MissingExtraError: it is a ``dev`` dependency."""
    try:
        import fatpack
    except ImportError as exc:
        raise MissingExtraError("dev", "the analytics benchmark's fatpack baseline") from exc
    return fatpack


def _py_rainflow(y: list[float], width: float) -> int:
    """Pure-Python rainflow: classify, find reversals sample by sample, count with a stack."""
    count = 0
    stack: list[float] = []
    last = None
    direction = 0
    for v in y:
        lv = (v // width) * width
        if last is None:
            last = lv
            stack.append(lv)
            continue
        if lv == last:
            continue
        d = 1 if lv > last else -1
        if direction and d != direction:
            stack.append(last)
            while len(stack) >= 4:
                s0, s1, s2, s3 = stack[-4:]
                r1, r2, r3 = abs(s1 - s0), abs(s2 - s1), abs(s3 - s2)
                if r2 <= r1 and r2 <= r3:
                    count += 1
                    del stack[-3:-1]
                else:
                    break
        direction, last = d, lv
    return count


def _baseline(machine: Machine, crane: SyntheticCrane, hours: float,
              rate_hz: float) -> dict[str, float]:
    t0, _ = crane.shift_bounds(0)
    h = crane.history(t0 + np.arange(int(hours * 3600 * rate_hz)) / rate_hz)
    widths = default_class_widths(machine)
    chans = [h.load_channel(machine, c) for c in load_channels(machine)]
    clock = time.process_time  # CPU time: the machine is shared, wall time varies with load
    start = clock()
    for ch, c in zip(chans, load_channels(machine), strict=True):
        _py_rainflow(ch.tolist(), widths[c])
    py = clock() - start
    fatpack = _fatpack()
    start = clock()
    for ch, c in zip(chans, load_channels(machine), strict=True):
        k = int(np.ceil((ch.max() - ch.min()) / widths[c])) + 1
        rev, _ = fatpack.find_reversals(ch, k=k)
        fatpack.find_rainflow_cycles(rev)
    fp = clock() - start
    state = AnalyticsState(machine)
    start = clock()
    for c in load_channels(machine):
        state.counters[c].update(h.load_channel(machine, c))
        state.counters[c].snapshot()
    ours = clock() - start
    return {"py": py, "fatpack": fp, "ours": ours}


def run(days: int = 30, rate_hz: float = 100.0, baseline_hours: float = 0.25,
        pdf: bool = True) -> dict[str, Any]:
    """Run the benchmark; return its figures (see the module docstring).

    Raises:
        MissingExtraError: fatpack (a ``dev`` dependency) is not installed; checked first.
    """
    _fatpack()
    machine = load_machine("patu655")
    crane = SyntheticCrane(machine, seed=0, days=days)
    state = AnalyticsState(machine)
    gen = wall = cpu = 0.0
    n = 0
    it = crane.chunks(rate_hz, 3600.0)
    while True:
        g0 = time.perf_counter()
        h: LoadHistory | None = next(it, None)
        gen += time.perf_counter() - g0
        if h is None:
            break
        w0, c0 = time.perf_counter(), time.process_time()
        state.update(h)
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
        n += h.n
        del h
    w0, c0 = time.perf_counter(), time.process_time()
    rep = state.report()
    wall += time.perf_counter() - w0
    cpu += time.process_time() - c0
    pdf_s: float | None = None
    pdf_cpu: float | None = None
    if pdf:
        from cranetwin.reports import write

        with tempfile.TemporaryDirectory() as d:
            p0, c0 = time.perf_counter(), time.process_time()
            write(rep, machine, "pdf", Path(d) / "r.pdf", "bench: synthetic shifts")
            pdf_s, pdf_cpu = time.perf_counter() - p0, time.process_time() - c0
    base = _baseline(machine, crane, baseline_hours, rate_hz)
    hours = n / rate_hz / 3600.0
    scale = hours / baseline_hours
    worst = max(rep.life, key=lambda e: e.damage)
    return {
        "hours": round(hours, 3),
        "days": days,
        "rate_hz": rate_hz,
        "samples_per_channel": n,
        "load_channels": len(load_channels(machine)),
        "wall_seconds": round(wall, 3),
        "cpu_seconds": round(cpu, 3),
        "samples_per_second": round(n / wall),
        "cpu_samples_per_second": round(n / cpu),
        # None (JSON null) without --pdf: not measured
        "report_pdf_seconds": None if pdf_s is None else round(pdf_s, 3),
        "report_pdf_cpu_seconds": None if pdf_cpu is None else round(pdf_cpu, 3),
        "report_total_seconds": round(wall + (pdf_s or 0.0), 3),
        "report_total_cpu_seconds": round(cpu + (pdf_cpu or 0.0), 3),
        "generate_seconds_not_counted": round(gen, 3),
        "peak_rss_mib": round(_peak_rss_mib(), 1),
        "baseline_hours_measured": baseline_hours,
        "baseline_pure_python_rainflow_scaled_cpu_seconds": round(base["py"] * scale, 2),
        "baseline_fatpack_rainflow_scaled_cpu_seconds": round(base["fatpack"] * scale, 2),
        "ours_rainflow_only_scaled_cpu_seconds": round(base["ours"] * scale, 2),
        "rainflow_speedup_vs_pure_python": round(base["py"] / base["ours"], 1),
        "rainflow_speedup_vs_fatpack": round(base["fatpack"] / base["ours"], 1),
        "speedup": round(base["py"] * scale / cpu, 2),
        "work_cycles": len(rep.cycles),
        "events": len(rep.events),
        "kp": round(rep.classification.kp, 4) if rep.classification else None,
        "max_damage": worst.damage,
    }


def run_stored(days: int = 30, shift_h: float = 1.0, rate_hz: float = 100.0,
               direct_hours: float = 2.0, url: str | None = None,
               export_runs: int = 3) -> dict[str, Any]:
    """The stored-data benchmark (``--stored``): reports of any range from what the twin
    worker stored.

    Data through the real pipeline: ``days`` daily shifts of ``shift_h`` hours (06:00 UTC on)
    of exact sensor samples (:func:`cranetwin.testing.blocks.kinematic_samples`, 120 s of
    motion with lifts, tiled) written as sample blocks with ``Store.write_blocks`` (what the
    ingest writer calls), then processed by :class:`~cranetwin.service.worker.TwinWorker` (each
    minute replayed, derived summaries, events and the minute's analytics part stored, hours
    and days rolled up). Timed: ``write_seconds`` and ``worker_seconds`` (not part of a
    report); ``report_<days>d_seconds`` — the API's analytics of the whole span
    (:func:`cranetwin.service.analytics.analytics_report`: stored parts merged); over
    ``direct_hours`` of the first shift (from 06:17:30, or a quarter into a shorter shift, so
    both edges are partial minutes),
    the same merged report (``merged_range_seconds``) and the direct baseline that replays
    every minute of the range (``direct_range_seconds``), ``speedup_vs_direct`` their ratio
    and ``equal_to_direct`` whether they agree (spectra, damage, events, work cycles);
    the raw-sample export rates of the whole span in-process (:func:`_export_rates`) and as a
    user runs it (``export_runs`` times each; 0: not measured): downloaded over HTTP from a
    ``cranetwin serve`` process and written by ``cranetwin export``
    (:mod:`cranetwin.bench.export`). ``export_samples_per_second`` is the HTTP Parquet download
    (wall, median) when measured, else the in-process Parquet export.
    """
    from cranetwin.service.analytics import analytics_report, direct_report
    from cranetwin.service.backend import Backend
    from cranetwin.service.replayer import Replayer
    from cranetwin.service.timerange import TimeRange
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    machine = load_machine("patu655")
    t0 = 1795392000.0  # 2026-11-22 00:00 UTC
    mid = "bench-crane"
    with tempfile.TemporaryDirectory() as d:
        b = Backend.open(url or f"sqlite:///{d}/bench.db")
        b.store.add_machine(mid, wire_id=4242, secret=b"b" * 32)
        base = kinematic_samples(machine, 120.0, rate_hz)
        w_s = 0.0
        seq = 0
        for day in range(days):
            start = t0 + day * 86400.0 + 6 * 3600.0
            blocks = list(tiled_blocks(mid, machine, start, shift_h * 3600.0 + 5.0, 1.0,
                                       base=base, seq0=seq, origin_s=t0))
            seq += len(blocks)
            a = time.perf_counter()
            b.store.write_blocks(blocks)
            w_s += time.perf_counter() - a
        replayer = Replayer()
        worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                            replayer=replayer, quiet_s=0.0)
        a = time.perf_counter()
        windows = 0
        while True:
            n = worker.catch_up(b.machine(mid))
            windows += n
            if n == 0:
                break
        worker_s = time.perf_counter() - a
        rng = TimeRange(t0, t0 + days * 86400.0)
        a, c = time.perf_counter(), time.process_time()
        rep = analytics_report(b, replayer, machine, mid, rng)
        rep_s, rep_cpu = time.perf_counter() - a, time.process_time() - c
        off = 6 * 3600.0 + min(1050.0, shift_h * 900.0 + 0.5)  # inside a minute
        short = TimeRange(t0 + off, t0 + off + direct_hours * 3600.0)
        a = time.perf_counter()
        merged = analytics_report(b, replayer, machine, mid, short)
        merged_s = time.perf_counter() - a
        a = time.perf_counter()
        direct = direct_report(b, replayer, machine, mid, short)
        direct_s = time.perf_counter() - a
        exp = _export_rates(b, machine, mid, rng, short)
        if export_runs:
            from cranetwin.bench.export import cli_export, served_export

            db_url = url or f"sqlite:///{d}/bench.db"
            key = b.create_key("fleet", "bench export")[1]
            exp |= served_export(db_url, key, mid, rng.t0_s, rng.t1_s, export_runs)
            exp |= cli_export(db_url, mid, rng.t0_s, rng.t1_s, export_runs)
            exp["export_samples_per_second"] = exp["export_http_parquet_samples_per_second"]
        b.close()
    assert rep is not None and merged is not None and direct is not None
    same = (all(np.array_equal(x.cycles.count, y.cycles.count)
                and np.array_equal(x.cycles.lower, y.cycles.lower)
                for x, y in zip(merged.spectra, direct.spectra, strict=True))
            and bool(np.allclose([e.damage for e in merged.life],
                                 [e.damage for e in direct.life], rtol=1e-12, atol=0.0))
            and [(e.kind, e.t_start) for e in merged.events]
            == [(e.kind, e.t_start) for e in direct.events]
            and [(c.t_grab, c.t_release) for c in merged.cycles]
            == [(c.t_grab, c.t_release) for c in direct.cycles])
    worst = max(rep.life, key=lambda e: e.damage)
    return {
        "days": days, "shift_h": shift_h, "rate_hz": rate_hz,
        "stored_hours": round(days * shift_h, 3), "samples": rep.n_samples,
        "write_seconds": round(w_s, 3), "worker_windows": windows,
        "worker_seconds": round(worker_s, 3),
        "worker_seconds_per_window": round(worker_s / max(windows, 1), 4),
        f"report_{days}d_seconds": round(rep_s, 3),
        f"report_{days}d_cpu_seconds": round(rep_cpu, 3),
        "direct_range_hours": direct_hours,
        "merged_range_seconds": round(merged_s, 3),
        "direct_range_seconds": round(direct_s, 3),
        "speedup_vs_direct": round(direct_s / merged_s, 1),
        "equal_to_direct": bool(same),
        "work_cycles": len(rep.cycles), "events": len(rep.events),
        "kp": round(rep.classification.kp, 4) if rep.classification else None,
        "max_damage": worst.damage,
        "remaining_years_worst": (None if not np.isfinite(worst.remaining_days)
                                  else round(worst.remaining_days / 365.25, 2)),
        **exp,
        "peak_rss_mib": round(_peak_rss_mib(), 1),
    }


def _export_rates(backend: Any, machine: Machine, mid: str, whole: Any,
                  short: Any) -> dict[str, Any]:
    """Raw-sample export rates in this process (:mod:`cranetwin.service.export`, as the API
    runs it: chunks read in a prefetch thread; no HTTP) of the whole stored span:
    ``export_inprocess_samples_per_second`` (Parquet, wall) and ``…_cpu_…`` (CPU of both
    threads), ``export_inprocess_csv_samples_per_second`` and
    ``export_read_samples_per_second`` (reading and decoding alone); baseline in the same run
    over the ``short`` range: the same Parquet writer fed by ``Store.read_samples`` (block by
    block), and the paged JSON samples route's service call (``samples_page``, 10000 samples a
    page) as it serves them."""
    import orjson

    from cranetwin.service import export as ex
    from cranetwin.service.queries import samples_page

    def run(fmt: str | None, rng: Any, reader: Any = None) -> tuple[int, float, float]:
        a, c = time.perf_counter(), time.process_time()
        n = 0
        chunks = reader(rng) if reader is not None else ex.prefetched(ex.raw_chunks(
            backend, machine, mid, rng, 100.0))

        def counted() -> Any:
            nonlocal n
            for ch in chunks:
                n += int(ch["t_s"].shape[0])
                yield ch

        if fmt is None:
            for _ in counted():
                pass
        else:
            for _ in ex.encode(counted(), ex.schema("raw", machine), fmt):
                pass
        return n, time.perf_counter() - a, time.process_time() - c

    def per_block(rng: Any) -> Any:
        names = [ch.name for ch in machine.channels]
        t = rng.t0_s
        while t < rng.t1_s:
            s = backend.read_samples(mid, t, min(rng.t1_s, t + 1000.0))
            if s.t_s.shape[0]:
                idx = {c: j for j, c in enumerate(s.channels)}
                yield {"t_ns": s.t_ns, "t_s": s.t_s, **{k: s.values[:, idx[k]] for k in names}}
            t += 1000.0

    n_pq, w_pq, c_pq = run("parquet", whole)
    n_csv, w_csv, _ = run("csv", whole)
    n_rd, w_rd, _ = run(None, whole)
    n_b, w_b, _ = run("parquet", short, per_block)
    a = time.perf_counter()
    n_json, cursor = 0, None
    while True:
        page = samples_page(backend, mid, short, 10_000, cursor, 100.0)
        orjson.dumps({"t": page.t, "values": page.values})
        n_json += len(page.t)
        cursor = page.next_cursor
        if cursor is None:
            break
    w_json = time.perf_counter() - a
    return {
        "export_samples": n_pq,
        "export_samples_per_second": round(n_pq / w_pq),
        "export_inprocess_samples_per_second": round(n_pq / w_pq),
        "export_inprocess_cpu_samples_per_second": round(n_pq / max(c_pq, 1e-9)),
        "export_inprocess_csv_samples_per_second": round(n_csv / w_csv),
        "export_read_samples_per_second": round(n_rd / w_rd),
        "baseline_export_per_block_read_samples_per_second": round(n_b / w_b),
        "baseline_json_pages_samples_per_second": round(n_json / w_json),
    }


def bench_analytics(
    days: int = typer.Option(30, help="Days of 8-hour shifts (--stored: of shifts of "
                             "--shift-h hours)."),
    rate_hz: float = typer.Option(100.0, help="Sample rate [Hz]."),
    baseline_hours: float = typer.Option(0.25, help="Hours of data the baselines run on."),
    pdf: bool = typer.Option(True, help="Also time writing the PDF report."),
    stored: bool = typer.Option(False, "--stored", help="Reports from stored data written "
                                "through the store and the twin worker (see run_stored)."),
    shift_h: float = typer.Option(1.0, help="--stored: hours of data per day."),
    direct_hours: float = typer.Option(2.0, help="--stored: range of the direct baseline [h]."),
    export_runs: int = typer.Option(3, help="--stored: downloads over HTTP and `cranetwin "
                                    "export` runs timed per format (0: none)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Time a 30-day load-history analysis (rainflow, damage, events, productivity)."""
    if stored:
        emit(run_stored(days, shift_h, rate_hz, direct_hours, export_runs=export_runs),
             as_json)
        return
    res = run(days, rate_hz, baseline_hours, pdf)
    emit(res, as_json)


def register(bench_app: typer.Typer) -> None:
    """Add ``cranetwin bench analytics``."""
    bench_app.command("analytics")(bench_analytics)
