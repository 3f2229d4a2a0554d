"""``cranetwin bench api``: the HTTP API under load, on a real uvicorn server on loopback.

Setup: a database (temporary SQLite unless ``--db``) filled through the store's write path with
``--hours`` (24) of one crane at 100 Hz (8.64 M samples, 11 channels) in 10-s blocks, the exact
kinematic samples of :mod:`cranetwin.testing.blocks` tiled in time; the twin worker then derives
the last ``--worker-hours`` (1) of it. ``cranetwin serve`` runs in a subprocess.

Figures (``--json`` prints one object):

* ``load_history_p95_ms`` — GET /history of the whole span, 2000 points, 4 channels (3 raw,
  1 derived); baseline: the same min/max/mean computed from the raw samples (read + numpy).
* ``twin_60s_p95_ms`` — GET /twin of a 60-s window at 50 Hz, each window different (no cache
  hit); ``twin_60s_cached_p95_ms`` for repeated windows (scrubbing); baseline: one in-process
  replay of a 60-s window without the per-machine smoothing reuse (the twin's default).
* ``live_clients`` websockets on one machine while blocks of 0.04 s (4 samples) are stored at
  25 Hz with current timestamps (as the ingest daemon commits datagram batches);
  ``live_p95_latency_ms`` from the commit of a block to a client receiving
  the frame of its newest sample; baseline: the same with one client.
"""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin.bench import emit

MID = "bench-crane"
CHANNELS = "lift_pA,jib_pA,ext_pA,force:lift"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _p95(x: list[float]) -> float:
    return float(np.percentile(np.asarray(x), 95)) if x else float("nan")


def _fill(url: str, hours: float, worker_hours: float) -> tuple[float, float, dict[str, Any]]:
    from cranetwin.model import load_machine
    from cranetwin.service.backend import Backend
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=4242, secret=os.urandom(32))
    end = float(np.floor(time.time() / 60.0) * 60.0 - 600.0)
    start = end - hours * 3600.0
    t = time.perf_counter()
    batch: list[Any] = []
    for blk in tiled_blocks(MID, machine, start, hours * 3600.0, 10.0, base=base):
        batch.append(blk)
        if len(batch) == 360:
            b.store.write_blocks(batch)
            batch = []
    if batch:
        b.store.write_blocks(batch)
    fill_s = time.perf_counter() - t
    t = time.perf_counter()
    b.store.rollup()  # what the ingest daemon does every 30 s
    rollup_s = time.perf_counter() - t
    stats = b.store.stats(MID)
    # the worker derives the last worker_hours (its watermark placed there, as after a restart)
    from cranetwin.service.backend import Progress

    b.reset_progress(Progress.empty(MID, end - worker_hours * 3600.0))
    t = time.perf_counter()
    w = TwinWorker(b, Settings(database_url=url, worker_settle_s=0.0))
    windows = w.catch_up(b.machine(MID))
    worker_s = time.perf_counter() - t
    key = b.create_key("viewer", "bench")[1]
    b.close()
    info = {"samples": stats.samples, "blocks": stats.blocks, "fill_seconds": round(fill_s, 2),
            "fill_samples_per_second": round(stats.samples / fill_s),
            "rollup_seconds": round(rollup_s, 2),
            "worker_windows": windows, "worker_seconds": round(worker_s, 2),
            "worker_real_time_factor": round(windows * 60.0 / max(worker_s, 1e-9), 1),
            "key": key}
    return start, end, info


def _history_baseline(url: str, start: float, end: float) -> float:
    """Min/max/mean in 2000 buckets of 3 raw channels computed from the raw samples [ms]."""
    from cranetwin.storage import Store

    st = Store.open(url)
    t = time.perf_counter()
    edges = np.linspace(start, end, 2001)
    a = start
    acc = []
    while a < end:  # read in 1-hour pieces (bounded memory)
        s = st.read_samples(MID, a, min(end, a + 3600.0))
        idx = np.searchsorted(edges, s.t_s, side="right") - 1
        for name in CHANNELS.split(",")[:3]:
            col = s.column(name)
            acc.append((np.bincount(idx, col, 2000), np.bincount(idx, minlength=2000)))
            m = np.full(2000, np.inf)
            np.minimum.at(m, idx, col)
        a += 3600.0
    ms = (time.perf_counter() - t) * 1e3
    st.close()
    return ms


