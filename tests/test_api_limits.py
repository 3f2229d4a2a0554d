"""Service limits: the replay cache's byte bound, the token bucket per key (429 with
Retry-After), the heavy pool (503 when full), and fairness on a real uvicorn server: one busy key
does not slow another key's cheap requests by more than 2×.
"""

from __future__ import annotations

import re
import socket
import statistics
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.limits import Rate, RateLimiter, TokenBucket
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.service.cache import LruCache, nbytes_of
from cranetwin.service.errors import BusyError
from cranetwin.service.heavy import HeavyPool
from cranetwin.settings import Settings
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0
SPAN = 180.0
MID = "crane-1"


# --- token bucket ------------------------------------------------------------------------------
@pytest.mark.timeout(10)
def test_bucket_admits_its_burst_then_says_when_tokens_are_back() -> None:
    b = TokenBucket(Rate(per_s=2.0, burst=5.0), now=0.0)
    assert [b.take(1.0, 0.0) for _ in range(5)] == [0.0] * 5
    assert b.take(1.0, 0.0) == pytest.approx(0.5)  # one token back after 1/rate
    assert b.take(3.0, 0.0) == pytest.approx(1.5)
    assert b.take(1.0, 0.5) == 0.0  # refilled by rate × elapsed
    assert b.take(1.0, 100.0) == 0.0 and b.tokens == pytest.approx(4.0)  # capped at burst
    assert b.take(50.0, 200.0) == 0.0 and b.tokens == pytest.approx(0.0)  # cost ≤ burst


@pytest.mark.timeout(10)
def test_limiter_keeps_a_bucket_per_key_and_charges_heavy_requests_more() -> None:
    now = [0.0]
    lim = RateLimiter({"viewer": Rate(1.0, 10.0), "fleet": Rate(1.0, 10.0),
                       "admin": Rate(1.0, 10.0)}, heavy_cost=5.0, clock=lambda: now[0])
    assert lim.take("a", "viewer", heavy=True) == 0.0
    assert lim.take("a", "viewer", heavy=True) == 0.0
    assert lim.take("a", "viewer", heavy=False) == pytest.approx(1.0)
    assert lim.take("b", "viewer", heavy=True) == 0.0  # another key: its own bucket
    now[0] = 3.0
    assert lim.take("a", "viewer", heavy=False) == 0.0


# --- replay cache --------------------------------------------------------------------------------
@pytest.mark.timeout(10)
def test_cache_holds_at_most_its_bytes_evicting_least_recently_used() -> None:
    c: LruCache[bytes] = LruCache(100, max_bytes=1000)
    for i in range(5):
        assert c.put(i, b"x" * 300)
        assert c.nbytes <= 1000
    assert len(c) == 3 and c.nbytes == 900 and c.evictions == 2
    assert c.get(2) is not None  # 2 is now the most recently used
    c.put(5, b"y" * 300)
    assert c.get(3) is None and c.get(2) is not None
    assert not c.put(6, b"z" * 1001)  # larger than the whole bound: not cached
    assert c.nbytes <= 1000
    c.put(2, b"w" * 10)  # replacing a value counts its new size
    assert c.nbytes == 610


@pytest.mark.timeout(10)
def test_nbytes_of_counts_arrays_bytes_and_containers() -> None:
    a = np.zeros((100, 16))
    assert nbytes_of(a) == 12800
    assert nbytes_of({"t": a, "q": [a, b"abc"]}) == 25600 + 3 + 2  # plus the keys' lengths


# --- heavy pool ----------------------------------------------------------------------------------
@pytest.mark.timeout(20)
def test_heavy_pool_refuses_beyond_workers_plus_queue_and_frees_slots() -> None:
    pool = HeavyPool(workers=1, queue=1)
    gate = threading.Event()
    try:
        f1 = pool.submit(gate.wait, 10)
        f2 = pool.submit(gate.wait, 10)
        with pytest.raises(BusyError):
            pool.submit(gate.wait, 10)
        with pytest.raises(BusyError):
            pool.lease()
        assert pool.admitted == 2 and pool.refused == 2
        gate.set()
        assert f1.result(10) and f2.result(10)
        deadline = time.monotonic() + 5
        while pool.admitted and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pool.admitted == 0
        with pool.lease() as lease:
            assert lease.submit(sum, [1, 2]).result(5) == 3
        assert pool.admitted == 0
    finally:
        gate.set()
        pool.close()


