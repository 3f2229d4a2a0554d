"""``cranetwin bench import``: a logger file into storage, from Parquet and from CSV, against
``pandas.read_csv`` + ``DataFrame.to_sql`` of the same CSV into the same kind of database.

Rates are throughput: the process first imports a one-minute file of each format untimed (the
first read loads pyarrow and its pandas shim, about 1.4 CPU s, which on a one-hour file was 70 %
of the Parquet path's time). What one command costs from a cold start is reported apart:
``parquet_command_seconds`` and ``parquet_command_cpu_seconds``, a fresh process that imports
the Parquet file and nothing else (interpreter, imports and all), the one ``peak_rss_mib`` is
read from (``csv_peak_rss_mib``: the same for the CSV file).

A sample is one instant of every channel (one row of the file, 11 channels of the PATU 655).
The file is synthetic (a random walk inside each channel's range, on its resolution, 100 Hz)
and written chunk by chunk. Each path imports into a fresh database (a temporary SQLite file,
or ``--db`` for PostgreSQL: a fresh machine id per path). ``peak_rss_mib`` is the peak
resident memory of a separate process that imports the Parquet file and nothing else. The
pandas baseline reads at most the file's first hour (:data:`PANDAS_MAX_ROWS`: it holds the whole
frame in memory), so ``speedup_vs_pandas`` is a ratio of rates. ``parquet_cpu_seconds`` (and
``parquet_cpu_samples_per_second``, ``csv_cpu_seconds``) is the CPU time of the process over the
timed import, every thread counted: on a shared machine the wall rates follow its load (reported
as ``load_average_1min`` before the timed imports), the CPU time much less. Targets: ≥ 1 M
samples/s from Parquet, ≥ 10× the pandas path, ≤ 1 GiB for a 24 h file (``--hours 24``).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit
from cranetwin.errors import MissingExtraError
from cranetwin.model import Machine, load_machine

RATE_HZ = 100
T0_S = 1_767_225_600  # 2026-01-01T00:00:00Z
CHUNK_ROWS = 360_000
PANDAS_MAX_ROWS = 360_000
"""The pandas baseline reads at most this many rows (one hour): it holds the whole frame in
memory (≈ 7 GB for a 24 h CSV), which would measure swapping, not parsing."""


def _chunks(machine: Machine, rows: int, seed: int = 0) -> Any:
    """(t_s, values) chunks of a random walk inside every channel's range, on its grid."""
    rng = np.random.default_rng(seed)
    chans = machine.channels
    lo = np.array([c.min for c in chans])
    hi = np.array([c.max for c in chans])
    res = np.array([c.resolution for c in chans])
    x = (lo + hi) / 2
    for a in range(0, rows, CHUNK_ROWS):
        n = min(CHUNK_ROWS, rows - a)
        steps = rng.normal(0.0, 1.0, (n, len(chans))) * (hi - lo) * 2e-3
        walk = x + np.cumsum(steps, axis=0)
        walk = lo + np.abs(np.mod(walk - lo, 2 * (hi - lo)) - (hi - lo))  # reflect into range
        walk = np.clip(np.rint(walk / res) * res, lo, hi)
        x = walk[-1]
        yield (T0_S + np.arange(a, a + n) / RATE_HZ), walk


def write_files(machine: Machine, rows: int, directory: Path) -> tuple[Path, Path]:
    """The same synthetic recording as CSV and as Parquet (zstd)."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("import", "bench import (Parquet)") from exc
    names = ["t_s", *(c.name for c in machine.channels)]
    csv_path, pq_path = directory / "rec.csv", directory / "rec.parquet"
    schema = pa.schema([pa.field(n, pa.float64()) for n in names])
    with csv_path.open("w", encoding="utf-8") as fh, pq.ParquetWriter(pq_path, schema,
                                                                      compression="zstd") as w:
        fh.write(",".join(names) + "\n")
        for t, v in _chunks(machine, rows):
            np.savetxt(fh, np.column_stack([t, v]), fmt=["%.2f", *(["%.6g"] * v.shape[1])],
                       delimiter=",")
            w.write_table(pa.table([t, *v.T], schema=schema))
    return csv_path, pq_path


def _import(path: Path, machine: Machine, url: str, machine_id: str,
            ) -> tuple[float, int, float]:
    """Wall time [s], samples stored, and CPU time of the process (every thread: reader,
    writer, Parquet decoding) [s] of one :func:`import_file` into ``url``."""
    from cranetwin.importer import import_file
    from cranetwin.storage import Store

    with Store.open(url) as store:
        store.add_machine(machine_id, abs(hash(machine_id)) % 2**31 + 1, b"b" * 32)
        t, c = time.perf_counter(), time.process_time()
        res = import_file(path, machine, store, machine_id)
        dt, cpu = time.perf_counter() - t, time.process_time() - c
    if res.report.rows_refused or res.refused:
        raise RuntimeError(f"bench import refused data: {res.report.summary()}")
    return dt, res.samples_stored, cpu


def _pandas(path: Path, url: str, rows: int) -> float | None:
    """Seconds for ``pandas.read_csv`` of the first ``rows`` rows + ``DataFrame.to_sql``."""
    try:
        import pandas as pd
    except ImportError:
        return None
    from sqlalchemy import create_engine

    engine = create_engine(url)
    t = time.perf_counter()
    df = pd.read_csv(path, nrows=rows)
    df.to_sql(f"pandas_{uuid.uuid4().hex[:8]}", engine, index=False, if_exists="fail")
    dt = time.perf_counter() - t
    engine.dispose()
    return dt


def _vm_hwm_mib() -> float:
    """This process's peak resident memory [MiB]: VmHWM, which (unlike ``ru_maxrss``) does not
    inherit the parent's peak across fork and exec."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child_peak_rss(path: Path, url: str) -> tuple[float, float, float]:
    """Peak RSS [MiB], wall time [s] and CPU time (user + system) [s] of a fresh process that
    imports ``path`` (and does nothing else)."""
    code = ("import sys; from pathlib import Path; from cranetwin.bench.importer import _import,"
            " _vm_hwm_mib; from cranetwin.model import load_machine;"
            " _import(Path(sys.argv[1]), load_machine('patu655'), sys.argv[2], sys.argv[3]);"
            " print(_vm_hwm_mib())")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, str(path), url,
                          f"rss-{uuid.uuid4().hex[:8]}"], check=True, capture_output=True,
                         text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return float(out.stdout.strip().splitlines()[-1]), wall, cpu