def _twin_baseline(url: str, start: float) -> float:
    """One in-process 60-s replay at 100 Hz with the smoothing choice made every time [ms]."""
    from cranetwin.model import load_machine
    from cranetwin.storage import Store
    from cranetwin.twin import replay

    st = Store.open(url)
    machine = load_machine("patu655")
    out = []
    for k in range(3):
        a = start + 3600.0 + 60.0 * k
        s = st.read_samples(MID, a - 2.0, a + 62.0)
        t = time.perf_counter()
        replay(s, machine, grid_hz=100.0)
        out.append((time.perf_counter() - t) * 1e3)
    st.close()
    return float(np.median(out))


def _serve(url: str, port: int) -> subprocess.Popen[bytes]:
    # one client measuring speed: its 60 twin requests in a row would exceed a viewer key's
    # rate limit (tests/test_api_limits.py measures the limits)
    env = {**os.environ, "CRANETWIN_DATABASE_URL": url, "CRANETWIN_RATE_LIMIT": "false"}
    proc = subprocess.Popen([sys.executable, "-c", "from cranetwin.cli import main; main()",
                             "serve", "--port", str(port), "--no-worker", "--log-level",
                             "warning"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    import httpx

    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    err = proc.stderr.read().decode() if proc.stderr else ""
    raise RuntimeError(f"server did not start: {err}")


def _http(port: int, key: str, start: float, end: float, n_history: int,
          n_twin: int) -> dict[str, float]:
    import httpx

    h = {"X-API-Key": key}
    base = f"http://127.0.0.1:{port}/api/v1/machines/{MID}"
    hist: list[float] = []
    with httpx.Client(headers=h, timeout=120.0) as c:
        r = c.get(f"{base}/history", params={"from": start, "to": end, "channels": CHANNELS,
                                             "max_points": 2000})
        r.raise_for_status()
        n_points = len(r.json()["channels"]["lift_pA"]["t"])
        for _ in range(n_history):
            t = time.perf_counter()
            c.get(f"{base}/history", params={"from": start, "to": end, "channels": CHANNELS,
                                             "max_points": 2000}).raise_for_status()
            hist.append((time.perf_counter() - t) * 1e3)
        c.get(f"{base}/twin", params={"from": start + 60, "to": start + 120,
                                      "rate_hz": 50}).raise_for_status()  # warm-up
        twin: list[float] = []
        cached: list[float] = []
        rng = np.random.default_rng(1)
        for k in range(n_twin):
            a = start + 600.0 + 60.0 * k + float(rng.uniform(0, 30))
            t = time.perf_counter()
            r = c.get(f"{base}/twin", params={"from": a, "to": a + 60.0, "rate_hz": 50})
            r.raise_for_status()
            twin.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            c.get(f"{base}/twin", params={"from": a, "to": a + 60.0, "rate_hz": 50})
            cached.append((time.perf_counter() - t) * 1e3)
        twin_bytes = len(r.content)
    return {"history_points": n_points, "load_history_p95_ms": _p95(hist),
            "load_history_median_ms": float(np.median(hist)),
            "twin_60s_p95_ms": _p95(twin), "twin_60s_median_ms": float(np.median(twin)),
            "twin_60s_cached_p95_ms": _p95(cached), "twin_60s_bytes": twin_bytes}


def _live(url: str, port: int, key: str, clients: int, seconds: float,
          block_hz: float = 25.0) -> dict[str, float]:
    """Open ``clients`` websockets, store a block of 100/block_hz samples block_hz times a
    second (as datagram batches arrive), measure latencies."""
    import websockets

    from cranetwin.model import load_machine
    from cranetwin.storage import Store
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    st = Store.open(url)
    committed: dict[float, float] = {}  # newest sample time of a block -> commit wall time
    lat: list[float] = []
    stop = threading.Event()

    def writer() -> None:
        seq = int(time.time() * 100)  # unique across runs (writes are idempotent on seq)
        t_next = time.time()
        dt = 1.0 / block_hz
        n = int(round(100.0 / block_hz))
        last = -np.inf  # newest sample written [s]: blocks never overlap (storage refuses that)
        while not stop.is_set():
            newest = float(np.floor(time.time() * 100.0) / 100.0)
            t0 = max(newest - (n - 1) / 100.0, round(last + 0.01, 2))
            k = int(round((newest - t0) * 100.0)) + 1
            if k >= 1:
                blk = next(tiled_blocks(MID, machine, t0, k / 100.0, k / 100.0, base=base,
                                        seq0=seq))
                st.write_blocks([blk])
                last = round(t0 + (k - 1) / 100.0, 2)
                committed[last] = time.time()
                seq += 1
            t_next += dt
            time.sleep(max(0.0, t_next - time.time()))

    async def client(ready: asyncio.Event, n_ready: list[int]) -> None:
        uri = f"ws://127.0.0.1:{port}/api/v1/machines/{MID}/live?key={key}"
        async with websockets.connect(uri, max_size=None, open_timeout=60) as ws:
            await ws.recv()  # hello
            n_ready[0] += 1
            if n_ready[0] == clients:
                ready.set()
            await ready.wait()
            while not stop.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), timeout=1.0)
                except TimeoutError:
                    continue
                now = time.time()
                # frames start with {"t":<time>, — read it without parsing the whole frame
                text = msg if isinstance(msg, str) else msg.decode()
                t = round(float(text[5:text.index(",")]), 2)
                c = committed.get(t)
                if c is not None:
                    lat.append((now - c) * 1e3)

    async def main() -> None:
        ready = asyncio.Event()
        n_ready = [0]
        tasks = [asyncio.create_task(client(ready, n_ready)) for _ in range(clients)]
        await asyncio.wait_for(ready.wait(), timeout=120)
        th = threading.Thread(target=writer, daemon=True)
        th.start()
        await asyncio.sleep(seconds)
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        th.join()

    asyncio.run(main())
    st.close()
    return {"p95": _p95(lat), "median": float(np.median(lat)) if lat else float("nan"),
            "frames": float(len(lat)), "frames_per_client_s": len(lat) / clients / seconds}