@pytest.mark.timeout(20)
def test_a_stream_gives_its_admission_back_when_done_or_never_started() -> None:
    import asyncio
    import gc
    from types import SimpleNamespace

    from cranetwin.api.limits import stream_heavy

    pool = HeavyPool(workers=1, queue=0)
    services: Any = SimpleNamespace(heavy=pool)

    async def run() -> list[bytes]:
        _, never = await stream_heavy(services, None, lambda: 1, lambda _: iter([b"x"]))
        assert pool.admitted == 1
        del never
        gc.collect()
        assert pool.admitted == 0
        _, body = await stream_heavy(services, None, lambda: 1, lambda _: iter([b"a", b"b"]))
        return [chunk async for chunk in body]

    try:
        assert asyncio.run(run()) == [b"a", b"b"]
        assert pool.admitted == 0
    finally:
        pool.close()


@pytest.mark.timeout(20)
def test_replays_run_on_threads_until_the_worker_processes_are_up() -> None:
    from concurrent.futures import ThreadPoolExecutor

    gate = threading.Event()
    procs = ThreadPoolExecutor(1)  # stands in for the process pool: any Executor
    pool = HeavyPool(workers=1, queue=2, processes=procs, process_count=1,
                     process_warm=lambda: gate.wait(10))
    try:
        assert not pool.processes_ready
        # the first call starts the processes in the background and runs on a heavy thread
        assert pool.submit(lambda: "thread", process_fn=lambda: "process").result(5) == "thread"
        assert pool.submit(lambda: "thread", process_fn=lambda: "process").result(5) == "thread"
        gate.set()  # warmed up
        deadline = time.monotonic() + 5
        while not pool.processes_ready and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pool.submit(lambda: "thread", process_fn=lambda: "process").result(5) == "process"
        assert pool.submit(lambda: "thread").result(5) == "thread"  # no process_fn: threads
    finally:
        gate.set()
        pool.close()

    def broken() -> None:
        raise OSError("no spawn here")

    pool = HeavyPool(workers=1, queue=0, processes=ThreadPoolExecutor(1), process_warm=broken)
    try:
        pool.start_processes()
        time.sleep(0.2)
        assert not pool.processes_ready  # a failed start leaves the replays on the threads
        assert pool.submit(lambda: "thread", process_fn=lambda: "process").result(5) == "thread"
    finally:
        pool.close()


@pytest.mark.timeout(10)
def test_one_replay_process_by_default_none_for_the_embedded_demo() -> None:
    assert Settings(database_url="sqlite://").replay_processes == 1
    assert Settings(database_url="sqlite://", worker_in_process=True).replay_processes == 0
    assert Settings(database_url="sqlite://", worker_in_process=True,
                    heavy_processes=2).replay_processes == 2
    assert Settings(database_url="sqlite://", heavy_processes=0).replay_processes == 0


# --- the API -------------------------------------------------------------------------------------
def _fill(services: Services) -> dict[str, str]:
    machine = load_machine("patu655")
    services.backend.store.add_machine(MID, wire_id=1, secret=b"s" * 32)
    services.backend.store.write_blocks(list(tiled_blocks(
        MID, machine, T0, SPAN, 1.0, base=kinematic_samples(machine, 60.0))))
    return {name: services.backend.create_key(role, name)[1]
            for name, role in (("a", "viewer"), ("b", "viewer"), ("admin", "admin"))}


@dataclass
class Api:
    client: TestClient
    services: Services
    keys: dict[str, str]

    def get(self, path: str, who: str, **params: Any) -> httpx.Response:
        return self.client.get(path, params=params, headers={"X-API-Key": self.keys[who]})


def _api(tmp: Path, **settings: Any) -> Iterator[Api]:
    app = create_app(Settings(database_url=f"sqlite:///{tmp / 'limits.db'}",
                              worker_in_process=False, warm_up=False, **settings))
    with TestClient(app) as client:
        yield Api(client, app.state.services, _fill(app.state.services))


def _metric(text: str, name: str) -> float:
    m = re.search(rf"^{name} ([0-9.e+-]+)$", text, re.M)
    assert m, f"{name} not in /metrics"
    return float(m.group(1))


@pytest.mark.timeout(120)
def test_a_key_over_its_rate_gets_429_with_retry_after_and_others_do_not(tmp_path: Path) -> None:
    for api in _api(tmp_path, rate_viewer_per_s=0.5, rate_viewer_burst=20, rate_heavy_cost=10):
        base = f"/api/v1/machines/{MID}/twin"
        rng = {"from": T0 + 10, "to": T0 + 12, "rate_hz": 10}
        assert api.get(base, "a", **rng).status_code == 200
        assert api.get(base, "a", **rng).status_code == 200
        r = api.get(base, "a", **rng)  # 20 tokens spent: a third heavy request is refused
        assert r.status_code == 429, r.text
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["status"] == 429 and r.json()["title"] == "Too many requests"
        assert 1 <= int(r.headers["Retry-After"]) <= 20  # 10 tokens at 0.5/s
        assert api.get("/api/v1/machines", "b").status_code == 200  # another key: unaffected
        assert api.get(base, "b", **rng).status_code == 200
        text = api.get("/metrics", "admin").text
        assert _metric(text, 'cranetwin_http_refused_total{reason="rate_limit",role="viewer"}') \
            == 1


