"""The raw-sample export as a user runs it, timed from outside the server.

:func:`served_export`: a ``cranetwin serve`` process of its own on the benchmark's database
(worker off, warm-up off: its start is not timed), and a client that downloads
``GET /api/v1/machines/{id}/export`` of a range with a fleet key, as Parquet and as CSV, each
``runs`` times after one small download that loads the server's pyarrow (a long-running server
pays that once). Timed per download: wall from sending the request to the last byte received
(``httpx`` streaming in 1 MiB reads, the bytes only counted), the server process's CPU time
(user + system, /proc) and the client's. Rows are counted from the file (the Parquet footer,
CSV lines) so a short download cannot pass for a fast one.

:func:`cli_export`: ``cranetwin export --out FILE.parquet`` in a process of its own, timed
from the start to the exit (Python start and imports included: what a user waits for), with
its CPU time (``RUSAGE_CHILDREN``) and the export time it prints itself.

Both report medians over the runs; rates are samples (rows of all channels) per second.
"""

from __future__ import annotations

import io
import os
import re
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from cranetwin.bench.ingest_daemon import cpu_seconds
from cranetwin.errors import MissingExtraError

CLI = "from cranetwin.cli import main; main()"
"""The ``cranetwin`` command as ``python -c`` runs it (the console script may not be on PATH)."""

_CLI_LINE = re.compile(r"raw of .*, ([0-9,]+) bytes in ([0-9.]+) s")


def _parquet() -> Any:
    """``pyarrow.parquet`` (to count the rows of a file), or MissingExtraError (extra
    ``import``, as the export itself)."""
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("import", "the export benchmark") from exc
    return pq


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rows(body: bytes | None, lines: int, fmt: str) -> int:
    if fmt == "csv":
        return lines - 1  # the header line
    assert body is not None
    return int(_parquet().ParquetFile(io.BytesIO(body)).metadata.num_rows)


def _download(client: Any, url: str, key: str, params: dict[str, Any], fmt: str,
              pid: int) -> tuple[int, float, float, float]:
    """One download: (rows, wall [s], server CPU [s], client CPU [s])."""
    keep: list[bytes] | None = [] if fmt == "parquet" else None
    lines = 0
    s0, c0, w0 = cpu_seconds(pid), time.process_time(), time.perf_counter()
    with client.stream("GET", url, params={**params, "format": fmt},
                       headers={"X-API-Key": key}) as r:
        if r.status_code != 200:
            raise RuntimeError(f"export answered {r.status_code}: {r.read()[:300]!r}")
        for piece in r.iter_raw(1 << 20):
            if keep is not None:
                keep.append(piece)
            else:
                lines += piece.count(b"\n")
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    s1 = cpu_seconds(pid)
    server = (s1 - s0) if s0 is not None and s1 is not None else float("nan")
    return _rows(None if keep is None else b"".join(keep), lines, fmt), wall, server, cpu


def served_export(db_url: str, key: str, machine_id: str, t0_s: float, t1_s: float,
                  runs: int = 3, start_timeout_s: float = 120.0) -> dict[str, Any]:
    """Downloads of [t0_s, t1_s) of ``machine_id`` from a ``cranetwin serve`` process on
    ``db_url`` with the fleet key ``key`` (see the module docstring).

    Returns:
        ``export_http_<fmt>_…`` figures: rows, median wall [s], samples per second (wall),
        samples per server CPU second, client CPU seconds.

    Raises:
        RuntimeError: The server did not start or an export did not answer 200.
    """
    import httpx

    port = _free_port()
    env = {**os.environ, "CRANETWIN_DATABASE_URL": db_url, "CRANETWIN_WARM_UP": "false",
           "CRANETWIN_WORKER_IN_PROCESS": "false", "CRANETWIN_ALARM_CHECK_INTERVAL_S": "0"}
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen([sys.executable, "-c", CLI, "serve", "--port", str(port),
                                 "--no-worker", "--log-level", "warning"],
                                env=env, stdout=log, stderr=subprocess.STDOUT)
        base = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(timeout=600.0) as client:
                deadline = time.monotonic() + start_timeout_s
                while True:
                    try:
                        if client.get(f"{base}/healthz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    if proc.poll() is not None or time.monotonic() > deadline:
                        log.seek(0)
                        raise RuntimeError(f"cranetwin serve did not start: "
                                           f"{log.read()[-2000:].decode(errors='replace')}")
                    time.sleep(0.1)
                url = f"{base}/api/v1/machines/{machine_id}/export"
                out: dict[str, Any] = {}
                for fmt in ("parquet", "csv"):
                    _download(client, url, key, {"from": t0_s, "to": t0_s + 1.0}, fmt, proc.pid)
                    got = [_download(client, url, key, {"from": t0_s, "to": t1_s}, fmt,
                                     proc.pid) for _ in range(runs)]
                    rows = got[0][0]
                    if any(g[0] != rows for g in got):
                        raise RuntimeError(f"{fmt} downloads differ in rows: {got}")
                    wall = statistics.median(g[1] for g in got)
                    server = statistics.median(g[2] for g in got)
                    p = f"export_http_{fmt}"
                    out |= {f"{p}_rows": rows, f"{p}_seconds": round(wall, 3),
                            f"{p}_samples_per_second": round(rows / wall),
                            f"{p}_server_cpu_samples_per_second": round(rows / max(server, 1e-9)),
                            f"{p}_client_cpu_seconds": round(
                                statistics.median(g[3] for g in got), 3),
                            f"{p}_walls": [round(g[1], 3) for g in got]}
                return out
        finally:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def cli_export(db_url: str, machine_id: str, t0_s: float, t1_s: float,
               runs: int = 3) -> dict[str, Any]:
    """``cranetwin export`` of [t0_s, t1_s) to a Parquet file, ``runs`` times (see the module
    docstring).

    Returns:
        ``export_cli_…``: median wall of the whole command [s], samples per second of it, its
        CPU seconds, and the export's own seconds as the command prints them.

    Raises:
        RuntimeError: The command failed.
    """
    pq = _parquet()
    env = {**os.environ, "CRANETWIN_DATABASE_URL": db_url}
    walls, cpus, own = [], [], []
    rows = 0
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "raw.parquet"
        for _ in range(runs):
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            w0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", CLI, "export", "--machine", machine_id,
                                  "--from", repr(t0_s), "--to", repr(t1_s), "--out", str(out)],
                                 env=env, capture_output=True, text=True, timeout=600)
            walls.append(time.perf_counter() - w0)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime)
            m = _CLI_LINE.search(res.stdout)
            if res.returncode != 0 or m is None:
                raise RuntimeError(f"cranetwin export failed ({res.returncode}): "
                                   f"{res.stdout[-500:]} {res.stderr[-2000:]}")
            own.append(float(m.group(2)))
            rows = int(pq.ParquetFile(out).metadata.num_rows)
    wall, exp = statistics.median(walls), statistics.median(own)
    return {"export_cli_rows": rows, "export_cli_seconds": round(wall, 3),
            "export_cli_samples_per_second": round(rows / wall),
            "export_cli_cpu_seconds": round(statistics.median(cpus), 3),
            "export_cli_export_seconds": round(exp, 3),
            "export_cli_export_samples_per_second": round(rows / exp)}
