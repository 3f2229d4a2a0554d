"""Several ingest hosts behind a UDP load balancer, on one box (``cranetwin.testing.netns``).

Namespaces ``fleet`` → ``lb`` → ``hostA`` | ``hostB``: journaled senders in ``fleet`` stream to a
virtual IP on ``lb``, which DNATs each flow by a hash of (source address . source port) to one
``cranetwin ingest`` daemon per host; acks return through ``lb``; both daemons write to one fresh
PostgreSQL database through a TCP relay in the root namespace. Then ``kill -9`` of hostB's daemon
mid-stream and hostB out of the balancer: hostB's machines finish through hostA (their journals
retransmit), hostA's machines never move, every sample is stored exactly once.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from sqlalchemy import text

from conftest import SECRET, _pg_conninfo, pg_unreachable_reason
from cranetwin.bench.chaos import TcpProxy
from cranetwin.bench.ingest_daemon import DaemonProcess, start_daemon
from cranetwin.storage import Store
from cranetwin.testing.netns import HOSTS, VIP, Topology, unavailable_reason
from test_ingest_reliability import registered

PORT = 9000
WIRE_IDS = list(range(1, 13))  # 12 flows: all on one host by chance with p = 2/4096

FLEET = """
import asyncio, json, sys
from cranetwin.bench.ingest import patu_layout
from cranetwin.ingest.sender import SyntheticSource, run_fleet
from cranetwin.protocol import MachineKey
a = json.loads(sys.argv[1])
layout = patu_layout()
keys = [MachineKey(w, f"crane-{w}", a["secret"].encode(), layout) for w in a["wire_ids"]]
stats = asyncio.run(run_fleet(
    keys, (a["vip"], a["port"]), [SyntheticSource(k, seed=k.wire_id) for k in keys],
    journal_dir=a["journal"], fsync=False, speed=a["speed"], duration_s=a["duration_s"],
    max_unacked=16, min_rto_s=0.3, max_rto_s=2.0, drain_timeout_s=120, status_every_s=0))
