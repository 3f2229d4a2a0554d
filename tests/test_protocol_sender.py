"""Sender core against the Receiver over a simulated lossy link (drops, duplicates, reordering
both ways): retransmission until acked, nothing lost or doubled, bounded memory with spill."""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass, field

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.protocol import (
    BadHmacError,
    Layout,
    MachineKey,
    MemorySpill,
    Receiver,
    ReplayedError,
    Sender,
    StatusReport,
    datagram_seq,
    encode_ack,
    on_grid,
)
from cranetwin.samples import SampleBlock

PATU = load_machine("patu655")
KEY = MachineKey(3, "crane-3", b"q" * 32, Layout.from_channels(PATU.channels))
PERIOD = 10_000_000
MS = 1_000_000
T0 = 10**18


def _signal(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    cols = []
    for ch in PATU.channels:
        x = (ch.min + ch.max) / 2 + (ch.max - ch.min) * 0.2 * np.sin(t + rng.uniform(0, 6))
        cols.append(x + rng.normal(0, 2 * ch.resolution, n))
    v = np.stack(cols, axis=1)
    v[rng.random(v.shape) < 0.01] = np.nan
    return v


class Link:
    """Two-way link: drops, duplicates and delays (hence reorders) each datagram."""

    def __init__(self, seed: int, loss: float, dup: float, delay_ms: tuple[float, float]) -> None:
        self.rng = np.random.default_rng(seed)
        self.loss, self.dup, self.delay = loss, dup, delay_ms
        self.queue: list[tuple[int, int, str, bytes]] = []
        self._tie = itertools.count()
        self.up = True

    def send(self, now: int, to: str, dg: bytes) -> None:
        if not self.up:
            return
        copies = 0 if self.rng.random() < self.loss else 1
        copies += int(copies and self.rng.random() < self.dup)
        for _ in range(copies):
            d = int(self.rng.uniform(*self.delay) * MS)
            heapq.heappush(self.queue, (now + d, next(self._tie), to, dg))

    def due(self, now: int) -> list[tuple[str, bytes]]:
        out = []
        while self.queue and self.queue[0][0] <= now:
            _, _, to, dg = heapq.heappop(self.queue)
            out.append((to, dg))
        return out


@dataclass
class Server:
    """What the daemon does, in memory: receive → idempotent write → commit → ack."""

    rx: Receiver = field(default_factory=lambda: Receiver({KEY.wire_id: KEY}))
    stored: dict[int, SampleBlock | StatusReport] = field(default_factory=dict)
    uncommitted: list[int] = field(default_factory=list)
    writes: int = 0
    replayed: int = 0

    def on_datagram(self, dg: bytes, now: int, link: Link) -> None:
        try:
            item = self.rx.receive(dg, now)  # the link never forges: only replays may fail
        except ReplayedError as err:
            self.replayed += 1
            assert err.machine_id == KEY.machine_id
            link.send(now, "machine", self.rx.ack(err.machine_id, now))
            return
        if item.seq in self.stored and isinstance(item, SampleBlock):
            old = self.stored[item.seq]
            assert isinstance(old, SampleBlock)
            assert np.array_equal(old.values, item.values, equal_nan=True)
        self.stored[item.seq] = item
        self.writes += 1
        self.uncommitted.append(item.seq)

    def commit(self, now: int, link: Link) -> None:
        if self.uncommitted:
            for s in self.uncommitted:
                self.rx.mark_durable(KEY.machine_id, s)
            self.uncommitted.clear()
            link.send(now, "machine", self.rx.ack(KEY.machine_id, now))


def _run(sender: Sender, values: np.ndarray, link: Link, *, outage_ms: tuple[int, int] = (0, 0),
         max_s: float = 900.0) -> Server:
    """One row per 10 ms tick; the server commits every 50 ms."""
    srv = Server()
    now, i = T0, 0
    while now < T0 + max_s * 1e9:
        ms = (now - T0) // MS
        link.up = not outage_ms[0] <= ms < outage_ms[1]
        if i < len(values):
            sender.push(T0 + i * PERIOD, values[i:i + 1])
            i += 1
            if i == len(values):
                sender.flush()
        for dg in sender.datagrams_to_send(now):
            link.send(now, "server", dg)
        for to, dg in link.due(now):
            if to == "server":
                srv.on_datagram(dg, now, link)
            else:
                sender.receive(dg, now)
        if ms % 50 == 0:
            srv.commit(now, link)
        if i == len(values) and sender.idle:
            break
        now += PERIOD
    return srv


def _samples(srv: Server) -> tuple[np.ndarray, np.ndarray]:
    blocks = [b for _, b in sorted(srv.stored.items()) if isinstance(b, SampleBlock)]
    return (np.concatenate([b.times_ns() for b in blocks]),
            np.concatenate([b.values for b in blocks]))


@pytest.mark.parametrize("seed", [1, 2])
def test_lossy_link_delivers_every_sample_exactly_once(seed: int) -> None:
    values = _signal(3000, seed)
    sender = Sender(KEY, PERIOD, first_seq=500, batch_samples=50)
    srv = _run(sender, values, Link(seed, loss=0.2, dup=0.05, delay_ms=(5, 150)))
    assert sender.idle
    t, v = _samples(srv)
    assert np.array_equal(t, T0 + np.arange(3000) * PERIOD)  # none lost, none doubled
    assert np.array_equal(v, on_grid(values, KEY.layout.resolutions), equal_nan=True)
    assert sender.retransmissions > 0 and srv.writes + srv.replayed > len(srv.stored)
    assert sorted(srv.stored) == list(range(500, 500 + len(srv.stored)))
    assert sender.acked_samples == 3000


def test_outage_spills_beyond_the_memory_bound_and_recovers_everything() -> None:
    values = _signal(6000, 3)
    spill = MemorySpill()
    sender = Sender(KEY, PERIOD, batch_samples=50, max_unacked=8, spill=spill,
                    max_rto_ns=4_000_000_000)
    peak = {"mem": 0, "spill": 0}
    orig_push = sender.push

    def push(t0: int, v: np.ndarray) -> None:
        orig_push(t0, v)
        peak["mem"] = max(peak["mem"], sender.in_memory)
        peak["spill"] = max(peak["spill"], sender.spilled)

    sender.push = push  # type: ignore[method-assign]
    srv = _run(sender, values, Link(4, loss=0.05, dup=0.0, delay_ms=(10, 40)),
               outage_ms=(5_000, 45_000))  # link down 40 s: 80 datagrams, memory holds 8
    assert peak["mem"] == 8 and peak["spill"] > 60
    assert sender.idle and len(spill) == 0
    t, v = _samples(srv)
    assert np.array_equal(t, T0 + np.arange(6000) * PERIOD)
    assert np.array_equal(v, on_grid(values, KEY.layout.resolutions), equal_nan=True)


def test_retransmits_with_backoff_until_acked() -> None:
    sender = Sender(KEY, PERIOD, batch_samples=10, rto_ns=1_000_000_000,
                    max_rto_ns=8_000_000_000)
    sender.push(T0, _signal(10))
    send_times = []
    now = T0
    while now < T0 + 40 * 10**9:
        if sender.datagrams_to_send(now):
            send_times.append((now - T0) / 1e9)
        nxt = sender.next_timer_ns()
        assert nxt is not None and nxt > now
        now = nxt
    gaps = np.diff(send_times)
    assert list(gaps[:4]) == [1.0, 2.0, 4.0, 8.0] and set(gaps[4:]) == {8.0}  # capped
    assert not sender.idle
    sender.receive(encode_ack(KEY, 1), now)
    assert sender.idle and sender.datagrams_to_send(now + 10**12) == []


def test_ack_after_silence_resets_backoff_of_the_rest() -> None:
    sender = Sender(KEY, PERIOD, batch_samples=10)
    sender.push(T0, _signal(30))
    now = T0
    for _ in range(6):  # three datagrams, each sent 6 times: backoff now 30 s (capped)
        sender.datagrams_to_send(now)
        now = sender.next_timer_ns() or now
    assert len(sender.datagrams_to_send(now)) == 3
    assert sender.next_timer_ns() - now > 10 * 10**9  # type: ignore[operator]
    sender.receive(encode_ack(KEY, 1), now)  # seq 0 acked: the link is back
    assert sender.next_timer_ns() <= now + 10**9  # type: ignore[operator]


def test_forged_or_foreign_acks_change_nothing() -> None:
    sender = Sender(KEY, PERIOD, batch_samples=10)
    sender.push(T0, _signal(10))
    sender.datagrams_to_send(T0)
    forged = MachineKey(3, "crane-3", b"z" * 32, KEY.layout)
    with pytest.raises(BadHmacError):
        sender.receive(encode_ack(forged, 10), T0)
    other = MachineKey(4, "x", b"q" * 32, KEY.layout)
    with pytest.raises(Exception) as info:
        sender.receive(encode_ack(other, 10), T0)
    assert getattr(info.value, "reason", None) == "garbage"
    assert sender.in_memory == 1


def test_time_gap_flushes_a_short_batch_and_oversize_batches_split() -> None:
    sender = Sender(KEY, PERIOD, batch_samples=50, first_seq=10)
    v = _signal(30)
    sender.push(T0, v[:20])
    sender.push(T0 + 25 * PERIOD, v[20:])  # 5 samples missing in time
    assert sender.in_memory == 1 and sender.buffered_samples == 10
    dgs = sender.datagrams_to_send(T0)
    assert [datagram_seq(d) for d in dgs] == [10]
    big = np.random.default_rng(0).integers(-(2**30), 2**30, (400, 11)) * np.asarray(
        KEY.layout.resolutions)
    s2 = Sender(KEY, PERIOD, batch_samples=400, first_seq=0)
    s2.push(T0, big)
    dgs = s2.datagrams_to_send(T0)
    assert all(len(d) <= 1200 for d in dgs) and len(dgs) > 1
    assert [datagram_seq(d) for d in dgs] == list(range(len(dgs)))
    assert s2.next_seq == len(dgs)


def test_status_is_sent_and_acknowledged_like_data() -> None:
    sender = Sender(KEY, PERIOD, batch_samples=10, first_seq=7)
    seq = sender.push_status(StatusReport("ignored", 0, T0, 61.0, 24.0, 100.0, 10.0,
                                          {"slew_angle": 0.25}))
    assert seq == 7
    rx = Receiver({KEY.wire_id: KEY})
    [dg] = sender.datagrams_to_send(T0)
    rep = rx.receive(dg, T0)
    assert isinstance(rep, StatusReport) and rep.channels == {"slew_angle": 0.25}
    rx.mark_durable(KEY.machine_id, 7)
    sender.receive(rx.ack(KEY.machine_id, T0), T0)
    assert sender.idle


def test_restamped_lag_verifies_and_moves_the_receiver_floor() -> None:
    from cranetwin.protocol.sender import datagram_lag, restamp_lag

    sender = Sender(KEY, PERIOD, first_seq=40, batch_samples=10)
    sender.push(T0, _signal(30))
    dgs = sender.datagrams_to_send(T0)
    assert [datagram_lag(d) for d in dgs] == [0, 1, 2]
    again = restamp_lag(dgs[2], KEY.secret, 0)
    rx = Receiver({KEY.wire_id: KEY})
    a, b = rx.receive(dgs[2], T0), rx.receive(again, T0)
    assert isinstance(a, SampleBlock) and isinstance(b, SampleBlock)
    assert np.array_equal(a.values, b.values, equal_nan=True)
    assert rx.floor(KEY.machine_id) == 42
    sender.receive(encode_ack(KEY, 41), T0)  # 40 acked: the rest now carry the new oldest
    dgs = sender.datagrams_to_send(T0 + 10**10)
    assert [datagram_lag(d) for d in dgs] == [0, 1]
