"""Fleet bus under faults, with real processes and the real NATS server:

* ``cranetwin store-writer`` killed with SIGKILL mid-stream and restarted, while blocks (with
  retransmissions) keep being published: every acknowledged block stored exactly once
  (PostgreSQL);
* the ingest daemon writing to JetStream acknowledges nothing while NATS is down (a private
  ``nats-server`` stopped under it), and everything once it is back; after a SIGKILL of the NATS
  server, what was acknowledged is still in the stream and gets stored.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import SECRET, running_daemon
from cranetwin.bus.sink import JetStreamStore
from cranetwin.bus.subjects import BusConfig
from cranetwin.storage import Store
from test_bus import (
    block,
    delete_stream,
    fresh_bus,
    nats_unreachable_reason,
    run_writer,
    stored_keys,
)
from test_ingest_daemon import drive, grid_values, make_sender

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]
SRC = Path(__file__).resolve().parents[1] / "src"


# --- a storage writer process ------------------------------------------------------------------
def _env(cfg: BusConfig) -> dict[str, str]:
    env = dict(os.environ)
    env.update({"PYTHONPATH": f"{SRC}{os.pathsep}{env.get('PYTHONPATH', '')}",
                "CRANETWIN_BUS_STREAM": cfg.stream, "CRANETWIN_BUS_PREFIX": cfg.prefix,
                "CRANETWIN_BUS_PARTITIONS": str(cfg.partitions),
                "CRANETWIN_BUS_ACK_WAIT_S": str(cfg.ack_wait_s)})
    return env


def start_writer(cfg: BusConfig, db_url: str, log: Path) -> subprocess.Popen[bytes]:
    """``cranetwin store-writer`` in a subprocess; returns once its ready line is printed."""
    cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "store-writer",
           "--bus", cfg.url, "--db", db_url, "--batch-max", "100", "--log-level", "WARNING"]
    with open(log, "ab") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, env=_env(cfg))
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    line = proc.stdout.readline() if ready else b""
    if not line.startswith(b'{"event": "ready"'):
        proc.kill()
        proc.wait(10)
        raise AssertionError(f"store-writer did not start: {line!r} {log.read_text()[-2000:]}")
    return proc


def stop_writer(proc: subprocess.Popen[bytes]) -> dict[str, Any]:
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    lines = [json.loads(x) for x in out.decode().splitlines() if x.startswith("{")]
    return next(x for x in lines if x.get("event") == "stopped")


@pytest.fixture
def bus() -> Iterator[BusConfig]:
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    cfg = fresh_bus(partitions=4, ack_wait_s=1.0)
    yield cfg
    delete_stream(cfg)


@pytest.mark.postgres
def test_store_writer_killed_mid_stream_stores_every_acked_block_exactly_once(
        bus: BusConfig, pg_url: str, tmp_path: Path) -> None:
    machines = [f"crane-{w}" for w in range(1, 9)]
    sink = JetStreamStore.open_bus(pg_url, bus)
    for w, m in enumerate(machines, 1):
        sink.add_machine(m, w, SECRET)
    per_machine = 150
    blocks = {m: [block(m, s, n=20) for s in range(per_machine)] for m in machines}
    acked: set[tuple[str, int, int]] = set()
    published = threading.Event()
    errors: list[BaseException] = []

    def publish() -> None:
        """Batches of 40 new blocks plus 10 retransmitted ones, as a daemon would publish."""
        rng = random.Random(5)
        order = [b for s in range(per_machine) for m in machines for b in [blocks[m][s]]]
        sent: list[Any] = []
        try:
            for i in range(0, len(order), 40):
                batch = order[i:i + 40] + rng.sample(sent, min(10, len(sent)))
                res = sink.write_batch(batch)
                acked.update((b.machine_id, b.epoch, b.seq) for b, o in res if o.durable)
                sent.extend(order[i:i + 40])
                time.sleep(0.02)
        except BaseException as exc:
            errors.append(exc)
        finally:
            published.set()

    store = Store.open(pg_url)
    writer = start_writer(bus, pg_url, tmp_path / "writer.log")
    t = threading.Thread(target=publish)
    t.start()
    try:
        end = time.monotonic() + 60
        while store.stats().blocks < 200 and time.monotonic() < end:
            time.sleep(0.02)
        assert store.stats().blocks >= 200, "the writer stored nothing"
        writer.kill()  # SIGKILL mid-stream: a batch may be committed and not acked
        writer.wait(10)
        killed_at = store.stats().blocks
        time.sleep(0.5)  # publishing goes on while no writer runs
        writer = start_writer(bus, pg_url, tmp_path / "writer.log")
        assert published.wait(120)
        t.join(10)
        assert not errors, errors
        total = len(machines) * per_machine
        assert len(acked) == total
        end = time.monotonic() + 90
        while store.stats().blocks < total and time.monotonic() < end:
            time.sleep(0.1)
        counters = stop_writer(writer)
        assert killed_at < total, "the kill was not mid-stream"
        keys = stored_keys(store, machines)
        assert len(keys) == len(set(keys)) == total, "lost or doubled blocks"
        assert set(keys) == acked
        assert counters["refused"] == {} and counters["bad_messages"] == 0
        for m in machines:
            got = store.read_samples(m, 0, 4e9)
            want = np.concatenate([b.values for b in blocks[m]])
            assert np.array_equal(got.values, want), m
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait(10)
        t.join(30)
        store.close()
        sink.close()


# --- a private NATS server that the test may stop -----------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class PrivateNats:
    """``nats-server -js`` on a free loopback port with its own store directory."""

    def __init__(self, store_dir: Path) -> None:
        exe = shutil.which("nats-server")
        if exe is None:
            pytest.skip("nats-server is not installed")
        self.exe = exe
        self.port = _free_port()
        self.store_dir = store_dir
        self.url = f"nats://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [self.exe, "-a", "127.0.0.1", "-p", str(self.port), "-js", "-sd",
             str(self.store_dir)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        end = time.monotonic() + 20
        while time.monotonic() < end:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port),
                                                                         0.2):
                if nats_unreachable_reason(self.url) is None:
                    return
            time.sleep(0.05)
        raise AssertionError("private nats-server did not start")

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(20)
        self.proc = None


@pytest.fixture
def private_nats(tmp_path: Path) -> Iterator[PrivateNats]:
    srv = PrivateNats(tmp_path / "js")
    srv.start()
    yield srv
    srv.stop(signal.SIGKILL)


def test_daemon_acks_only_after_the_pubAck_and_acked_blocks_survive_a_nats_crash(
        private_nats: PrivateNats, sqlite_url: str) -> None:
    cfg = BusConfig(url=private_nats.url, stream="CT_OUTAGE", prefix="ctoutage.blocks",
                    partitions=2, publish_timeout_s=0.5, ack_wait_s=1.0)
    sink = JetStreamStore.open_bus(sqlite_url, cfg)
    sink.add_machine("crane-1", 1, SECRET)
    sink.add_machine("crane-2", 2, SECRET)
    values, values2 = grid_values(600, 1), grid_values(400, 2)
    sender = make_sender(1, values, batch_samples=50)
    with running_daemon(sink, retry_max_s=0.3, retry_min_s=0.05) as daemon:
        # NATS down before anything is sent: the daemon retries, acknowledges nothing
        private_nats.stop()
        assert not drive([sender], daemon.address, timeout_s=4.0)
        snap = daemon.snapshot()
        assert snap["accepted"] > 0 and snap["acks_sent"] == 0
        assert sender.acked_samples == 0 and daemon.storage_outage
        # back: everything is acknowledged, once the PubAcks are in
        private_nats.start()
        assert drive([sender], daemon.address, timeout_s=60.0)
        assert sender.acked_samples == 600 and not daemon.storage_outage
        # down again while connected (nats-py reconnecting): no ack until it is back
        stored = daemon.snapshot()["stored_blocks"]
        private_nats.stop()
        second = make_sender(2, values2, batch_samples=50)
        assert not drive([second], daemon.address, timeout_s=4.0)
        # nothing of the second machine published or acknowledged (a late retransmission of
        # the first machine's may still be re-acked: it is already durable)
        assert second.acked_samples == 0 and daemon.snapshot()["stored_blocks"] == stored
        private_nats.start()
        assert drive([second], daemon.address, timeout_s=60.0)
        assert second.acked_samples == 400
    sink.close()
    # the server dies hard after the acks: the acknowledged blocks are in its file store
    private_nats.stop(signal.SIGKILL)
    private_nats.start()
    store = Store.open(sqlite_url)
    try:
        run_writer(store, cfg, until=lambda: store.stats().samples >= 1000, timeout_s=60)
        assert np.array_equal(store.read_samples("crane-1", 0, 4e9).values, values)
        assert np.array_equal(store.read_samples("crane-2", 0, 4e9).values, values2)
        assert store.stats().samples == 1000
    finally:
        store.close()
