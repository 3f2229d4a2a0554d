"""Machine-side shell: spill file, sample sources, and run_sender against an in-process UDP
server on loopback (real sockets, real asyncio)."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import threading
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.cli.send import parse_key
from cranetwin.errors import CraneTwinError
from cranetwin.ingest.sender import (
    FileSpill,
    RecordingSource,
    SyntheticSource,
    parse_host,
    run_fleet,
    run_sender,
)
from cranetwin.model import load_machine
from cranetwin.protocol import (
    Layout,
    MachineKey,
    Receiver,
    ReplayedError,
    Sender,
    StatusReport,
    on_grid,
)
from cranetwin.samples import SampleBlock

LAYOUT = Layout.from_channels(load_machine("patu655").channels)
SECRET = bytes.fromhex("00112233445566778899aabbccddeeff" * 2)
PERIOD = 10_000_000


def test_file_spill_is_fifo_survives_reopen_and_cuts_torn_records(tmp_path: Path) -> None:
    p = tmp_path / "m.spill"
    sp = FileSpill(p)
    items = [bytes([i]) * (i + 1) for i in range(20)]
    for it in items:
        sp.append(it)
    assert [sp.popleft() for _ in range(5)] == items[:5]
    sp.close()
    with open(p, "ab") as f:  # a record torn by a crash mid-write
        f.write(b"\x00\x00\x01\x00abc")
    sp = FileSpill(p)
    assert len(sp) == 15
    assert [sp.popleft() for _ in range(15)] == items[5:]
    assert len(sp) == 0 and p.stat().st_size == 8  # drained: truncated to the header
    with pytest.raises(IndexError):
        sp.popleft()
    sp.close()


def test_sender_core_with_file_spill_keeps_memory_bounded(tmp_path: Path) -> None:
    key = MachineKey(1, "m1", SECRET, LAYOUT)
    spill = FileSpill(tmp_path / "m1.spill")
    s = Sender(key, PERIOD, batch_samples=50, max_unacked=4, spill=spill)
    src = SyntheticSource(key, seed=1)
    values = src.read(0, 5000)
    s.push(0, values)  # 100 datagrams while nothing is acked
    assert s.in_memory == 4 and s.spilled == 96 and len(spill) == 96
    rx = Receiver({1: key})
    got: dict[int, SampleBlock] = {}
    now = 0
    while not s.idle:
        for dg in s.datagrams_to_send(now):
            item = rx.receive(dg, now)
            assert isinstance(item, SampleBlock)
            got[item.seq] = item
            rx.mark_durable("m1", item.seq)
        s.receive(rx.ack("m1", now), now)
        assert s.in_memory <= 4
        now += 10**8
    v = np.concatenate([got[k].values for k in sorted(got)])
    assert np.array_equal(v, on_grid(values, LAYOUT.resolutions), equal_nan=True)
    assert (tmp_path / "m1.spill").stat().st_size == 8


def test_synthetic_source_is_stateless_in_range_and_on_grid() -> None:
    key = MachineKey(1, "m1", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=3)
    a = src.read(100, 50)
    assert np.array_equal(a, src.read(100, 50), equal_nan=True)
    lo = np.array([c.min for c in LAYOUT.channels])
    hi = np.array([c.max for c in LAYOUT.channels])
    ok = np.isnan(a) | ((a >= lo - 1e-9) & (a <= hi + 1e-9))
    assert ok.all()
    assert np.array_equal(a, on_grid(a, LAYOUT.resolutions), equal_nan=True)
    rec = RecordingSource(np.arange(10.0)[:, None], offset=8)
    assert rec.read(0, 4)[:, 0].tolist() == [8.0, 9.0, 0.0, 1.0]


class _Server(asyncio.DatagramProtocol):
    """A minimal daemon: receive, store idempotently, 'commit' every 50 ms, ack; re-ack replays."""

    def __init__(self, keys: dict[int, MachineKey], drop_first: int = 0) -> None:
        self.rx = Receiver(keys)
        self.stored: dict[tuple[str, int], SampleBlock | StatusReport] = {}
        self.pending: dict[str, tuple[list[int], tuple[str, int]]] = {}
        self.drop_first = drop_first
        self.received = 0
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.received += 1
        if self.received <= self.drop_first:
            return  # a lossy start: the sender must retransmit
        try:
            item = self.rx.receive(data, 0)
        except ReplayedError as err:
            assert err.machine_id and self.transport
            self.transport.sendto(self.rx.ack(err.machine_id, 0), addr)
            return
        self.stored[(item.machine_id, item.seq)] = item
        seqs, _ = self.pending.setdefault(item.machine_id, ([], addr))
        seqs.append(item.seq)

    async def committer(self) -> None:
        while True:
            await asyncio.sleep(0.05)
            for mid, (seqs, addr) in list(self.pending.items()):
                for s in seqs:
                    self.rx.mark_durable(mid, s)
                assert self.transport
                self.transport.sendto(self.rx.ack(mid, 0), addr)
            self.pending.clear()


async def _serve(keys: dict[int, MachineKey], **kw: int) -> tuple[_Server, int, asyncio.Task[None]]:
    loop = asyncio.get_running_loop()
    srv = _Server(keys, **kw)
    transport, _ = await loop.create_datagram_endpoint(lambda: srv, local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    return srv, port, asyncio.create_task(srv.committer())


def _samples(srv: _Server, mid: str) -> np.ndarray:
    blocks = sorted((s, b) for (m, s), b in srv.stored.items()
                    if m == mid and isinstance(b, SampleBlock))
    return np.concatenate([b.values for _, b in blocks])


def test_run_sender_streams_everything_over_loopback(caplog: pytest.LogCaptureFixture) -> None:
    key = MachineKey(11, "crane-11", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=11)

    async def main() -> None:
        srv, port, task = await _serve({11: key}, drop_first=3)
        stats = await run_sender(key, ("127.0.0.1", port), src, speed=25.0, duration_s=4.0,
                                 status_every_s=1.0, rto_s=0.2, tick_s=0.02)
        task.cancel()
        assert stats.unacked == 0 and stats.samples == 400 and stats.acked_samples == 400
        assert stats.retransmissions >= 1  # the first datagrams were dropped
        v = _samples(srv, "crane-11")
        assert np.array_equal(v, on_grid(src.read(0, 400), LAYOUT.resolutions), equal_nan=True)
        status = [b for b in srv.stored.values() if isinstance(b, StatusReport)]
        assert len(status) >= 4 and status[0].latitude_deg == pytest.approx(61.0)
        assert stats.bytes_per_sample < 20

    with caplog.at_level(logging.DEBUG):
        asyncio.run(main())
    assert SECRET.hex() not in caplog.text and "crane-11" in caplog.text


def test_sender_survives_a_server_that_starts_late(tmp_path: Path) -> None:
    key = MachineKey(12, "crane-12", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=12)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    async def main() -> None:
        loop = asyncio.get_running_loop()
        sender = asyncio.create_task(run_sender(
            key, ("127.0.0.1", port), src, speed=20.0, duration_s=3.0, rto_s=0.1,
            spill_path=tmp_path / "c12.spill", max_unacked=4, status_every_s=0))
        await asyncio.sleep(0.8)  # server down: ICMP errors, spill fills
        srv = _Server({12: key})
        await loop.create_datagram_endpoint(lambda: srv, local_addr=("127.0.0.1", port))
        task = asyncio.create_task(srv.committer())
        stats = await sender
        task.cancel()
        assert stats.unacked == 0 and stats.max_spilled > 0
        v = _samples(srv, "crane-12")
        assert np.array_equal(v, on_grid(src.read(0, 300), LAYOUT.resolutions), equal_nan=True)

    asyncio.run(main())


def test_fleet_of_three_over_one_loop() -> None:
    keys = [MachineKey(20 + i, f"f-{i}", SECRET, LAYOUT) for i in range(3)]
    srcs = [SyntheticSource(k, seed=i) for i, k in enumerate(keys)]

    async def main() -> None:
        srv, port, task = await _serve({k.wire_id: k for k in keys})
        stats = await run_fleet(keys, ("127.0.0.1", port), srcs, speed=50.0, duration_s=2.0,
                                status_every_s=0, tick_s=0.02)
        task.cancel()
        assert [s.unacked for s in stats] == [0, 0, 0]
        for k, src in zip(keys, srcs, strict=True):
            assert np.array_equal(_samples(srv, k.machine_id),
                                  on_grid(src.read(0, 200), LAYOUT.resolutions), equal_nan=True)

    asyncio.run(main())


def test_key_and_host_parsing() -> None:
    assert parse_key(SECRET.hex()) == SECRET
    assert parse_key("a-text-secret-of-20b") == b"a-text-secret-of-20b"
    with pytest.raises(CraneTwinError):
        parse_key("short")
    assert parse_host("127.0.0.1:5005") == ("127.0.0.1", 5005)
    assert parse_host("[::1]:7") == ("::1", 7)
    with pytest.raises(CraneTwinError):
        parse_host("localhost")


def test_send_cli_refuses_without_a_key(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CRANETWIN_MACHINE_KEY", raising=False)
    r = CliRunner().invoke(app, ["send", "--machine", "x", "--wire-id", "1",
                                 "--scenario", "synthetic", "--duration", "0.1"])
    assert r.exit_code != 0
    assert "key" in (r.output + str(r.exception)).lower()


def test_synthetic_source_does_not_depend_on_chunking() -> None:
    src = SyntheticSource(MachineKey(1, "m1", SECRET, LAYOUT), seed=5)
    whole = src.read(0, 3000)
    parts = np.concatenate([src.read(i, 7) for i in range(0, 3000, 7)])[:3000]
    assert np.array_equal(whole, parts, equal_nan=True)


def test_status_carries_the_optional_channels() -> None:
    key = MachineKey(13, "crane-13", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=13, dropout=0.0)

    async def main() -> None:
        srv, port, task = await _serve({13: key})
        await run_sender(key, ("127.0.0.1", port), src, speed=50.0, duration_s=1.0,
                         status_every_s=0.5, tick_s=0.02)
        task.cancel()
        status = [b for b in srv.stored.values() if isinstance(b, StatusReport)]
        assert status and all(set(s.channels) == {"slew_angle"} for s in status)
        j = LAYOUT.index("slew_angle")
        t_first = min(b.t0_ns for b in srv.stored.values() if isinstance(b, SampleBlock))
        for s in status:  # the status repeats the latest sample of the optional channel
            i = (s.t_ns - t_first) // PERIOD
            assert s.channels["slew_angle"] == pytest.approx(src.read(i, 1)[0, j])

    asyncio.run(main())


def _udp_server_thread(keys: dict[int, MachineKey]) -> tuple[int, dict[tuple[str, int], object],
                                                             threading.Event]:
    """A blocking loopback server in a thread: receive, store, ack at once."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    stored: dict[tuple[str, int], object] = {}
    done = threading.Event()
    rx = Receiver(keys)

    def loop() -> None:
        while not done.is_set():
            try:
                data, addr = sock.recvfrom(2048)
            except TimeoutError:
                continue
            try:
                item = rx.receive(data, 0)
            except ReplayedError as err:
                assert err.machine_id
                sock.sendto(rx.ack(err.machine_id, 0), addr)
                continue
            stored[(item.machine_id, item.seq)] = item
            rx.mark_durable(item.machine_id, item.seq)
            sock.sendto(rx.ack(item.machine_id, 0), addr)
        sock.close()

    threading.Thread(target=loop, daemon=True).start()
    return sock.getsockname()[1], stored, done