def bench_api(
    hours: float = typer.Option(24.0, help="Hours of 100 Hz data to store."),
    worker_hours: float = typer.Option(1.0, help="Hours the twin worker derives before the "
                                       "measurement."),
    db: str | None = typer.Option(None, "--db", help="Database URL (default: temporary SQLite)."),
    clients: int = typer.Option(200, help="Live websocket clients."),
    live_seconds: float = typer.Option(10.0, help="Duration of the live measurement [s]."),
    requests: int = typer.Option(30, help="Requests per REST measurement."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Load history, twin and live-stream latency of the API on a real server."""
    tmp = tempfile.TemporaryDirectory()
    url = db or f"sqlite:///{Path(tmp.name) / 'bench.db'}"
    start, end, info = _fill(url, hours, worker_hours)
    key = str(info.pop("key"))
    port = _free_port()
    proc = _serve(url, port)
    try:
        rest = _http(port, key, start, end, requests, requests)
        one = _live(url, port, key, 1, min(live_seconds, 5.0))
        many = _live(url, port, key, clients, live_seconds)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    hist_base = _history_baseline(url, start, end)
    twin_base = _twin_baseline(url, start)
    tmp.cleanup()
    out: dict[str, Any] = {
        "database": url.split(":", 1)[0], "hours": hours, **info,
        "history_points": rest["history_points"],
        "load_history_p95_ms": round(rest["load_history_p95_ms"], 2),
        "load_history_median_ms": round(rest["load_history_median_ms"], 2),
        "load_history_baseline_raw_ms": round(hist_base, 1),
        "load_history_speedup_vs_raw": round(hist_base / rest["load_history_p95_ms"], 1),
        "twin_60s_p95_ms": round(rest["twin_60s_p95_ms"], 2),
        "twin_60s_median_ms": round(rest["twin_60s_median_ms"], 2),
        "twin_60s_cached_p95_ms": round(rest["twin_60s_cached_p95_ms"], 2),
        "twin_60s_bytes": rest["twin_60s_bytes"],
        "twin_60s_baseline_replay_ms": round(twin_base, 1),
        "twin_60s_ratio_to_baseline_replay": round(rest["twin_60s_p95_ms"] / twin_base, 2),
        "live_clients": clients,
        "live_p95_latency_ms": round(many["p95"], 1),
        "live_median_latency_ms": round(many["median"], 1),
        "live_frames_per_client_per_s": round(many["frames_per_client_s"], 1),
        "live_1_client_p95_latency_ms": round(one["p95"], 1),
        "live_1_client_frames_per_s": round(one["frames_per_client_s"], 1),
        "live_p95_ratio_to_1_client": round(many["p95"] / one["p95"], 2),
        "targets": {"load_history_p95_ms": 100, "twin_60s_p95_ms": 200,
                    "live_clients": 200, "live_p95_latency_ms": 250},
    }
    emit(out, as_json)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("api")(bench_api)
