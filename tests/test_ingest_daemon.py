"""Ingest daemon: stores what machines send, acks only after commit, counts and drops bad input
(answering only authenticated datagrams), flushes on shutdown, publishes new blocks, serves
Prometheus metrics.

The helpers here (a sans-IO sender driven over a real UDP socket, a store with a write hook)
are also used by ``test_ingest_faults.py``.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
import urllib.request
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest

from conftest import SECRET, running_daemon
from cranetwin.model import load_machine
from cranetwin.protocol import (
    DatagramError,
    Layout,
    MachineKey,
    MemoryJournal,
    Sender,
    StatusReport,
    decode_ack,
    encode_data,
    peek_header,
)
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, WriteResult
from cranetwin.storage.live import InProcessBus

LAYOUT = Layout.from_channels(load_machine("patu655").channels)
PERIOD_NS = 10_000_000  # 100 Hz
T0_NS = (time.time_ns() // 10**9 - 3600) * 10**9
"""An hour ago, on a whole second: inside the daemon's accepted time window."""


def key(wire_id: int, secret: bytes = SECRET) -> MachineKey:
    return MachineKey(wire_id, f"crane-{wire_id}", secret, LAYOUT)


def grid_values(n: int, seed: int) -> np.ndarray:
    """Random-walk samples on the resolution grid, well inside each channel's range."""
    rng = np.random.default_rng(seed)
    res = np.asarray(LAYOUT.resolutions)
    lo = np.ceil(np.array([c.min for c in LAYOUT.channels]) / res)
    hi = np.floor(np.array([c.max for c in LAYOUT.channels]) / res)
    mid = (lo + hi) // 2
    k = mid + np.cumsum(rng.integers(-3, 4, size=(n, res.size)), axis=0)
    k = np.clip(k, mid - (hi - lo) // 4, mid + (hi - lo) // 4)
    return k * res


def datagram(wire_id: int, seq: int, n: int = 20, seed: int = 0, *, epoch: int = 7,
             t0_ns: int | None = None, values: np.ndarray | None = None) -> bytes:
    """One data datagram of crane-``wire_id``: ``n`` samples at 100 Hz."""
    v = grid_values(n, seed) if values is None else values
    t0 = T0_NS + seq * n * PERIOD_NS if t0_ns is None else t0_ns
    return encode_data(key(wire_id), seq, t0, PERIOD_NS, v, epoch=epoch)


def make_sender(wire_id: int, values: np.ndarray, *, batch_samples: int = 50,
                max_unacked: int = 64) -> Sender:
    s = Sender(key(wire_id), PERIOD_NS, journal=MemoryJournal(), batch_samples=batch_samples,
               max_unacked=max_unacked, min_rto_ns=200_000_000, max_rto_ns=1_000_000_000)
    s.push(T0_NS, values)
    s.flush()
    return s


def udp(timeout_s: float = 5.0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(timeout_s)
    return s


def drive(senders: Sequence[Sender], address: tuple[str, int], timeout_s: float,
          until: Callable[[], bool] | None = None,
          on_reply: Callable[[bytes, float], None] | None = None) -> bool:
    """Run ``senders`` against the daemon over one UDP socket until all are idle (or ``until``
    holds); True if that happened within ``timeout_s``."""
    by_wire = {s.key.wire_id: s for s in senders}
    sock = udp()
    sock.setblocking(False)
    end = time.monotonic() + timeout_s
    try:
        while time.monotonic() < end:
            done = until() if until is not None else all(s.idle for s in senders)
            if done:
                return True
            now = time.time_ns()
            for s in senders:
                for dg in s.datagrams_to_send(now):
                    sock.sendto(dg, address)
            r, _, _ = select.select([sock], [], [], 0.01)
            while r:
                try:
                    reply = sock.recv(2048)
                except BlockingIOError:
                    break
                if on_reply is not None:
                    on_reply(reply, time.monotonic())
                try:
                    by_wire[peek_header(reply).wire_id].receive(reply, time.time_ns())
                except (DatagramError, KeyError):
                    pass
        return False
    finally:
        sock.close()


def wait_for(cond: Callable[[], bool], timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, "condition not met in time"
        time.sleep(0.01)


class HookStore(Store):
    """A store that calls ``hook(blocks)`` before every batch write (to gate, slow down or fail
    writes)."""

    hook: Callable[[Sequence[SampleBlock]], None] = staticmethod(lambda blocks: None)

    def write_batch(self, blocks: Sequence[SampleBlock]) -> WriteResult:
        self.hook(blocks)
        return super().write_batch(blocks)


def hook_store(db_url: str, wire_ids: Sequence[int] = (1, 2)) -> HookStore:
    s = HookStore(Store.open(db_url).engine)
    for w in wire_ids:
        s.add_machine(f"crane-{w}", w, SECRET)
    return s


@pytest.fixture
def store(db_url: str) -> Store:
    s = Store.open(db_url)
    for w in (1, 2):
        s.add_machine(f"crane-{w}", w, SECRET)
    return s


# --- tests ---------------------------------------------------------------------------------------
@pytest.mark.timeout(60)
def test_stores_every_sample_and_acks(store: Store) -> None:
    vals = {w: grid_values(1234, w) for w in (1, 2)}
    senders = [make_sender(w, vals[w]) for w in (1, 2)]
    with running_daemon(store) as d:
        assert drive(senders, d.address, 30), "senders still hold unacknowledged datagrams"
    for w in (1, 2):
        got = store.read_samples(f"crane-{w}", 0, 4e9)
        assert got.channels == LAYOUT.names
        assert np.array_equal(got.values, vals[w])
        assert np.allclose(got.t_s, (T0_NS + np.arange(1234) * PERIOD_NS) / 1e9, atol=1e-6)
    m = d.snapshot()
    assert m["stored_samples"] == 2 * 1234 and m["dropped_total"] == 0
    assert m["received"] == m["accepted"] == m["stored_blocks"] + m["duplicates"]
    assert m["acks_sent"] > 0 and m["write_errors"] == 0 and m["writer_restarts"] == 0


@pytest.mark.timeout(60)
def test_ack_only_after_commit(db_url: str) -> None:
    gs = hook_store(db_url, [1])
    gate = threading.Event()
    gs.hook = lambda blocks: None if gate.wait(20) else pytest.fail("gate never opened")
    with running_daemon(gs) as d:
        s = udp()
        s.sendto(datagram(1, 5), d.address)
        s.settimeout(0.5)
        with pytest.raises(TimeoutError):
            s.recv(2048)  # not durable yet: no ack
        assert gs.stats().blocks == 0
        gate.set()
        s.settimeout(10)
        ack = decode_ack(s.recv(2048), key(1))
        assert ack.covers(5) and ack.epoch == 7
        assert gs.stats().blocks == 1  # the ack came after the commit
        s.close()


@pytest.mark.timeout(60)
def test_bad_datagrams_are_counted_per_reason_and_never_answered(store: Store) -> None:
    good = datagram(1, 1)
    forged = bytearray(good)
    forged[-1] ^= 0x01
    wrong_version = bytearray(good)
    wrong_version[2] = 99
    bad = {
        "garbage": [b"hello world", bytes(range(256)) * 4],
        "truncated": [b"", good[:20]],
        "bad_hmac": [bytes(forged), good[:-5],  # a cut tag cannot verify
                     encode_data(key(1, b"x" * 32), 2, T0_NS, PERIOD_NS, grid_values(5, 1),
                                 epoch=7)],
        "unknown_machine": [encode_data(key(77), 1, T0_NS, PERIOD_NS, grid_values(5, 2),
                                        epoch=7)],
        "wrong_version": [bytes(wrong_version)],
    }
    with running_daemon(store) as d:
        s = udp()
        s.sendto(good, d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(1)
        # now seq 1 is durable: a forged copy of it (registered wire id, low seq, bad tag) must
        # not be answered with that machine's real ack, nor anything else
        for dgs in bad.values():
            for dg in dgs:
                s.sendto(dg, d.address)
        wait_for(lambda: d.snapshot()["received"] >= 1 + sum(map(len, bad.values())))
        s.settimeout(0.5)
        with pytest.raises(TimeoutError):
            s.recv(2048)
        s.settimeout(5)
        s.sendto(good, d.address)  # an authentic replay of a durable datagram: acked again
        assert decode_ack(s.recv(2048), key(1)).covers(1)
        s.close()
        wait_for(lambda: d.snapshot()["received"] >= 2 + sum(map(len, bad.values())))
    m = d.snapshot()
    assert m["dropped"] == {r: len(v) for r, v in bad.items()} | {"replayed": 1}
    assert m["stored_blocks"] == 1 and store.stats().samples == 20
    assert m["acks_sent"] == 2 and m["refusals_sent"] == 0


@pytest.mark.timeout(60)
def test_shutdown_flushes_everything_accepted(db_url: str) -> None:
    ss = hook_store(db_url, [1])
    ss.hook = lambda blocks: time.sleep(0.2)
    n = 200
    with running_daemon(ss, batch_max=10) as d:
        s = udp()
        for seq in range(n):
            s.sendto(datagram(1, seq, n=10, seed=seq), d.address)
        wait_for(lambda: d.snapshot()["received"] >= n)
        assert d.snapshot()["queue_depth"] > 0  # the writer is behind: shutdown must flush
        s.close()
    assert ss.stats().blocks == n
    assert d.snapshot()["dropped_total"] == 0


@pytest.mark.timeout(60)
def test_status_reports_live_fanout_and_prometheus_metrics(store: Store) -> None:
    bus = InProcessBus()
    sub = bus.subscribe()
    vals = grid_values(300, 3)
    sender = make_sender(1, vals)
    sender.push_status(StatusReport("crane-1", 0, T0_NS, 61.05, 28.19, 80.0, 1234.5))
    with running_daemon(store, bus=bus, metrics_host="127.0.0.1", metrics_port=0) as d:
        assert drive([sender], d.address, 30)
        assert d.metrics_url is not None and d.metrics_url.startswith("http://127.0.0.1:")
        # an ack is counted after its sendto returns: the sender may have it a moment earlier
        wait_for(lambda: d.snapshot()["acks_sent"] >= 1)
        text = urllib.request.urlopen(d.metrics_url, timeout=5).read().decode()
        s = udp()
        s.sendto(b"junk", d.address)  # one dropped datagram, to see a labelled counter
        wait_for(lambda: d.snapshot()["dropped"].get("garbage") == 1)
        text2 = urllib.request.urlopen(d.metrics_url, timeout=5).read().decode()
        s.close()
    notes = []
    while (note := sub.get(timeout=0.1)) is not None:
        notes.append(note)
    assert sum(n.n for n in notes) == 300
    got = np.concatenate([n.block.values for n in sorted(notes, key=lambda n: n.seq)
                          if n.block is not None])
    assert np.array_equal(got, vals)
    m = store.get_machine("crane-1")
    assert m.latitude_deg == pytest.approx(61.05, abs=1e-7)
    assert m.operating_hours == pytest.approx(1234.5, abs=1 / 3600)
    assert not math.isnan(m.last_seen_s or math.nan)
    lines = {ln.rsplit(" ", 1)[0]: float(ln.rsplit(" ", 1)[1]) for ln in text.splitlines()
             if ln and not ln.startswith("#")}
    assert lines["cranetwin_ingest_stored_samples_total"] == 300
    assert lines["cranetwin_ingest_status_reports_total"] == 1
    assert lines["cranetwin_ingest_acks_sent_total"] >= 1
    assert lines["cranetwin_ingest_writer_restarts_total"] == 0
    assert lines["cranetwin_ingest_write_seconds_count"] >= 1
    assert "cranetwin_ingest_queue_depth" in lines
    assert 'cranetwin_ingest_dropped_total{reason="garbage"} 1.0' in text2
    snap = d.snapshot()
    assert snap["status_reports"] == 1 and snap["stored_samples"] == 300


@pytest.mark.timeout(60)
def test_two_daemons_in_one_process_have_their_own_metrics(db_url: str, tmp_path: Any) -> None:
    a, b = Store.open(db_url), Store.open(f"sqlite:///{tmp_path / 'other.db'}")
    for s in (a, b):
        s.add_machine("crane-1", 1, SECRET)
    with running_daemon(a, metrics_host="127.0.0.1", metrics_port=0) as da, \
            running_daemon(b, metrics_host="127.0.0.1", metrics_port=0) as db:
        sock = udp()
        sock.sendto(datagram(1, 1), da.address)
        assert decode_ack(sock.recv(2048), key(1)).covers(1)
        sock.close()
        assert da.metrics_url and db.metrics_url and da.metrics_url != db.metrics_url
        ta = urllib.request.urlopen(da.metrics_url, timeout=5).read().decode()
        tb = urllib.request.urlopen(db.metrics_url, timeout=5).read().decode()
    assert "cranetwin_ingest_stored_blocks_total 1.0" in ta
    assert "cranetwin_ingest_stored_blocks_total 0.0" in tb