@pytest.mark.timeout(120)
def test_full_heavy_pool_answers_503_with_retry_after_and_cheap_routes_still_answer(
        tmp_path: Path) -> None:
    for api in _api(tmp_path, heavy_workers=1, heavy_queue=0):
        gate = threading.Event()
        api.services.heavy.submit(gate.wait, 30)  # the only heavy thread is busy
        try:
            r = api.get(f"/api/v1/machines/{MID}/twin", "a", **{"from": T0, "to": T0 + 2})
            assert r.status_code == 503, r.text
            assert r.headers["content-type"].startswith("application/problem+json")
            assert int(r.headers["Retry-After"]) >= 1
            r = api.get(f"/api/v1/machines/{MID}/export", "admin",
                        **{"from": T0, "to": T0 + 2, "format": "csv"})
            assert r.status_code == 503, r.text
            assert api.get("/api/v1/machines", "b").status_code == 200
            assert api.get(f"/api/v1/machines/{MID}/history", "b",
                           **{"from": T0, "to": T0 + 60, "channels": "lift_pA"}
                           ).status_code == 200
        finally:
            gate.set()
        text = api.get("/metrics", "admin").text
        assert _metric(text, 'cranetwin_http_refused_total{reason="busy",role="viewer"}') == 1
        assert _metric(text, 'cranetwin_http_refused_total{reason="busy",role="admin"}') == 1


@pytest.mark.timeout(180)
def test_replay_cache_stays_within_its_byte_bound(tmp_path: Path) -> None:
    bound = 600_000  # about two 5-s windows at 50 Hz (≈ 250 kB each)
    for api in _api(tmp_path, twin_cache_bytes=bound, rate_limit=False):
        sizes = []
        for k in range(12):  # distinct windows inside stored data: each is cached
            r = api.get(f"/api/v1/machines/{MID}/twin", "a",
                        **{"from": T0 + 5 * k, "to": T0 + 5 * k + 5, "rate_hz": 50})
            assert r.status_code == 200
            sizes.append(len(r.content))
            text = api.get("/metrics", "admin").text
            assert _metric(text, "cranetwin_twin_cache_bytes") <= bound
        assert sum(sizes) > 2 * bound  # without the bound the cache would hold more
        assert _metric(text, "cranetwin_twin_cache_max_bytes") == bound
        assert _metric(text, "cranetwin_twin_cache_evictions") > 0
        assert 0 < api.services.fleet.twin_cache.nbytes <= bound


# --- fairness on a real server -------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def server(tmp_path: Path) -> Iterator[tuple[str, dict[str, str], Services]]:
    import uvicorn

    # a viewer's twin request costs 50 of its 200 tokens, 20 back per second: key A has a
    # burst of 4 replays, then 0.4 per second; key B's 90 cheap requests stay within its bucket.
    # Default heavy_processes: replays in a worker process, started in the background once the
    # server is up; on the API's own threads (heavy_processes=0) B's median was 4× its quiet one
    # in the same conditions (60 → 244 ms, load average 24 on 2 cores)
    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'fair.db'}",
                              worker_in_process=False, warm_up=True, rate_viewer_burst=200,
                              rate_viewer_per_s=20, rate_heavy_cost=50))
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           access_log=False, lifespan="on"))
    t = threading.Thread(target=server.run, daemon=True)
    t.start()
    try:
        deadline = time.monotonic() + 60
        while not server.started:
            assert time.monotonic() < deadline and t.is_alive(), "uvicorn did not start"
            time.sleep(0.05)
        services = app.state.services
        assert services.heavy.processes is not None  # the default: a replay process
        deadline = time.monotonic() + 120
        while not services.heavy.processes_ready:  # started in the background
            assert time.monotonic() < deadline, "the replay process did not start"
            time.sleep(0.1)
        yield f"http://127.0.0.1:{port}", _fill(services), services
    finally:
        server.should_exit = True
        t.join(30)


FLOOR_MS = 20.0
"""Absolute allowance on top of 2× the quiet median [ms]: at medians of a few ms, a single
thread switch of the interpreter (5 ms) would otherwise decide the test."""


