"""Ingest daemon: stores what machines send, acks only after commit, counts and drops bad input,
flushes on shutdown, publishes new blocks, writes metrics."""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from conftest import SECRET, running_daemon
from cranetwin.bench.ingest import T0_NS, Fleet, grid_values, make_sender, patu_layout
from cranetwin.protocol import MachineKey, StatusReport, decode_ack, encode_data
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store
from cranetwin.storage.live import InProcessBus

LAYOUT = patu_layout()


def key(wire_id: int, secret: bytes = SECRET) -> MachineKey:
    return MachineKey(wire_id, f"crane-{wire_id}", secret, LAYOUT)


@pytest.fixture
def store(db_url: str) -> Store:
    s = Store.open(db_url)
    for w in (1, 2):
        s.add_machine(f"crane-{w}", w, SECRET)
    return s


def udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(5)
    return s


def test_stores_every_sample_and_acks(store: Store) -> None:
    vals = {w: grid_values(LAYOUT, 1234, w) for w in (1, 2)}
    with running_daemon(store) as d:
        assert d.address is not None
        fleet = Fleet([make_sender(key(w), vals[w]) for w in (1, 2)], d.address)
        assert fleet.run(timeout_s=30), "senders still hold unacknowledged datagrams"
        fleet.close()
    for w in (1, 2):
        got = store.read_samples(f"crane-{w}", 0, 4e9)
        assert got.channels == LAYOUT.names
        assert np.array_equal(got.values, vals[w])
        assert np.allclose(got.t_s, (T0_NS + np.arange(1234) * 10_000_000) / 1e9, atol=1e-6)
    m = d.snapshot()
    assert m["stored_samples"] == 2 * 1234 and m["dropped_total"] == 0
    assert m["received"] == m["accepted"] == m["stored_blocks"] + m["duplicates"]


class GatedStore(Store):
    """A store whose writes wait for a gate (to observe the daemon before commit)."""

    gate: threading.Event

    def store_blocks(self, blocks: Sequence[SampleBlock]) -> list[SampleBlock]:
        assert self.gate.wait(20)
        return super().store_blocks(blocks)


def test_ack_only_after_commit(db_url: str) -> None:
    gs = GatedStore(Store.open(db_url).engine)
    gs.gate = threading.Event()
    gs.add_machine("crane-1", 1, SECRET)
    with running_daemon(gs) as d:
        assert d.address is not None
        s = udp()
        s.sendto(encode_data(key(1), 5, T0_NS, 10_000_000, grid_values(LAYOUT, 20, 0)),
                 d.address)
        s.settimeout(0.5)
        with pytest.raises(TimeoutError):
            s.recv(2048)  # not durable yet: no ack
        assert gs.stats().blocks == 0
        gs.gate.set()
        s.settimeout(10)
        ack = decode_ack(s.recv(2048), key(1))
        assert ack.covers(5)
        assert gs.stats().blocks == 1  # the ack came after the commit
        s.close()


def test_bad_datagrams_are_counted_per_reason_and_dropped(store: Store) -> None:
    good = encode_data(key(1), 1, T0_NS, 10_000_000, grid_values(LAYOUT, 20, 0))
    forged = bytearray(good)
    forged[-1] ^= 0x01
    wrong_version = bytearray(good)
    wrong_version[2] = 99
    bad = {
        "garbage": [b"hello world", bytes(range(256)) * 4],
        "truncated": [b"", good[:20]],
        "bad_hmac": [bytes(forged), good[:-5],  # a cut tag cannot verify
                     encode_data(key(1, b"x" * 32), 2, T0_NS, 10_000_000,
                                 grid_values(LAYOUT, 5, 1))],
        "unknown_machine": [encode_data(key(77), 1, T0_NS, 10_000_000,
                                        grid_values(LAYOUT, 5, 2))],
        "wrong_version": [bytes(wrong_version)],
    }
    with running_daemon(store) as d:
        assert d.address is not None
        s = udp()
        for dgs in bad.values():
            for dg in dgs:
                s.sendto(dg, d.address)
        s.sendto(good, d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(1)
        s.sendto(good, d.address)  # a replay of a durable datagram: dropped, but acked again
        assert decode_ack(s.recv(2048), key(1)).covers(1)
        s.close()
        deadline = time.monotonic() + 10
        while d.snapshot()["received"] < sum(map(len, bad.values())) + 2:
            assert time.monotonic() < deadline
            time.sleep(0.01)
    m = d.snapshot()
    expected = {r: len(v) for r, v in bad.items()} | {"replayed": 1}
    got = m["dropped"]
    assert got == expected
    assert m["stored_blocks"] == 1 and store.stats().samples == 20


class SlowStore(Store):
    def store_blocks(self, blocks: Sequence[SampleBlock]) -> list[SampleBlock]:
        time.sleep(0.2)
        return super().store_blocks(blocks)


def test_shutdown_flushes_everything_accepted(db_url: str) -> None:
    ss = SlowStore(Store.open(db_url).engine)
    ss.add_machine("crane-1", 1, SECRET)
    n = 200
    with running_daemon(ss, batch_max=10) as d:
        assert d.address is not None
        s = udp()
        for seq in range(n):
            s.sendto(encode_data(key(1), seq, T0_NS + seq * 10 * 10_000_000, 10_000_000,
                                 grid_values(LAYOUT, 10, seq)), d.address)
        deadline = time.monotonic() + 10
        while d.snapshot()["received"] < n:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        assert d.snapshot()["queue_depth"] > 0  # the writer is behind: shutdown must flush
        s.close()
    assert ss.stats().blocks == n


def test_status_reports_and_live_fanout_and_metrics(store: Store, tmp_path: Path) -> None:
    bus = InProcessBus()
    sub = bus.subscribe()
    metrics = tmp_path / "m.json"
    vals = grid_values(LAYOUT, 300, 3)
    sender = make_sender(key(1), vals)
    sender.push_status(StatusReport("crane-1", 0, T0_NS, 61.05, 28.19, 80.0, 1234.5))
    with running_daemon(store, bus=bus, metrics_path=metrics) as d:
        assert d.address is not None
        fleet = Fleet([sender], d.address)
        assert fleet.run(timeout_s=30)
        fleet.close()
        time.sleep(0.5)
        assert metrics.exists()
        live = json.loads(metrics.read_text())
        assert {"received", "dropped", "queue_depth", "queue_max", "stored_samples"} <= set(live)
    notes = []
    while (note := sub.get(timeout=0.1)) is not None:
        notes.append(note)
    assert sum(n.n for n in notes) == 300
    assert all(n.block is not None for n in notes)
    got = np.concatenate([n.block.values for n in sorted(notes, key=lambda n: n.seq)
                          if n.block is not None])
    assert np.array_equal(got, vals)
    m = store.get_machine("crane-1")
    assert m.latitude_deg == pytest.approx(61.05, abs=1e-7)
    assert m.operating_hours == pytest.approx(1234.5, abs=1 / 3600)
    assert not math.isnan(m.last_seen_s or math.nan)
    final = json.loads(metrics.read_text())
    assert final["status_reports"] == 1 and final["stored_samples"] == 300