def _warm_up(machine: Machine, directory: Path, url: str | None) -> None:
    """Import a one-minute file of each format once, untimed (module and library loading), into
    ``url`` (None: a temporary SQLite file each)."""
    w = directory / "warm"
    w.mkdir()
    csv_path, pq_path = write_files(machine, 60 * RATE_HZ, w)
    for i, path in enumerate((pq_path, csv_path)):
        _import(path, machine, url or f"sqlite:///{w / f'warm{i}.db'}",
                f"warm-{i}-{uuid.uuid4().hex[:8]}")


def run(hours: float, db: str | None) -> dict[str, Any]:
    machine = load_machine("patu655")
    rows = int(hours * 3600 * RATE_HZ)
    with tempfile.TemporaryDirectory(prefix="ct-bench-import-") as tmp:
        d = Path(tmp)
        csv_path, pq_path = write_files(machine, rows, d)

        def url(name: str) -> str:
            return db if db is not None else f"sqlite:///{d / name}.db"

        tag = uuid.uuid4().hex[:8]
        _warm_up(machine, d, db)
        load = os.getloadavg()[0]
        t_pq, n_pq, cpu_pq = _import(pq_path, machine, url("parquet"), f"bench-pq-{tag}")
        t_csv, n_csv, cpu_csv = _import(csv_path, machine, url("csv"), f"bench-csv-{tag}")
        rss, cmd_wall, cmd_cpu = _child_peak_rss(pq_path, url("rss"))
        csv_rss, _, _ = _child_peak_rss(csv_path, url("csv-rss"))
        pd_rows = min(rows, PANDAS_MAX_ROWS)
        t_pd = _pandas(csv_path, url("pandas"), pd_rows)
        out: dict[str, Any] = {
            "hours": hours, "samples": rows, "channels": len(machine.channels),
            "database": "sqlite" if db is None else db.split(":", 1)[0],
            "parquet_samples_per_second": round(n_pq / t_pq),
            "csv_samples_per_second": round(n_csv / t_csv),
            "parquet_cpu_seconds": round(cpu_pq, 3),
            "parquet_cpu_samples_per_second": round(n_pq / max(cpu_pq, 1e-9)),
            "csv_cpu_seconds": round(cpu_csv, 3),
            "pandas_samples_per_second": None if t_pd is None else round(pd_rows / t_pd),
            "pandas_samples": pd_rows,
            "speedup_vs_pandas": None if t_pd is None else round((n_pq / t_pq) / (pd_rows / t_pd),
                                                                   2),
            "peak_rss_mib": round(rss, 1),
            "csv_peak_rss_mib": round(csv_rss, 1),
            "parquet_command_seconds": round(cmd_wall, 2),
            "parquet_command_cpu_seconds": round(cmd_cpu, 2),
            "csv_mib": round(csv_path.stat().st_size / 2**20, 1),
            "parquet_mib": round(pq_path.stat().st_size / 2**20, 1),
            "load_average_1min": round(load, 2),
        }
    return out


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("import")
    def import_bench(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        hours: float = typer.Option(1.0, help="Hours of 100 Hz data in the file (24: the "
                                              "memory target's day)."),
        db: str | None = typer.Option(None, "--db", help="Database URL (default: a temporary "
                                      "SQLite file per path)."),
    ) -> None:
        """Samples/s into storage from Parquet and CSV vs. pandas read_csv + to_sql; peak RSS."""
        emit(run(hours, db), as_json)
