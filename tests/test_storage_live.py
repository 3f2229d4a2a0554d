"""Live fan-out: every published block reaches every subscriber, in-process and across
processes through PostgreSQL NOTIFY and Redis pub/sub."""

from __future__ import annotations

import socket
import sys

import numpy as np
import pytest

from conftest import pg_unreachable_reason
from cranetwin.errors import MissingExtraError, StorageError, StorageUnavailableError
from cranetwin.samples import SampleBlock
from cranetwin.storage.live import BlockNote, InProcessBus, LiveBus, _payloads, open_bus

pytestmark = pytest.mark.timeout(60)


def blocks(n: int, machine: str = "crane-1") -> list[SampleBlock]:
    return [SampleBlock(machine, s, 1_000 + s * 500, 10, ("a",), (1.0,),
                        np.arange(50.0)[:, None]) for s in range(n)]


def drain(sub: object, expect: int, timeout: float = 5.0) -> list[BlockNote]:
    out: list[BlockNote] = []
    while len(out) < expect:
        note = sub.get(timeout=timeout)  # type: ignore[attr-defined]
        if note is None:
            break
        out.append(note)
    return out


def test_in_process_bus_delivers_blocks_to_every_subscriber() -> None:
    bus = InProcessBus()
    a, b = bus.subscribe(), bus.subscribe()
    bus.publish(blocks(5))
    for sub in (a, b):
        got = drain(sub, 5, timeout=0.5)
        assert [n.seq for n in got] == list(range(5))
        assert got[0].block is not None and got[0].block.n == 50
    b.close()
    bus.publish(blocks(1))
    assert len(drain(a, 1, 0.5)) == 1 and b.get(timeout=0.05) is None


def test_slow_subscriber_drops_oldest_not_ingest() -> None:
    bus = InProcessBus(maxsize=3)
    sub = bus.subscribe()
    bus.publish(blocks(10))
    got = drain(sub, 10, timeout=0.05)
    assert [n.seq for n in got] == [7, 8, 9] and sub.dropped == 7


def test_payloads_stay_under_notify_limit() -> None:
    ps = _payloads(blocks(1000, machine="m" * 100), limit=7000)
    assert len(ps) > 1 and all(len(p) < 7000 for p in ps)


def _redis_up() -> bool:
    try:
        socket.create_connection(("127.0.0.1", 6379), timeout=1).close()
        return True
    except OSError:
        return False


@pytest.mark.parametrize("url", [
    pytest.param("postgresql+psycopg://postgres@127.0.0.1:5432/test", marks=pytest.mark.postgres),
    "redis://127.0.0.1:6379",
])
def test_broker_bus_delivers_notes_across_connections(url: str) -> None:
    if url.startswith("postgresql") and (reason := pg_unreachable_reason()):
        pytest.skip(reason)
    if url.startswith("redis") and not _redis_up():
        pytest.skip("no Redis server reachable at 127.0.0.1:6379")
    pub: LiveBus = open_bus(url)
    sub_bus: LiveBus = open_bus(url)
    sub = sub_bus.subscribe()
    try:
        import time

        time.sleep(0.3)  # the listener thread is subscribed
        sent = blocks(300)
        pub.publish(sent)
        got = drain(sub, 300)
        assert [(n.machine_id, n.seq, n.t0_ns, n.t_end_ns, n.n) for n in got] == [
            (b.machine_id, b.seq, b.t0_ns, b.t_end_ns, b.n) for b in sent]
    finally:
        sub.close()
        pub.close()
        sub_bus.close()


def test_unknown_bus_url_is_rejected() -> None:
    with pytest.raises(StorageError, match="unknown live bus"):
        open_bus("kafka://127.0.0.1:9092")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_redis_bus_without_a_server_raises_storage_unavailable() -> None:
    pytest.importorskip("redis")
    bus = open_bus(f"redis://127.0.0.1:{_free_port()}")
    with pytest.raises(StorageUnavailableError, match="redis unreachable"):
        bus.publish(blocks(1))
    with pytest.raises(StorageUnavailableError):
        bus.subscribe()
    bus.close()


@pytest.mark.parametrize(("url", "module", "extra"), [
    ("redis://127.0.0.1:6379", "redis", "redis"),
    ("postgresql://127.0.0.1/test", "psycopg", "postgres"),
])
def test_broker_bus_without_its_extra_names_the_extra(
        monkeypatch: pytest.MonkeyPatch, url: str, module: str, extra: str) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # import raises ImportError
    with pytest.raises(MissingExtraError, match=rf"cranetwin\[{extra}\]") as info:
        open_bus(url)
    assert info.value.extra == extra
