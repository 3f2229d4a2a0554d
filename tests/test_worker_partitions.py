"""Twin workers as a scaled-out service: machine partitions owned exclusively through PostgreSQL
advisory locks, rebalanced when a worker joins or dies (kill -9), every window processed exactly
once (the counters equal a single worker's), lag per partition on the metrics endpoint."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import pytest

from cranetwin.model import load_machine
from cranetwin.service.backend import Backend
from cranetwin.service.ownership import (
    Ownership,
    PartitionSpec,
    PartitionSpecError,
    parse_partitions,
    partition_of,
)
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage.engine import make_engine
from cranetwin.storage.locks import SessionLocks
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole minute
P = 4


# --- the partition spec and the hash ------------------------------------------------------------
def test_parse_partitions() -> None:
    assert parse_partitions("auto", 8) == PartitionSpec(8, None)
    assert parse_partitions("auto") == PartitionSpec(16, None)
    assert parse_partitions("2/4") == PartitionSpec(4, (2,))
    assert parse_partitions("0,3,5", 8) == PartitionSpec(8, (0, 3, 5))
    assert parse_partitions("all", 3) == PartitionSpec(3, (0, 1, 2))
    for bad, of in (("4/4", None), ("1/4", 8), ("0,9", 8), ("x", 8), ("0,1", None), ("", 8),
                    ("auto", 0)):
        with pytest.raises(PartitionSpecError):
            parse_partitions(bad, of)


def test_partition_of_is_stable_and_spreads() -> None:
    # fixed values: the hash must never change between releases (workers of two versions)
    assert partition_of("crane-0", 16) == 14 and partition_of("crane-1", 1024) == 780
    counts = [0] * 16
    for i in range(16_000):
        counts[partition_of(f"m{i}", 16)] += 1
    assert min(counts) > 850 and max(counts) < 1150


# --- ownership in one process: two sessions -----------------------------------------------------
@pytest.mark.postgres
@pytest.mark.timeout(60)
def test_ownership_rebalances_between_sessions(pg_url: str) -> None:
    ea, eb, ec = make_engine(pg_url), make_engine(pg_url), make_engine(pg_url)
    a, b = Ownership(PartitionSpec(P, None), ea), Ownership(PartitionSpec(P, None), eb)
    assert a.refresh() == {0, 1, 2, 3}  # alone: everything
    assert b.refresh() == set()  # joins: nothing free yet
    assert a.refresh() == {0, 1}  # two members: A gives up its highest half
    assert b.refresh() == {2, 3}
    assert a.refresh() == {0, 1} and b.refresh() == {2, 3}  # stable
    fixed = Ownership(PartitionSpec(P, (1, 2)), ec)
    assert fixed.refresh() == set()  # held by others: it waits
    a.close()  # A leaves: its locks go with its session
    assert fixed.refresh() == {1}
    assert b.refresh() == {0, 2, 3}  # B takes what the fixed worker does not hold
    b.close()
    assert fixed.refresh() == {1, 2}
    fixed.close()
    for e in (ea, eb, ec):
        e.dispose()


def test_ownership_on_sqlite_needs_no_locks(sqlite_url: str) -> None:
    e = make_engine(sqlite_url)
    own = Ownership(parse_partitions("1,3", 4), e)
    assert not own.locked and own.refresh() == {1, 3}
    assert Ownership(parse_partitions("auto", 4), e).refresh() == {0, 1, 2, 3}
    e.dispose()


# --- real processes -----------------------------------------------------------------------------
def _machines() -> list[str]:
    """One machine id per partition."""
    out: list[str] = []
    per = [0] * P
    i = 0
    while len(out) < P:
        mid = f"crane-{i:02d}"
        p = partition_of(mid, P)
        if per[p] < 1:
            per[p] += 1
            out.append(mid)
        i += 1
    return out


def _fill(b: Backend, ids: list[str], start_s: float, dur_s: float, seq0: int) -> None:
    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    for mid in ids:
        b.store.write_blocks(list(tiled_blocks(mid, machine, T0 + start_s, dur_s, 1.0,
                                               base=base, seq0=seq0, origin_s=T0)))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def spawn(pg_url: str, tmp_path: Path) -> Iterator[object]:
    procs: list[subprocess.Popen[str]] = []

    def start(port: int) -> subprocess.Popen[str]:
        err = (tmp_path / f"worker-{port}.log").open("w")
        env = {**os.environ, "CRANETWIN_WORKER_INTERVAL_S": "0.2"}
        env.pop("CRANETWIN_DATABASE_URL", None)
        p = subprocess.Popen(
            [sys.executable, "-c", "from cranetwin.cli import main; main()", "worker",
             "--db", pg_url, "--partitions", "auto", "--of", str(P), "--quiet-s", "1e6",
             "--metrics-bind", f"127.0.0.1:{port}", "--log-level", "info"],
            stdout=subprocess.PIPE, stderr=err, text=True, env=env)
        procs.append(p)
        assert p.stdout is not None
        ready, _, _ = select.select([p.stdout], [], [], 90.0)
        line = p.stdout.readline() if ready else ""
        assert line.startswith("cranetwin worker ready") and "partitions auto of 4" in line, line
        return p

    yield start
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(30)


def _owners(locks: SessionLocks) -> dict[int, set[int]]:
    """Server pid → partitions it holds."""
    ns = locks.namespace(f"cranetwin.worker.partition/{P}")
    out: dict[int, set[int]] = {}
    for h in locks.holders([ns]):
        out.setdefault(h.pid, set()).add(h.key)
    return out


def _wait(cond: object, timeout_s: float, what: str) -> float:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():  # type: ignore[operator]
            return time.monotonic() - t0
        time.sleep(0.1)
    raise AssertionError(f"not within {timeout_s} s: {what}")


def _watermarks(b: Backend, ids: list[str]) -> list[float | None]:
    return [None if (p := b.progress(m)) is None else p.watermark_s for m in ids]


@pytest.mark.postgres
@pytest.mark.timeout(420)
def test_two_workers_split_partitions_and_survive_kill_9(pg_url: str, spawn: object,
                                                         tmp_path: Path) -> None:
    ids = _machines()
    b = Backend.open(pg_url)
    for i, mid in enumerate(ids):
        b.store.add_machine(mid, wire_id=i + 1, secret=b"s" * 32)
    _fill(b, ids, 0.0, 150.0, 0)  # windows [0, 60) and [60, 120) are ready
    locks = SessionLocks(b.store.engine)
    port_a, port_b = _free_port(), _free_port()
    a = spawn(port_a)  # type: ignore[operator]
    _wait(lambda: list(_owners(locks).values()) == [set(range(P))], 60, "A owns all")
    a_pid = next(iter(_owners(locks)))
    # A is warm (its first replay compiles or loads the twin: up to a minute on a busy host)
    _wait(lambda: any(w is not None for w in _watermarks(b, ids)), 180, "A replays")
    bw = spawn(port_b)  # type: ignore[operator]
    _wait(lambda: sorted(len(v) for v in _owners(locks).values()) == [2, 2], 120,
          "A and B own two partitions each")
    owners = list(_owners(locks).values())
    assert owners[0].isdisjoint(owners[1]) and owners[0] | owners[1] == set(range(P))
    _wait(lambda: _watermarks(b, ids) == [T0 + 120] * len(ids), 240, "phase 1 processed")

    def scrape() -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{port_b}/metrics", timeout=10) as r:
            return str(r.read().decode())

    _wait(lambda: "cranetwin_worker_partitions_owned 2.0" in scrape(), 120, "B's gauges")
    lag = {ln.split('"')[1]: float(ln.split()[-1]) for ln in scrape().splitlines()
           if ln.startswith("cranetwin_worker_partition_lag_seconds{")}
    assert {int(k) for k in lag} == next(v for k, v in _owners(locks).items() if k != a_pid)
    assert all(0 < v <= 30 for v in lag.values()), lag  # data to T0+150, watermark T0+120

    # more data for every machine; A is killed once it is busy with its share of it (most
    # likely inside a window: its transaction is rolled back and B does the window again)
    a_ids = [m for m in ids if partition_of(m, P) in _owners(locks)[a_pid]]
    _fill(b, ids, 150.0, 120.0, 150)
    _wait(lambda: any(w is not None and w > T0 + 120 for w in _watermarks(b, a_ids)), 120,
          "A works on the new data")
    a.send_signal(signal.SIGKILL)  # type: ignore[attr-defined]
    a.wait(30)  # type: ignore[attr-defined]
    took = _wait(lambda: list(_owners(locks).values()) == [set(range(P))], 60,
                 "B takes A's partitions")
    _wait(lambda: _watermarks(b, ids) == [T0 + 240] * len(ids), 240, "phase 2 processed")
    got = {m: asdict(p) for m in ids if (p := b.progress(m)) is not None}
    assert bw.poll() is None  # type: ignore[attr-defined]

    # the same data through one worker, in one go
    ref = Backend.open(f"sqlite:///{tmp_path / 'ref.db'}")
    for i, mid in enumerate(ids):
        ref.store.add_machine(mid, wire_id=i + 1, secret=b"s" * 32)
    _fill(ref, ids, 0.0, 270.0, 0)
    w = TwinWorker(ref, Settings(database_url="unused"), quiet_s=1e6)
    while w.run_once():
        pass
    want = {m: asdict(p) for m in ids if (p := ref.progress(m)) is not None}
    assert set(got) == set(want) == set(ids)
    for m in ids:
        assert got[m]["windows"] == want[m]["windows"] == 4, m
        floats = {k for k, v in want[m].items() if isinstance(v, float)}
        assert {k: v for k, v in got[m].items() if k not in floats} == {
            k: v for k, v in want[m].items() if k not in floats}, m
        assert {k: got[m][k] for k in floats} == pytest.approx(
            {k: want[m][k] for k in floats}, rel=1e-9, abs=1e-9), m
    print(f"takeover after kill -9: {took:.1f} s")
    ref.close()
    locks.close()
    b.close()
