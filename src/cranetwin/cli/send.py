"""``cranetwin send``: stream sensor samples (simulated, or a recorded file) to an ingest daemon.

The secret comes from a file (``--key-file``, not readable by other users) or the environment
(``$CRANETWIN_MACHINE_KEY``), never from the command line. Every datagram is journaled on disk
(``--journal``) before it is sent; what is not acknowledged when the command ends is sent first
on its next start.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import stat
from pathlib import Path

import typer

from cranetwin.errors import CraneTwinError

KEY_ENV = "CRANETWIN_MACHINE_KEY"
STATE_ENV = "CRANETWIN_STATE_DIR"
log = logging.getLogger(__name__)


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


def default_journal_root() -> Path:
    """Where ``cranetwin send`` keeps its journals: ``$CRANETWIN_STATE_DIR/send`` if set, else
    ``$XDG_STATE_HOME/cranetwin/send`` (``~/.local/state/cranetwin/send``); one subdirectory
    per machine id."""
    from cranetwin.settings import Settings, load_settings

    state = load_settings(Settings).state_dir
    if state is not None:
        return state.expanduser() / "send"
    xdg = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(xdg).expanduser() / "cranetwin" / "send"


def read_key_file(path: Path) -> str:
    """The secret in ``path``, refused if other users may read it (mode & 0o007) and with a
    warning if the file's group may (mode & 0o070).

    Raises:
        CraneTwinError: unreadable, or accessible to every user.
    """
    try:
        mode = path.stat().st_mode
        text = path.read_text("utf-8")
    except OSError as exc:
        raise CraneTwinError(f"cannot read the key file {path}: {exc}") from exc
    if mode & 0o007:
        raise CraneTwinError(f"the key file {path} is accessible to every user (mode "
                             f"{stat.S_IMODE(mode):04o}); run: chmod 600 {path}")
    if mode & 0o070:
        log.warning("the key file %s is readable by its group (mode %04o); chmod 600 it unless "
                    "that is intended", path, stat.S_IMODE(mode))
    return text


def send(
    machine: str = typer.Option(..., "--machine", help="Machine id (with --machines N: prefix "
                                "of <ID>-<i>)."),
    wire_id: int = typer.Option(..., "--wire-id", help="32-bit wire id registered for the "
                                "machine (with --machines N: the first of N consecutive ids)."),
    key: str | None = typer.Option(None, "--key", hidden=True,
                                   help="Refused: a secret on the command line is visible to "
                                   "every user (ps, /proc). Use --key-file or "
                                   f"${KEY_ENV}.", show_default=False),
    key_file: Path | None = typer.Option(None, "--key-file", help="File holding the HMAC "
                                         f"secret (mode 0600), else ${KEY_ENV}. Never logged."),
    journal: Path | None = typer.Option(
        None, "--journal", help="Directory of the durable send journals, one subdirectory per "
        f"machine id (default: ${STATE_ENV}/send, else ~/.local/state/cranetwin/send). "
        "Datagrams not acknowledged when the sender stops stay there and are sent first on the "
        "next start.", show_default=False),
    from_journal_only: bool = typer.Option(
        False, "--from-journal-only", help="Produce no new samples: send what the journal holds, "
        "wait for the acks and exit."),
    scenario: str = typer.Option("log-loading", help="Simulator scenario (fig3, log-loading, "
                                 "random for the PATU 655; one shipped for --model, e.g. "
                                 "dig-cycle for bobcat435; or a file), or 'synthetic' for "
                                 "built-in motion."),
    file: Path | None = typer.Option(
        None, "--file", help="Send a recording instead of simulating: a CSV, Parquet or MDF4 "
        "logger file, read and checked as `cranetwin import` reads it (with --mapping). Its rows "
        "go out at the file's sample period (× --speed) on the sender's clock, once (with "
        "--loop: cyclically); time gaps in the file are closed up.", show_default=False),
    mapping: Path | None = typer.Option(None, "--mapping", help="Mapping TOML of --file "
                                        "(columns, units, conventions; docs/IMPORT.md).",
                                        show_default=False),
    host: str = typer.Option("127.0.0.1:5005", help="Ingest daemon, HOST:PORT."),
    speed: float = typer.Option(1.0, help="Multiple of real time."),
    machines: int = typer.Option(1, min=1, help="Simulated fleet size."),
    duration: float | None = typer.Option(None, help="Seconds of data to send (default: until "
                                          "Ctrl-C), then wait for the last acks."),
    drain_timeout: float = typer.Option(30.0, min=0, help="Seconds to wait for the last acks "
                                        "after --duration (what is not acknowledged by then "
                                        "stays in the journal). Ctrl-C/SIGTERM do not wait."),
    model: str = typer.Option("patu655", help="Machine description (built-in name or TOML)."),
    batch: int = typer.Option(50, help="Samples per datagram."),
    sim_seconds: float | None = typer.Option(
        None, help="Length of a built-in scenario [s]: by default 86400 s simulated "
        "continuously (the machine holds still afterwards); with --loop 120 s replayed "
        "cyclically. A scenario file keeps its own length.", show_default=False),
    loop: bool = typer.Option(False, "--loop", help="Simulate --sim-seconds once and replay "
                              "them cyclically (starts no faster, and each restart jumps the "
                              "machine back to its first pose) instead of simulating "
                              "continuously."),
    seed: int = typer.Option(0, help="Seed of the simulated sensors."),
    position: str = typer.Option("61.0,25.0", help="GPS position reported in the status "
                                 "datagrams, LAT,LON [deg] (the location the machine was "
                                 "registered with)."),
    as_json: bool = typer.Option(False, "--json", help="Print the counters as JSON at the end."),
    log_level: str = typer.Option("INFO", help="Logging level."),
) -> None:
    """Stream sensor samples to the ingest daemon in real time (UDP, acked, retransmitted),
    every datagram journaled on disk before it is sent.

    Exit status 0 when everything was acknowledged, 2 when datagrams remain in the journal (they
    are sent on the next start) or on an error.
    """
    from cranetwin.ingest.sender import (
        RecordingSource,
        SampleSource,
        SyntheticSource,
        file_source,
        parse_host,
        run_fleet,
        simulator_source,
        simulator_stream,
    )
    from cranetwin.model import load_machine
    from cranetwin.protocol import Layout, MachineKey

    logging.basicConfig(level=log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if key is not None:
        raise CraneTwinError(f"--key is refused: a secret on the command line is visible to "
                             f"every user (ps, /proc/PID/cmdline); use --key-file FILE (mode "
                             f"0600) or set ${KEY_ENV}")
    text = read_key_file(key_file) if key_file is not None else os.environ.get(KEY_ENV)
    if not text:
        raise CraneTwinError(f"no machine key: give --key-file FILE or set ${KEY_ENV}")
    secret = parse_key(text)
    server = parse_host(host)
    position_deg = parse_position(position)
    root = journal if journal is not None else default_journal_root()
    m = load_machine(model)
    layout = Layout.from_channels(m.channels)
    ids = [machine] if machines == 1 else [f"{machine}-{i}" for i in range(machines)]
    keys = [MachineKey(wire_id + i, mid, secret, layout) for i, mid in enumerate(ids)]
    sources: list[SampleSource | None]
    period_s = 0.01
    if from_journal_only:
        missing = [str(root / k.machine_id) for k in keys if not (root / k.machine_id).is_dir()]
        if missing:
            raise CraneTwinError(f"--from-journal-only: no journal at {', '.join(missing)}")
        sources = [None] * len(keys)
    elif file is not None:
        from cranetwin.importer import load_mapping, read_file

        file_map = load_mapping(mapping, m)
        rec = file_source(keys[0], read_file(file, m, file_map).samples, Path(file).name,
                          file_map.payload_column)
        period_s = rec.period_s
        step = max(1, rec.values.shape[0] // machines)
        sources = [RecordingSource(rec.values, offset=i * step, anchored=True)
                   for i in range(machines)]
        if duration is None and not loop:
            duration = rec.values.shape[0] * period_s  # the file once
        if rec.gaps:
            typer.echo(f"{file}: {rec.gaps} time gap(s), {rec.gap_s:.3g} s in all, closed up: "
                       "rows are sent back to back on the sender's clock", err=True)
        if rec.payload_column is not None:
            typer.echo(f"{file}: the payload column {rec.payload_column!r} is not sent (the wire "
                       "carries sensor channels only); `cranetwin import` stores it", err=True)
    elif scenario == "synthetic":
        sources = [SyntheticSource(k, period_s, seed=seed + i) for i, k in enumerate(keys)]
    elif loop:
        values, period_s = simulator_source(keys[0], m, scenario,
                                            duration_s=sim_seconds or 120.0, seed=seed)
        step = max(1, values.shape[0] // machines)
        sources = [RecordingSource(values, offset=i * step) for i in range(machines)]
    else:
        from cranetwin.sim import prepare

        prep = prepare(m)
        sources = []
        for i, k in enumerate(keys):
            stream, period_s = simulator_stream(k, prep, scenario,
                                                duration_s=sim_seconds or 86400.0, seed=seed + i)
            sources.append(stream)

    async def main() -> list[dict[str, object]]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        stats = await run_fleet(keys, server, sources, journal_dir=root,
                                period_ns=int(round(period_s * 1e9)), speed=speed,
                                duration_s=duration, batch_samples=batch, stop=stop,
                                position_deg=position_deg, drain_timeout_s=drain_timeout)
        return [dict(s.__dict__, bytes_per_sample=s.bytes_per_sample) for s in stats]

    result = asyncio.run(main())
    if as_json:
        typer.echo(json.dumps(result if machines > 1 else result[0]))
    unacked = sum(int(str(r["unacked"])) for r in result)
    if unacked:
        where = root / machine if machines == 1 else root
        typer.echo(f"{unacked} datagrams not yet acknowledged, kept in {where}; they are sent "
                   "on the next start", err=True)
        raise typer.Exit(2)


def register(app: typer.Typer) -> None:
    app.command("send")(send)
