"""``cranetwin bench protocol``: wire size and codec speed of the protocol on simulated data.

Signal: the simulator's ``log-loading`` work cycle on the built-in PATU 655 (11 channels at
100 Hz, sensor noise, bias and dropouts), or ``--synthetic`` smooth motion + noise.

Figures: UDP payload bytes per sample (our headers and HMAC tags included; IPv4 + UDP headers
reported separately), losslessness at sensor resolution, largest datagram, and encode / decode /
receive (decode + HMAC + replay window) throughput in samples per second on one core.

Baseline, in the same run and with the same header, HMAC tag and batch length: each sample as
11 big-endian float32 values (the uncompressed layout a straightforward sender would use; the
paper's stream needs ≈ 62 bytes/sample). Ratios: ``size_ratio`` = baseline bytes / ours, and
``decode_slowdown`` = our decode time / baseline decode time (``np.frombuffer``).
"""

from __future__ import annotations

import time
from typing import Any

import typer

from cranetwin.bench import emit

PAPER_BYTES_PER_SAMPLE = 62.0


def run(seconds: float = 60.0, batch: int = 50, synthetic: bool = False,
        reps: int = 3) -> dict[str, Any]:
    """Measure; return the figures as a dict (see module docstring)."""
    import numpy as np

    from cranetwin.ingest.sender import SyntheticSource, simulator_source
    from cranetwin.model import load_machine
    from cranetwin.protocol import (
        IP_UDP_OVERHEAD_V4,
        Layout,
        MachineKey,
        Receiver,
        decode_data,
        encode_data,
        measure_bytes_per_sample,
    )
    from cranetwin.protocol.wire import HEADER_BYTES, tag

    machine = load_machine("patu655")
    key = MachineKey(1, "bench", b"b" * 32, Layout.from_channels(machine.channels))
    period_ns = 10_000_000
    if synthetic:
        values = SyntheticSource(key, 0.01, seed=1).read(0, int(seconds * 100))
        source = "synthetic"
    else:
        values, period_s = simulator_source(key, machine, "log-loading", duration_s=seconds)
        period_ns = int(round(period_s * 1e9))
        source = "sim:log-loading"
    n = values.shape[0]
    stats = measure_bytes_per_sample(key, values, period_ns, batch_samples=batch)

    chunks = [values[i:i + batch] for i in range(0, n, batch)]
    best_enc = best_dec = best_rx = best_base = float("inf")
    dgs: list[bytes] = []
    base: list[bytes] = []
    for _ in range(reps):
        t0 = time.perf_counter()
        dgs = [encode_data(key, s, s * batch * period_ns, period_ns, c)
               for s, c in enumerate(chunks)]
        best_enc = min(best_enc, time.perf_counter() - t0)
        t0 = time.perf_counter()
        for d in dgs:
            decode_data(d, key)
        best_dec = min(best_dec, time.perf_counter() - t0)
        rx = Receiver({1: key})
        t0 = time.perf_counter()
        for d in dgs:
            rx.receive(d, 0)
        best_rx = min(best_rx, time.perf_counter() - t0)
        # baseline: the same fixed header (46 bytes) + tag, float32 payload
        head = dgs[0][:HEADER_BYTES + 30]
        base = []
        for c in chunks:
            body = head + c.astype(">f4").tobytes()
            base.append(body + tag(key.secret, body))
        t0 = time.perf_counter()
        for b in base:
            if tag(key.secret, b[:-16]) == b[-16:]:
                np.frombuffer(b[HEADER_BYTES + 30:-16], dtype=">f4").reshape(-1, 11)
        best_base = min(best_base, time.perf_counter() - t0)
    base_bps = sum(len(b) for b in base) / n
    return {
        "source": source,
        "samples": n,
        "channels": values.shape[1],
        "rate_hz": 1e9 / period_ns,
        "batch_samples": batch,
        "datagrams": stats.datagrams,
        "bytes_per_sample": round(stats.bytes_per_sample, 3),
        "ip_udp_bytes_per_sample": round(stats.ip_udp_bytes_per_sample, 3),
        "max_datagram_bytes": stats.max_datagram_bytes,
        "lossless": stats.lossless,
        "target_bytes_per_sample": 20.0,
        "paper_bytes_per_sample": PAPER_BYTES_PER_SAMPLE,
        "baseline": "float32 per value, same header/HMAC/batch",
        "baseline_bytes_per_sample": round(base_bps, 3),
        "size_ratio": round(base_bps / stats.bytes_per_sample, 2),
        "paper_ratio": round(PAPER_BYTES_PER_SAMPLE / stats.bytes_per_sample, 2),
        "bandwidth_kbit_s_per_machine": round(
            (stats.bytes_per_sample + IP_UDP_OVERHEAD_V4 * stats.datagrams / n) * 8
            * 1e9 / period_ns / 1e3, 2),
        "encode_samples_per_second": round(n / best_enc),
        "decode_samples_per_second": round(n / best_dec),
        "receive_samples_per_second": round(n / best_rx),
        "baseline_decode_samples_per_second": round(n / best_base),
        "decode_slowdown": round(best_dec / best_base, 2),
    }


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("protocol")
    def protocol_bench(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        seconds: float = typer.Option(60.0, help="Seconds of 100 Hz data to encode."),
        batch: int = typer.Option(50, help="Samples per datagram."),
        synthetic: bool = typer.Option(False, help="Synthetic motion instead of the simulator."),
        reps: int = typer.Option(3, help="Repetitions; the best time is reported."),
    ) -> None:
        """Wire size (bytes/sample) and codec speed vs. a float32 baseline."""
        out = run(seconds, batch, synthetic, reps)
        emit(out, as_json)
