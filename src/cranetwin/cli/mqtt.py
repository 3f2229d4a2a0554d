"""``cranetwin mqtt-ingest`` (Sparkplug B over MQTT into storage) and ``cranetwin mqtt-send``
(a simulated machine publishing as a Sparkplug B edge node).

Options left out fall back to the shared settings (``CRANETWIN_MQTT_BROKER_URL``,
``CRANETWIN_MQTT_GROUP``, ``CRANETWIN_DATABASE_URL``, …; docs/INGEST.md, "MQTT / Sparkplug B").
The broker password is never an option: ``CRANETWIN_MQTT_PASSWORD`` (environment) only.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from urllib.parse import urlsplit

import typer

from cranetwin.errors import CraneTwinError
from cranetwin.samples import SampleBlock
from cranetwin.settings import Settings, load_settings


class MqttCliError(CraneTwinError):
    """An MQTT option or setting is unusable (one line, exit status 2)."""


@dataclass(frozen=True)
class Broker:
    """A broker address parsed from ``mqtt://[user@]host:port`` or ``mqtts://…``."""

    host: str
    port: int
    tls: bool
    username: str | None


def parse_broker(url: str) -> Broker:
    """The broker of an ``mqtt://`` or ``mqtts://`` URL (default ports 1883 and 8883).

    Raises:
        MqttCliError: another scheme, no host, a bad port, or a password in the URL (argv is
            readable by every local user: use ``CRANETWIN_MQTT_PASSWORD``).
    """
    u = urlsplit(url.strip())
    if u.scheme not in ("mqtt", "mqtts", "tcp", "ssl"):
        raise MqttCliError(f"--broker must be mqtt://HOST:PORT or mqtts://HOST:PORT, got "
                           f"{u.scheme or 'no'} scheme")
    if u.password is not None:
        raise MqttCliError("no password in the broker URL (every local user can read the "
                           "command line): set CRANETWIN_MQTT_PASSWORD")
    try:
        port = u.port
    except ValueError as exc:
        raise MqttCliError(f"--broker: {exc}") from None
    if not u.hostname:
        raise MqttCliError("--broker: no host")
    tls = u.scheme in ("mqtts", "ssl")
    return Broker(u.hostname, port or (8883 if tls else 1883), tls, u.username or None)


def _print(event: dict[str, object]) -> None:
    sys.stdout.write(json.dumps(event) + "\n")
    sys.stdout.flush()


def mqtt_ingest(
    broker: str | None = typer.Option(None, "--broker", help="mqtt://[USER@]HOST:PORT or "
                                      "mqtts://… (default: $CRANETWIN_MQTT_BROKER_URL)."),
    group: str | None = typer.Option(None, "--group", help="Sparkplug B group id (default: "
                                     "$CRANETWIN_MQTT_GROUP, else cranetwin)."),
    client_id: str | None = typer.Option(None, "--client-id", help="MQTT client id = name of "
                                         "the persistent session (default: "
                                         "$CRANETWIN_MQTT_CLIENT_ID)."),
    db: str | None = typer.Option(None, "--db", help="Database URL (default: "
                                  "$CRANETWIN_DATABASE_URL, else sqlite:///cranetwin.db)."),
    live: str | None = typer.Option(None, help="Live fan-out of stored blocks (default: "
                                    "$CRANETWIN_LIVE_BUS_URL, else none)."),
    batch_max: int | None = typer.Option(None, min=1, help="Messages per transaction at most "
                                         "(default: $CRANETWIN_INGEST_BATCH_MAX)."),
    log_level: str = typer.Option("INFO", help="Logging level."),
) -> None:
    """Store Sparkplug B DDATA blocks from an MQTT broker (QoS 1, acked after commit).

    Prints one JSON line on stdout once subscribed: {"event": "ready", "broker": "HOST:PORT",
    "group": G, "pid": N}, and one after SIGTERM/SIGINT: {"event": "stopped", <counters>}.
    """
    from cranetwin.ingest.config import DaemonConfig
    from cranetwin.ingest.mqtt import MqttConfig, MqttIngest
    from cranetwin.protocol import Limits
    from cranetwin.storage import Store
    from cranetwin.storage.live import open_bus

    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: "
                        "%(message)s")
    st = load_settings(Settings, mqtt_broker_url=broker, mqtt_group=group,
                       mqtt_client_id=client_id, database_url=db, live_bus_url=live,
                       ingest_batch_max=batch_max)
    if not st.mqtt_broker_url:
        raise MqttCliError("no broker: give --broker mqtt://HOST:PORT or set "
                           "CRANETWIN_MQTT_BROKER_URL")
    b = parse_broker(st.mqtt_broker_url)
    cfg = MqttConfig(host=b.host, port=b.port, tls=b.tls, protocol=st.mqtt_protocol,
                     group=st.mqtt_group,
                     client_id=st.mqtt_client_id, username=st.mqtt_username or b.username,
                     password=st.mqtt_password or None,
                     session_expiry_s=st.mqtt_session_expiry_s,
                     receive_maximum=st.mqtt_receive_maximum, batch_max=st.ingest_batch_max,
                     batch_wait_s=st.ingest_batch_wait_s,
                     limits=Limits(max_past_s=st.ingest_max_past_s,
                                   max_future_s=st.ingest_max_future_s,
                                   range_margin=st.ingest_range_margin),
                     writer=DaemonConfig())
    live_bus = open_bus(st.live_bus_url) if st.live_bus_url else None
    store = Store.open(st.database_url, busy_timeout_s=st.ingest_busy_timeout_s)
    try:
        adapter = MqttIngest(store, cfg, live_bus)
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: adapter.stop())

        def announce() -> None:
            if adapter.ready.wait(60):
                _print({"event": "ready", "broker": f"{b.host}:{b.port}", "group": cfg.group,
                        "pid": os.getpid()})

        threading.Thread(target=announce, daemon=True).start()
        final = adapter.run()
    finally:
        if live_bus is not None:
            live_bus.close()
        store.close()
    _print({"event": "stopped", **final})


