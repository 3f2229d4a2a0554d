"""``cranetwin send``: stream a (simulated) machine's sensor samples to an ingest daemon."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
from pathlib import Path

import typer

from cranetwin.errors import CraneTwinError

KEY_ENV = "CRANETWIN_MACHINE_KEY"


def parse_key(text: str) -> bytes:
    """A secret given as hex (≥ 32 hex digits, as ``cranetwin machines add`` prints it) or, if it
    is not hex, as UTF-8 text.

    Raises:
        CraneTwinError: shorter than 16 bytes.
    """
    t = text.strip()
    try:
        key = bytes.fromhex(t) if len(t) >= 32 else t.encode()
    except ValueError:
        key = t.encode()
    if len(key) < 16:
        raise CraneTwinError("the machine key must be at least 16 bytes (32 hex digits)")
    return key


def parse_position(text: str) -> tuple[float, float]:
    """``"LAT,LON"`` [deg] → (latitude, longitude).

    Raises:
        CraneTwinError: Not two numbers, or outside [-90, 90] × [-180, 180].
    """
    parts = text.split(",")
    try:
        lat, lon = (float(x) for x in parts)
    except ValueError:
        raise CraneTwinError(f"--position must be LAT,LON in degrees (e.g. 62.6,29.76), got "
                             f"{text!r}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise CraneTwinError(f"--position {text!r} is outside latitude [-90, 90] and longitude "
                             "[-180, 180] degrees")
    return lat, lon


def send(
    machine: str = typer.Option(..., "--machine", help="Machine id (with --machines N: prefix "
                                "of <ID>-<i>)."),
    wire_id: int = typer.Option(..., "--wire-id", help="32-bit wire id registered for the "
                                "machine (with --machines N: the first of N consecutive ids)."),
    key: str | None = typer.Option(None, "--key", help=f"HMAC secret (hex), else ${KEY_ENV}. "
                                   "Never logged.", show_default=False),
    key_file: Path | None = typer.Option(None, "--key-file", help="File holding the secret."),
    scenario: str = typer.Option("log-loading", help="Simulator scenario (fig3, log-loading, "
                                 "random, or a file), or 'synthetic' for built-in motion."),
    host: str = typer.Option("127.0.0.1:5005", help="Ingest daemon, HOST:PORT."),
    speed: float = typer.Option(1.0, help="Multiple of real time."),
    machines: int = typer.Option(1, min=1, help="Simulated fleet size."),
    duration: float | None = typer.Option(None, help="Seconds of data to send (default: until "
                                          "Ctrl-C), then wait for the last acks."),
    model: str = typer.Option("patu655", help="Machine description (built-in name or TOML)."),
    batch: int = typer.Option(50, help="Samples per datagram."),
    spill_dir: Path | None = typer.Option(None, help="Directory for spill files (default: "
                                          "in memory)."),
    sim_seconds: float = typer.Option(120.0, help="Simulated seconds, replayed cyclically."),
    seed: int = typer.Option(0, help="Seed of the simulated sensors."),
    position: str = typer.Option("61.0,25.0", help="GPS position reported in the status "
                                 "datagrams, LAT,LON [deg] (the location the machine was "
                                 "registered with)."),
    as_json: bool = typer.Option(False, "--json", help="Print the counters as JSON at the end."),
    log_level: str = typer.Option("INFO", help="Logging level."),
) -> None:
    """Stream sensor samples to the ingest daemon in real time (UDP, acked, retransmitted)."""
    from cranetwin.ingest.sender import (
        RecordingSource,
        SampleSource,
        SyntheticSource,
        parse_host,
        run_fleet,
        simulator_source,
    )
    from cranetwin.model import load_machine
    from cranetwin.protocol import Layout, MachineKey

    logging.basicConfig(level=log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if key is None and key_file is not None:
        key = key_file.read_text()
    key = key if key is not None else os.environ.get(KEY_ENV)
    if not key:
        raise CraneTwinError(f"no machine key: give --key, --key-file or set ${KEY_ENV}")
    secret = parse_key(key)
    server = parse_host(host)
    position_deg = parse_position(position)
    m = load_machine(model)
    layout = Layout.from_channels(m.channels)
    ids = [machine] if machines == 1 else [f"{machine}-{i}" for i in range(machines)]
    keys = [MachineKey(wire_id + i, mid, secret, layout) for i, mid in enumerate(ids)]
    sources: list[SampleSource]
    period_s = 0.01
    if scenario == "synthetic":
        sources = [SyntheticSource(k, period_s, seed=seed + i) for i, k in enumerate(keys)]
    else:
        values, period_s = simulator_source(keys[0], m, scenario, duration_s=sim_seconds,
                                            seed=seed)
        step = max(1, values.shape[0] // machines)
        sources = [RecordingSource(values, offset=i * step) for i in range(machines)]

    async def main() -> list[dict[str, object]]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        stats = await run_fleet(keys, server, sources, period_ns=int(round(period_s * 1e9)),
                                speed=speed, duration_s=duration, batch_samples=batch,
                                spill_path=spill_dir, stop=stop, position_deg=position_deg)
        return [dict(s.__dict__, bytes_per_sample=s.bytes_per_sample) for s in stats]

    result = asyncio.run(main())
    if as_json:
        typer.echo(json.dumps(result if machines > 1 else result[0]))
    unacked = sum(int(str(r["unacked"])) for r in result)
    if unacked:
        raise CraneTwinError(f"{unacked} datagram(s) not acknowledged by {host} in time")


def register(app: typer.Typer) -> None:
    app.command("send")(send)
