"""``cranetwin bench mqtt``: samples stored per second and CPU per sample of the MQTT ingest
adapter, against the storage write alone, in the same run.

One fresh SQLite file per path, the same blocks (random on-grid samples of the PATU 655 inside
every sensor range, ``--machines`` machines × ``--blocks`` blocks of ``--samples`` samples):

* **direct** (the baseline): ``Store.write_batch`` of the blocks in batches of
  ``--batch-max``, in this process; CPU is this process's time in the writes;
* **mqtt**: ``cranetwin mqtt-ingest`` as a process (its own Sparkplug group and session) and
  an edge node in this process publishing every block as Sparkplug B DDATA (QoS 1) to the
  broker; the run ends when every sample is in the database. CPU is the adapter process's
  user + system time (``/proc``) from its ready line to the end: decoding, validation, the
  writes and the MQTT client; the broker's and the publisher's CPU are in neither figure.

``mqtt_cpu_us_per_sample`` over ``direct_cpu_us_per_sample`` is what the MQTT path costs per
sample on top of the storage write; every sample is read back and compared exactly.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import typer

from cranetwin import codec
from cranetwin.bench import emit
from cranetwin.bench.ingest_daemon import cpu_seconds
from cranetwin.protocol import Layout
from cranetwin.protocol.machine import layout_of
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store

SECRET = b"bench-secret-0123456789abcdef"


def make_blocks(layout: Layout, machines: int, blocks: int, samples: int) -> list[SampleBlock]:
    """Blocks of random on-grid values inside every channel's range, 100 Hz, an hour ago."""
    rng = np.random.default_rng(0)
    lo = np.array([c.min for c in layout.channels])
    hi = np.array([c.max for c in layout.channels])
    t0 = (time.time_ns() // 10**9 - 3600) * 10**9
    out = []
    for s in range(blocks):
        for m in range(machines):
            v = codec.on_grid(lo + (hi - lo) * rng.random((samples, len(lo))),
                              layout.resolutions)
            out.append(SampleBlock(f"bench-{m}", s, t0 + s * samples * 10_000_000, 10_000_000,
                                   layout.names, layout.resolutions, v, epoch=1))
    return out


def _fresh_store(path: Path, machines: int) -> Store:
    store = Store.open(f"sqlite:///{path}")
    for m in range(machines):
        store.add_machine(f"bench-{m}", 9000 + m, SECRET)
    return store


def _check(store: Store, blocks: list[SampleBlock], machines: int) -> bool:
    for m in range(machines):
        mine = [b for b in blocks if b.machine_id == f"bench-{m}"]
        got = store.read_samples(f"bench-{m}", 0.0, 4e9)
        if not np.array_equal(got.values, np.concatenate([b.values for b in mine])):
            return False
    return True


def _direct(path: Path, blocks: list[SampleBlock], machines: int,
            batch_max: int) -> dict[str, Any]:
    store = _fresh_store(path, machines)
    try:
        cpu0, t0 = time.process_time(), time.perf_counter()
        for i in range(0, len(blocks), batch_max):
            store.write_batch(blocks[i:i + batch_max])
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - t0
        return {"cpu_s": cpu, "wall_s": wall, "exact": _check(store, blocks, machines)}
    finally:
        store.close()


def _mqtt(path: Path, blocks: list[SampleBlock], machines: int, batch_max: int,
          broker: tuple[str, int]) -> dict[str, Any]:
    from cranetwin.ingest.mqtt_edge import EdgePublisher

    store = _fresh_store(path, machines)
    group = f"bench{uuid.uuid4().hex[:8]}"
    cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "mqtt-ingest",
           "--broker", f"mqtt://{broker[0]}:{broker[1]}", "--group", group, "--client-id",
           f"bench-{group}", "--db", f"sqlite:///{path}", "--batch-max", str(batch_max),
           "--log-level", "WARNING"]
    env = {**os.environ, "CRANETWIN_MQTT_SESSION_EXPIRY_S": "30"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 120)
        if not ready or not proc.stdout.readline().startswith(b'{"event": "ready"'):
            raise RuntimeError("mqtt-ingest did not start")
        layout = layout_of("patu655")
        pub = EdgePublisher(broker[0], broker[1], group, "bench-edge",
                            {f"bench-{m}": layout for m in range(machines)})
        cpu0, t0 = cpu_seconds(proc.pid) or 0.0, time.perf_counter()
        try:
            pub.publish_all(blocks, timeout_s=300)
            deadline = time.monotonic() + 300
            while store.stats().blocks < len(blocks) and time.monotonic() < deadline:
                time.sleep(0.02)
            wall = time.perf_counter() - t0
            cpu = (cpu_seconds(proc.pid) or 0.0) - cpu0
        finally:
            pub.close()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
        final = json.loads(out.decode().splitlines()[-1])
        return {"cpu_s": cpu, "wall_s": wall, "exact": _check(store, blocks, machines),
                "stored_samples": final["stored_samples"], "dropped": final["dropped"]}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        store.close()


def run_bench(machines: int = 4, blocks: int = 100, samples: int = 100, batch_max: int = 1000,
              broker: tuple[str, int] = ("127.0.0.1", 1883)) -> dict[str, Any]:
    """Both paths over the same blocks; the figures of the module docstring."""
    data = make_blocks(layout_of("patu655"), machines, blocks, samples)
    n = sum(b.n for b in data)
    with tempfile.TemporaryDirectory(prefix="cranetwin-bench-mqtt-") as tmp:
        direct = _direct(Path(tmp) / "direct.db", data, machines, batch_max)
        mqtt = _mqtt(Path(tmp) / "mqtt.db", data, machines, batch_max, broker)
    return {
        "samples": n, "blocks": len(data), "samples_per_block": samples,
        "direct_samples_per_s": round(n / direct["wall_s"]),
        "direct_cpu_us_per_sample": round(direct["cpu_s"] / n * 1e6, 3),
        "mqtt_samples_per_s": round(n / mqtt["wall_s"]),
        "mqtt_cpu_us_per_sample": round(mqtt["cpu_s"] / n * 1e6, 3),
        "mqtt_cpu_ratio_vs_direct": round(mqtt["cpu_s"] / max(direct["cpu_s"], 1e-9), 2),
        "mqtt_stored_samples": mqtt["stored_samples"], "mqtt_dropped": mqtt["dropped"],
        "exact": bool(direct["exact"] and mqtt["exact"]),
    }


def mqtt(
    machines: int = typer.Option(4, min=1, help="Machines (Sparkplug devices)."),
    blocks: int = typer.Option(100, min=1, help="Blocks per machine."),
    samples: int = typer.Option(100, min=1, help="Samples per block (DDATA)."),
    batch_max: int = typer.Option(1000, min=1, help="Blocks per transaction at most."),
    broker: str = typer.Option("127.0.0.1:1883", help="MQTT broker HOST:PORT."),
    json_out: bool = typer.Option(False, "--json", help="One JSON object."),
) -> None:
    """MQTT adapter: samples/s and CPU per sample against Store.write_batch alone."""
    host, _, port = broker.rpartition(":")
    emit(run_bench(machines, blocks, samples, batch_max, (host, int(port))), json_out)


def register(bench_app: typer.Typer) -> None:
    bench_app.command("mqtt")(mqtt)
