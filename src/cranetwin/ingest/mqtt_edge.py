"""Machine side of the MQTT path: a Sparkplug B edge node publishing sample blocks (QoS 1).

For tests, benchmarks and the demo, and as a reference for a machine's own publisher
(docs/INGEST.md, "MQTT / Sparkplug B"). :class:`EdgePublisher` connects as the edge node,
publishes ``NBIRTH`` and a ``DBIRTH`` per machine (device), then one ``DDATA`` per block, each
with the next Sparkplug ``seq``; it answers a host's ``Node Control/Rebirth`` command with new
births. A block is *broker-acked* once :meth:`EdgePublisher.publish` 's message info reports
it published (the broker's PUBACK); from then on the broker, not the machine, is responsible
for it. This publisher keeps no durable queue: a machine that must survive its own crash keeps
its blocks on disk until the broker has acked them, as ``cranetwin send`` does for UDP.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable
from typing import Any

from cranetwin.ingest.mqtt import paho
from cranetwin.ingest.sparkplug import (
    BLOCK_METRICS,
    REBIRTH,
    UINT64,
    Topic,
    aliases_for,
    encode_birth,
    encode_ddata,
    pb,
)
from cranetwin.protocol import Layout
from cranetwin.samples import SampleBlock


class EdgePublisher:
    """One Sparkplug B edge node on a broker (see the module docstring).

    Args:
        host, port: The broker.
        group, edge_node: Sparkplug group and edge node ids of the topics.
        layouts: Machine id (device) → its channel layout, declared in the DBIRTHs.
        use_aliases: DDATA name metrics by the DBIRTH's aliases instead of by name.
        username, password: Broker credentials, or None.
        max_inflight: Messages awaiting the broker's PUBACK at most.
    """

    def __init__(self, host: str, port: int, group: str, edge_node: str,
                 layouts: dict[str, Layout], *, use_aliases: bool = False,
                 username: str | None = None, password: str | None = None,
                 max_inflight: int = 100) -> None:
        mqtt = paho()
        self.group, self.edge_node, self.layouts = group, edge_node, layouts
        self.use_aliases = use_aliases
        self._seq = 0
        self._lock = threading.Lock()
        self._connected = threading.Event()
        self.rebirths = 0
        self.last_births: list[Any] = []
        self._c: Any = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2,
                                   client_id=f"cranetwin-edge-{group}-{edge_node}",
                                   protocol=mqtt.MQTTv311, clean_session=True)
        if username is not None:
            self._c.username_pw_set(username, password)
        self._c.max_inflight_messages_set(max_inflight)
        self._c.on_connect = self._on_connect
        self._c.on_message = self._on_message
        death = pb().Payload()
        m = death.metrics.add()
        m.name, m.datatype, m.long_value = "bdSeq", UINT64, 0
        self._c.will_set(str(Topic(group, "NDEATH", edge_node)), death.SerializeToString(), 1)
        self._c.connect(host, port, 30)
        self._c.loop_start()
        try:
            if not self._connected.wait(10):
                raise TimeoutError("no CONNACK")
            self._wait(self.last_births, 10.0)
        except (TimeoutError, RuntimeError, ValueError) as exc:
            self.close()
            raise TimeoutError(f"MQTT broker {host}:{port} did not accept the edge node: "
                               f"{exc}") from exc

    def _next_seq(self) -> int:
        with self._lock:
            s = self._seq
            self._seq = (s + 1) % 256
            return s

    def _on_connect(self, client: Any, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if reason.is_failure:
            return
        client.subscribe(str(Topic(self.group, "NCMD", self.edge_node)), 1)
        self.births()
        self._connected.set()

    def _on_message(self, _c: Any, _u: Any, msg: Any) -> None:
        p = pb().Payload()
        try:
            p.ParseFromString(msg.payload)
        except Exception:
            return
        if any(m.name == REBIRTH and m.boolean_value for m in p.metrics):
            self.rebirths += 1
            self.births()

    def _aliases(self, layout: Layout) -> dict[str, int]:
        return aliases_for((*BLOCK_METRICS, *layout.names))

    def births(self) -> None:
        """Publish NBIRTH and every device's DBIRTH (QoS 0 for NBIRTH as Sparkplug asks,
        QoS 1 for the DBIRTHs the adapter learns aliases from; their message infos in
        :attr:`last_births`; the constructor returns once the broker has acked them)."""
        with self._lock:
            self._seq = 0
        now = time.time_ns() // 1_000_000
        node = pb().Payload()
        node.timestamp, node.seq = now, self._next_seq()
        m = node.metrics.add()
        m.name, m.datatype, m.long_value = "bdSeq", UINT64, 0
        self._c.publish(str(Topic(self.group, "NBIRTH", self.edge_node)),
                        node.SerializeToString(), 0)
        self.last_births = [
            self._c.publish(str(Topic(self.group, "DBIRTH", self.edge_node, device)),
                            encode_birth(layout, self._next_seq(), now, self._aliases(layout)),
                            1)
            for device, layout in self.layouts.items()]

    def publish(self, block: SampleBlock) -> Any:
        """Publish ``block`` as DDATA of its machine, QoS 1; returns paho's message info
        (``is_published()`` once the broker acked it, ``wait_for_publish(timeout)``)."""
        layout = self.layouts[block.machine_id]
        aliases = self._aliases(layout) if self.use_aliases else None
        body = encode_ddata(block, self._next_seq(), time.time_ns() // 1_000_000, aliases)
        return self._c.publish(str(Topic(self.group, "DDATA", self.edge_node,
                                         block.machine_id)), body, 1)

    def publish_all(self, blocks: Iterable[SampleBlock], timeout_s: float = 30.0) -> int:
        """Publish ``blocks`` and wait until the broker acked each; returns how many.

        Raises:
            TimeoutError: a block not acked by the broker within ``timeout_s``.
        """
        infos = [self.publish(b) for b in blocks]
        self._wait(infos, timeout_s)
        return len(infos)

    @staticmethod
    def _wait(infos: list[Any], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for info in infos:
            info.wait_for_publish(max(0.0, deadline - time.monotonic()))
            if not info.is_published():
                raise TimeoutError("the broker did not acknowledge every message in time")

    def close(self) -> None:
        """Disconnect (a clean disconnect: no NDEATH will)."""
        self._c.disconnect()
        self._c.loop_stop()
