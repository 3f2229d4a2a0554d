"""Ingest daemon hand-offs without polling: the event loop gathers datagrams into batches (one
queue put and one decoder wake-up per batch), queue_max bounds what is accepted and not yet
decoded, the decoder and writer threads block while idle, a shutdown after an idle spell longer
than the stall timeout still flushes, and the ``--processes`` parent sleeps until a restart is
due."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from conftest import SECRET, running_daemon
from cranetwin.ingest.config import DaemonConfig
from cranetwin.ingest.daemon import IngestDaemon
from cranetwin.ingest.processes import ProcessGroup, _Child
from cranetwin.protocol import decode_ack
from cranetwin.storage import Store
from test_ingest_daemon import datagram, key, udp, wait_for

ADDR = ("127.0.0.1", 40000)


class _Timer:
    def __init__(self, delay: float, fn: Callable[[], None]) -> None:
        self.delay, self.fn, self.cancelled = delay, fn, False

    def cancel(self) -> None:
        self.cancelled = True


class _FakeLoop:
    """Records ``call_later`` (the event loop side runs without a real loop)."""

    def __init__(self) -> None:
        self.timers: list[_Timer] = []

    def call_later(self, delay: float, fn: Callable[[], None]) -> _Timer:
        t = _Timer(delay, fn)
        self.timers.append(t)
        return t


def _daemon(sqlite_url: str, **config: Any) -> tuple[IngestDaemon, _FakeLoop]:
    d = IngestDaemon(Store.open(sqlite_url), DaemonConfig(port=0, **config))
    loop = _FakeLoop()
    d._loop = loop  # type: ignore[assignment]
    return d, loop


def test_datagrams_of_one_window_reach_the_decoder_as_one_batch(sqlite_url: str) -> None:
    d, loop = _daemon(sqlite_url, batch_wait_s=0.05, batch_max=100)
    for i in range(3):
        d._on_datagram(b"d%d" % i, ADDR)
    assert d._queue.qsize() == 0  # still gathering: the decoder was not woken
    assert [t.delay for t in loop.timers] == [0.05]  # one hand-over timer per batch
    loop.timers[0].fn()
    batch = d._queue.get_nowait()
    assert batch is not None and [raw[0] for raw in batch] == [b"d0", b"d1", b"d2"]
    assert d.snapshot()["queue_depth"] == 3  # accepted, not yet taken by the decoder
    d._on_datagram(b"d3", ADDR)  # the next window starts its own timer
    assert len(loop.timers) == 2 and d._queue.qsize() == 0


def test_a_full_batch_is_handed_over_at_once(sqlite_url: str) -> None:
    d, loop = _daemon(sqlite_url, batch_wait_s=10.0, batch_max=4)
    for i in range(4):
        d._on_datagram(b"d%d" % i, ADDR)
    batch = d._queue.get_nowait()
    assert batch is not None and len(batch) == 4
    assert loop.timers[0].cancelled  # the window's timer does not hand over an empty batch
    assert d._queue.qsize() == 0


def test_queue_max_counts_datagrams_gathering_and_queued(sqlite_url: str) -> None:
    d, loop = _daemon(sqlite_url, batch_wait_s=10.0, batch_max=3, queue_max=5)
    for i in range(7):
        d._on_datagram(b"d%d" % i, ADDR)
    s = d.snapshot()
    assert s["received"] == 7 and s["dropped"] == {"queue_full": 2}
    assert s["queue_depth"] == 5  # one batch of 3 queued, 2 gathering


@pytest.mark.timeout(60)
def test_idle_decoder_and_writer_block_instead_of_polling(sqlite_url: str) -> None:
    store = Store.open(sqlite_url)
    store.add_machine("crane-1", 1, SECRET)
    with running_daemon(store, rollup_interval_s=3600.0) as d:
        wait_for(lambda: all(t.is_alive() for t in d._threads.values()))
        calls = {"raw": 0, "decoded": 0}

        def counting(q: Any, name: str) -> None:
            get = q.get

            def wrapped(*args: Any, **kwargs: Any) -> Any:
                calls[name] += 1
                return get(*args, **kwargs)

            q.get = wrapped

        counting(d._queue, "raw")
        counting(d._decoded, "decoded")
        time.sleep(1.0)  # idle: a 0.1 s polling loop would come back ~10 times
        assert calls["raw"] <= 1 and calls["decoded"] <= 1  # (a thread not yet inside get)
        s = udp()
        s.sendto(datagram(1, 0), d.address)  # and traffic still wakes both at once
        assert decode_ack(s.recv(2048), key(1)).covers(0)
        s.close()
    assert store.stats().blocks == 1


@pytest.mark.timeout(60)
def test_shutdown_after_an_idle_spell_longer_than_the_stall_timeout_flushes(
        sqlite_url: str) -> None:
    """The writer waits for a batch far longer than ``stall_timeout_s``: that is not a stuck
    database call, so shutdown must not give up the batch still being gathered."""
    store = Store.open(sqlite_url)
    store.add_machine("crane-1", 1, SECRET)
    with running_daemon(store, stall_timeout_s=0.2, batch_wait_s=30.0) as d:
        time.sleep(0.5)  # the writer has been waiting longer than the stall timeout
        s = udp()
        s.sendto(datagram(1, 0), d.address)
        wait_for(lambda: d.snapshot()["received"] == 1)  # gathering (batch_wait_s is 30 s)
        assert d.snapshot()["stored_blocks"] == 0
    final = d.snapshot()
    assert final["dropped"] == {} and final["stored_blocks"] == 1 and final["acks_sent"] == 1
    assert decode_ack(s.recv(2048), key(1)).covers(0)
    s.close()
    assert store.stats().blocks == 1


def test_the_process_group_sleeps_until_the_next_due_restart(sqlite_url: str) -> None:
    g = ProcessGroup(sqlite_url, DaemonConfig(port=0), 3)
    assert g._sleep_s(5.0) == 5.0  # no children down: the backstop only
    now = time.monotonic()
    running: Any = threading.Thread()  # stands for a running child's Popen (not None)
    g._children = [_Child(0, -1, proc=running), _Child(1, -1, due=now + 0.7),
                   _Child(2, -1, due=now + 3.0)]
    assert 0.0 < g._sleep_s(5.0) <= 0.7
    g._children[1].due = now - 1.0  # overdue
    assert g._sleep_s(5.0) == 0.0