def _median_ms(client: httpx.Client, url: str, key: str, n: int) -> float:
    times = []
    for _ in range(n):
        t = time.perf_counter()
        r = client.get(url, headers={"X-API-Key": key})
        times.append((time.perf_counter() - t) * 1e3)
        assert r.status_code == 200, r.text
    return statistics.median(times)


HAMMER = """
import json, sys, threading
import httpx
import numpy as np

base, key, t0, span, n = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), 6
stop = threading.Event()
statuses, retry_after = [], []


def hammer(i):
    rng = np.random.default_rng(i)
    with httpx.Client(timeout=60) as a:
        while not stop.is_set():
            t = t0 + float(rng.uniform(0, span - 40))
            r = a.get(base + "/twin", params={"from": t, "to": t + 30,
                      "rate_hz": float(rng.choice([25, 50, 100]))}, headers={"X-API-Key": key})
            statuses.append(r.status_code)
            if r.status_code in (429, 503):
                retry_after.append(r.headers.get("Retry-After", ""))


threads = [threading.Thread(target=hammer, args=(i,)) for i in range(n)]
for t in threads:
    t.start()
sys.stdin.readline()
stop.set()
for t in threads:
    t.join(60)
print(json.dumps({"statuses": statuses, "retry_after": retry_after}))
"""
"""Key A's client: 6 threads asking for distinct twin windows as fast as the server answers,
retries ignored, until a line arrives on stdin; then the statuses as JSON. A process of its own,
so that its HTTP parsing does not compete with the server for this process's interpreter."""


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_busy_key_does_not_slow_another_keys_machine_list_by_more_than_2x(
        server: tuple[str, dict[str, str], Services]) -> None:
    import json
    import subprocess
    import sys

    base, keys, services = server
    machines = f"{base}/api/v1/machines"
    with httpx.Client(timeout=30) as b:
        _median_ms(b, machines, keys["b"], 10)  # warm
        quiet = _median_ms(b, machines, keys["b"], 40)
        a = subprocess.Popen([sys.executable, "-c", HAMMER, f"{base}/api/v1/machines/{MID}",
                              keys["a"], str(T0), str(SPAN)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
        try:
            time.sleep(2.0)  # A's burst is under way
            busy = _median_ms(b, machines, keys["b"], 40)
        finally:
            out, _ = a.communicate("stop\n", timeout=120)
    got = json.loads(out)
    statuses, retry_after = got["statuses"], got["retry_after"]
    print(f"machines median: quiet {quiet:.1f} ms, key A busy {busy:.1f} ms; A: "
          f"{statuses.count(200)} × 200, {statuses.count(429)} × 429, "
          f"{statuses.count(503)} × 503; cache {services.fleet.twin_cache.nbytes} B")
    assert statuses.count(200) >= 1
    assert statuses.count(429) >= 1, statuses  # A was throttled ...
    assert all(v.isdigit() and int(v) >= 1 for v in retry_after)  # ... and told when to retry
    assert busy <= 2.0 * quiet + FLOOR_MS, (quiet, busy)
    assert services.fleet.twin_cache.nbytes <= services.settings.twin_cache_bytes


# --- websockets ----------------------------------------------------------------------------------
@pytest.mark.timeout(120)
def test_live_connects_are_charged_and_refused_with_4429_and_a_reason(tmp_path: Path) -> None:
    from starlette.websockets import WebSocketDisconnect

    for api in _api(tmp_path, rate_viewer_per_s=0.01, rate_viewer_burst=3,
                    rate_limit_delay_s=0):
        def connect(who: str, api: Api = api) -> dict[str, Any]:
            with api.client.websocket_connect(f"/api/v1/machines/{MID}/live",
                                              headers={"X-API-Key": api.keys[who]}) as ws:
                first: dict[str, Any] = ws.receive_json()
                if first["type"] == "error":
                    with pytest.raises(WebSocketDisconnect) as closed:
                        ws.receive_json()
                    first["close"] = (closed.value.code, closed.value.reason)
                return first

        assert api.get("/api/v1/machines", "a").status_code == 200  # REST and live: one bucket
        assert [connect("a")["type"] for _ in range(2)] == ["hello", "hello"]
        refused = connect("a")
        assert refused["status"] == 429 and refused["title"] == "Too many requests"
        assert refused["close"] == (4429, "Too many requests")
        assert refused["retry_after"] >= 1
        assert api.get("/api/v1/machines", "a").status_code == 429  # the connects were charged
        assert connect("b")["type"] == "hello"  # another key: its own bucket
        text = api.get("/metrics", "admin").text
        assert _metric(text, 'cranetwin_http_refused_total{reason="rate_limit",role="viewer"}') \
            == 2