def mqtt_send(
    machine: str = typer.Option(..., help="Machine id (registered with `cranetwin machines "
                                "add`): the Sparkplug device id."),
    model: str = typer.Option("patu655", help="Built-in machine model."),
    broker: str | None = typer.Option(None, "--broker", help="mqtt://HOST:PORT (default: "
                                      "$CRANETWIN_MQTT_BROKER_URL)."),
    group: str | None = typer.Option(None, "--group", help="Sparkplug B group id."),
    edge_node: str = typer.Option("edge-1", help="Sparkplug B edge node id."),
    duration: float = typer.Option(60.0, min=0.01, help="Seconds of samples to publish [s]."),
    block_s: float = typer.Option(1.0, min=0.01, help="Seconds of samples per DDATA [s]."),
    fast: bool = typer.Option(False, help="Publish as fast as the broker acks, not in real "
                              "time."),
    aliases: bool = typer.Option(False, help="Name metrics by their DBIRTH aliases."),
) -> None:
    """Publish a machine's samples (the test recording) as Sparkplug B DDATA, QoS 1.

    Prints {"event": "sent", "blocks": N, "samples": M, "epoch": E} once the broker has acked
    every block.
    """
    from cranetwin.ingest.mqtt_edge import EdgePublisher
    from cranetwin.model import load_machine
    from cranetwin.protocol.machine import layout_of
    from cranetwin.protocol.sender import new_epoch
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    st = load_settings(Settings, mqtt_broker_url=broker, mqtt_group=group)
    if not st.mqtt_broker_url:
        raise MqttCliError("no broker: give --broker mqtt://HOST:PORT")
    b = parse_broker(st.mqtt_broker_url)
    mach = load_machine(model)
    layout = layout_of(model)
    epoch = new_epoch()
    start = float(int(time.time()))
    base = kinematic_samples(mach, 120.0)
    pub = EdgePublisher(b.host, b.port, st.mqtt_group, edge_node, {machine: layout},
                        use_aliases=aliases, username=st.mqtt_username or b.username,
                        password=st.mqtt_password or None)
    counted = [0, 0]

    def blocks() -> Iterator[SampleBlock]:
        cols = [base.channels.index(c) for c in layout.names]
        for blk in tiled_blocks(machine, mach, start, duration, block_s, base=base):
            if not fast:  # a block leaves once its last sample is taken
                time.sleep(max(0.0, (blk.t_end_ns + blk.period_ns) / 1e9 - time.time()))
            counted[0] += 1
            counted[1] += blk.n
            yield SampleBlock(machine, blk.seq, blk.t0_ns, blk.period_ns, layout.names,
                              layout.resolutions, blk.values[:, cols], epoch=epoch)

    try:
        pub.publish_all(blocks(), timeout_s=60.0)
    finally:
        pub.close()
    n, samples = counted
    _print({"event": "sent", "blocks": n, "samples": samples, "epoch": epoch})


def register(app: typer.Typer) -> None:
    app.command("mqtt-ingest")(mqtt_ingest)
    app.command("mqtt-send")(mqtt_send)