def test_send_cli_streams_a_small_fleet(monkeypatch: pytest.MonkeyPatch) -> None:
    keys = {100 + i: MachineKey(100 + i, f"cli-{i}", SECRET, LAYOUT) for i in range(2)}
    port, stored, done = _udp_server_thread(keys)
    monkeypatch.setenv("CRANETWIN_MACHINE_KEY", SECRET.hex())
    try:
        r = CliRunner().invoke(app, ["send", "--machine", "cli", "--wire-id", "100",
                                     "--machines", "2", "--scenario", "synthetic",
                                     "--host", f"127.0.0.1:{port}", "--speed", "50",
                                     "--duration", "1", "--json"])
    finally:
        done.set()
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert [o["unacked"] for o in out] == [0, 0] and [o["samples"] for o in out] == [100, 100]
    assert SECRET.hex() not in r.output
    for i in range(2):
        n = sum(b.n for (m, _), b in stored.items() if m == f"cli-{i}"
                and isinstance(b, SampleBlock))
        assert n == 100


def test_spill_left_by_an_earlier_run_is_sent_first_and_not_skipped(tmp_path: Path) -> None:
    """A restarted sender with a non-empty spill file must send the old datagrams before (and
    without the receiver's floor jumping over them because of) the new ones."""
    key = MachineKey(14, "crane-14", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=14)
    old = Sender(key, PERIOD, first_seq=100, batch_samples=50, max_unacked=2,
                 spill=FileSpill(tmp_path / "s"))
    old.push(0, src.read(0, 500))  # 10 datagrams, nothing acked; the process dies here
    assert old.in_memory == 2 and old.spilled == 8
    old.spill.close()  # type: ignore[attr-defined]
    new = Sender(key, PERIOD, first_seq=10_000, batch_samples=50, max_unacked=2,
                 spill=FileSpill(tmp_path / "s"))
    assert new.in_memory == 2 and new.spilled == 6  # seqs 102… reloaded (100, 101 were in RAM)
    new.push(500 * PERIOD, src.read(500, 100))
    rx = Receiver({14: key})
    got: dict[int, SampleBlock] = {}
    now = 0
    while not new.idle:
        for dg in new.datagrams_to_send(now):
            item = rx.receive(dg, now)  # must never be rejected as replayed
            assert isinstance(item, SampleBlock)
            got[item.seq] = item
            rx.mark_durable("crane-14", item.seq)
        new.receive(rx.ack("crane-14", now), now)
        now += 10**8
    assert sorted(got) == list(range(102, 110)) + [10_000, 10_001]
    v = np.concatenate([got[s].values for s in sorted(got)])
    assert np.array_equal(v, on_grid(src.read(100, 500), LAYOUT.resolutions), equal_nan=True)