print(json.dumps([vars(s) for s in stats]))
"""


@pytest.fixture
def fresh_database() -> Iterator[str]:
    """The name of a fresh PostgreSQL database (dropped afterwards)."""
    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    import psycopg

    name = f"h_netns_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    yield name
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture
def topology() -> Iterator[Topology]:
    reason = unavailable_reason()
    if reason:
        pytest.skip(reason)
    topo = Topology(PORT, WIRE_IDS).build()
    try:
        yield topo
    finally:
        topo.close()


def _seqs(store: Store, w: int) -> list[int]:
    with store.engine.connect() as c:
        return [int(r[0]) for r in c.execute(text(
            "SELECT b.seq FROM sample_blocks b JOIN machines m ON m.id = b.machine_pk "
            "WHERE m.wire_id = :w ORDER BY b.seq"), {"w": w})]


def _wait(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, what
        time.sleep(0.2)


@pytest.mark.slow
@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_two_hosts_behind_a_udp_balancer_lose_move_and_double_nothing(
        topology: Topology, fresh_database: str, tmp_path: Path) -> None:
    pg = _pg_conninfo().rsplit("/", 1)[0].replace("postgresql://", "postgresql+psycopg://", 1)
    store = registered(f"{pg}/{fresh_database}", WIRE_IDS)
    proxy = TcpProxy(("127.0.0.1", 5432), bind=topology.root_ip)
    url = f"postgresql+psycopg://postgres@{topology.root_ip}:{proxy.port}/{fresh_database}"
    daemons: dict[str, DaemonProcess] = {}
    fleet: subprocess.Popen[bytes] | None = None
    try:
        with ThreadPoolExecutor(2) as pool:  # both at once: each imports for 5-60 s under load
            started = {h: pool.submit(start_daemon, url, PORT, tmp_path, host=ip,
                                      prefix=topology.prefix(f"host{h}"), ready_timeout_s=90)
                       for h, ip in HOSTS.items()}
            failed = []
            for h, job in started.items():
                try:
                    daemons[h] = job.result()
                except RuntimeError as exc:  # kill the other one below, then report
                    failed.append(f"host{h}: {exc}")
        assert not failed, failed
        topology.short_udp_timeouts(1)
        args = {"secret": SECRET.decode(), "wire_ids": WIRE_IDS, "vip": VIP, "port": PORT,
                "journal": str(tmp_path / "journals"), "speed": 4.0, "duration_s": 60.0}
        t0 = time.monotonic()
        with open(tmp_path / "fleet.stderr", "wb") as err:
            fleet = subprocess.Popen([*topology.prefix("fleet"), sys.executable, "-c", FLEET,
                                      json.dumps(args)], stdout=subprocess.PIPE, stderr=err)
        _wait(lambda: all(len(_seqs(store, w)) >= 5 for w in WIRE_IDS), 60,
              "not every machine got blocks stored through the balancer")
        placed = topology.counts()
        host_of = {}
        for w, per_host in placed.items():  # a machine's datagrams land on one host
            assert sorted(per_host.values())[0] == 0 < sorted(per_host.values())[1], (w, placed)
            host_of[w] = max(per_host, key=lambda h: per_host[h])
        on_a = [w for w in WIRE_IDS if host_of[w] == "A"]
        on_b = [w for w in WIRE_IDS if host_of[w] == "B"]
        assert on_a and on_b, f"the hash put every machine on one host: {host_of}"

        os.kill(daemons["B"].pid, signal.SIGKILL)  # no flush, no goodbye
        daemons["B"].proc.wait(10)
        stored_by_b = {w: _seqs(store, w) for w in on_b}  # all hostB ever committed
        assert all(stored_by_b.values())
        topology.set_backends(["A"])  # the health checker takes hostB out

        out, _ = fleet.communicate(timeout=120)
        wall_s = time.monotonic() - t0
        assert fleet.returncode == 0, (tmp_path / "fleet.stderr").read_text()[-2000:]
        stats = {s["machine_id"]: s for s in json.loads(out)}
        final = daemons["A"].stop(60)
        moved = topology.counts()
    finally:
        if fleet is not None and fleet.poll() is None:
            fleet.kill()
            fleet.wait(10)
        for d in daemons.values():
            if d.poll() is None:
                d.kill()
        proxy.close()

    total = 0
    for w in WIRE_IDS:
        s = stats[f"crane-{w}"]
        assert s["unacked"] == 0 and s["refused"] == 0, s
        assert s["acked_samples"] == s["samples"] > 0
        seqs = _seqs(store, w)
        assert seqs == list(range(len(seqs))), f"crane-{w}: a block lost or doubled"
        assert store.stats(f"crane-{w}").samples == s["samples"], f"crane-{w}"
        total += s["samples"]
    for w in on_a:  # never moved
        assert moved[w]["B"] == 0 and moved[w]["A"] > placed[w]["A"], (w, moved[w])
    for w in on_b:  # finished through hostA, after what hostB had stored
        assert moved[w]["A"] > 0, (w, moved[w])
        assert set(stored_by_b[w]) <= set(_seqs(store, w))
    blocks = {w: len(_seqs(store, w)) for w in WIRE_IDS}
    by_a = sum(blocks[w] for w in on_a) + sum(blocks[w] - len(stored_by_b[w]) for w in on_b)
    assert final["stored_blocks"] == by_a, (final, by_a)
    store.close()
    print(json.dumps({"samples": total, "wall_s": round(wall_s, 1), "machines": {
        "A": len(on_a), "B": len(on_b)}, "blocks_stored": {
        "A": by_a, "B": sum(len(v) for v in stored_by_b.values())},
        "datagrams": {h: sum(c[h] for c in moved.values()) for h in HOSTS},
        "retransmissions": sum(s["retransmissions"] for s in stats.values())}))
