"""Machine-side shell: sample sources, the journaled sans-IO sender, run_sender against an
in-process UDP server on loopback (real sockets, real asyncio), restarts that resume from the
journal, refusals, and the ``cranetwin send`` command (secrets, journal, exit status)."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.cli.send import default_journal_root, parse_key
from cranetwin.errors import CraneTwinError
from cranetwin.ingest.journal import FileJournal, SenderError
from cranetwin.ingest.sender import (
    RecordingSource,
    SyntheticSource,
    journal_owner,
    parse_host,
    run_fleet,
    run_sender,
)
from cranetwin.model import load_machine
from cranetwin.protocol import (
    Layout,
    MachineKey,
    MemoryJournal,
    Receiver,
    RefusedError,
    ReplayedError,
    Sender,
    StatusReport,
    on_grid,
)
from cranetwin.samples import SampleBlock

LAYOUT = Layout.from_channels(load_machine("patu655").channels)
SECRET = bytes.fromhex("00112233445566778899aabbccddeeff" * 2)
PERIOD = 10_000_000


def expected(src: SyntheticSource, block: SampleBlock) -> np.ndarray:
    """What the source produced for a stored block: row = time / period."""
    return on_grid(src.read(block.t0_ns // PERIOD, block.n), LAYOUT.resolutions)


# --- sources -----------------------------------------------------------------------------------
@pytest.mark.timeout(10)
def test_synthetic_source_is_stateless_in_range_and_on_grid() -> None:
    key = MachineKey(1, "m1", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=3)
    row = time.time_ns() // PERIOD  # rows are absolute sample times
    a = src.read(row, 50)
    assert np.array_equal(a, src.read(row, 50), equal_nan=True)
    lo = np.array([c.min for c in LAYOUT.channels])
    hi = np.array([c.max for c in LAYOUT.channels])
    ok = np.isnan(a) | ((a >= lo - 1e-9) & (a <= hi + 1e-9))
    assert ok.all()
    assert np.array_equal(a, on_grid(a, LAYOUT.resolutions), equal_nan=True)
    rec = RecordingSource(np.arange(10.0)[:, None], offset=8)
    assert rec.read(0, 4)[:, 0].tolist() == [8.0, 9.0, 0.0, 1.0]


@pytest.mark.timeout(10)
def test_synthetic_source_does_not_depend_on_chunking() -> None:
    src = SyntheticSource(MachineKey(1, "m1", SECRET, LAYOUT), seed=5)
    r0 = 170_000_000_000
    whole = src.read(r0, 3000)
    parts = np.concatenate([src.read(r0 + i, 7) for i in range(0, 3000, 7)])[:3000]
    assert np.array_equal(whole, parts, equal_nan=True)


# --- the sans-IO sender on a file journal -------------------------------------------------------
def _deliver(sender: Sender, rx: Receiver, mid: str, got: dict[tuple[int, int], SampleBlock],
             now: int) -> int:
    """Run sender ↔ receiver (lossless, commit at once) until the sender is idle."""
    while not sender.idle:
        for dg in sender.datagrams_to_send(now):
            try:
                item = rx.receive(dg, now)
            except ReplayedError as err:
                sender.receive(rx.ack(mid, err.epoch, now), now)
                continue
            assert isinstance(item, SampleBlock)
            assert (item.epoch, item.seq) not in got
            got[(item.epoch, item.seq)] = item
            rx.mark_durable(mid, item.epoch, item.seq)
        sender.receive(rx.ack(mid, sender.epoch, now), now)
        now += 10**8
    return now


@pytest.mark.timeout(20)
def test_a_crashed_sender_resumes_from_its_file_journal(tmp_path: Path) -> None:
    """Datagrams handed out for sending are durable: a sender that dies with nothing acked
    is replaced by one on the same journal that sends them all (same epoch), then goes on."""
    key = MachineKey(14, "crane-14", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=14)
    now = time.time_ns()
    r0 = now // PERIOD - 1000
    j = FileJournal(tmp_path / "j", owner=journal_owner(key))
    old = Sender(key, PERIOD, journal=j, batch_samples=50, max_unacked=2)
    old.push(r0 * PERIOD, src.read(r0, 500))  # 10 datagrams
    assert len(old.datagrams_to_send(now)) == 2  # synced, 2 in flight, 8 waiting in the journal
    assert j.syncs == 1 and old.unacked == 10 and old.in_memory == 2
    epoch = j.epoch
    j._buf.clear()  # the process dies (kill -9): no close
    j._release_fds()
    j = FileJournal(tmp_path / "j", owner=journal_owner(key))
    new = Sender(key, PERIOD, journal=j, batch_samples=50, max_unacked=2)
    assert (new.epoch, new.next_seq, new.unacked) == (epoch, 10, 10)
    new.push((r0 + 500) * PERIOD, src.read(r0 + 500, 100))
    rx = Receiver({14: key})
    got: dict[tuple[int, int], SampleBlock] = {}
    _deliver(new, rx, "crane-14", got, now)
    assert sorted(got) == [(epoch, s) for s in range(12)]
    for b in got.values():
        assert np.array_equal(b.values, expected(src, b), equal_nan=True)
    assert len(j) == 0 and j.start == 12
    j.close()


@pytest.mark.timeout(20)
def test_a_refused_datagram_is_released_and_kept_in_the_dead_letter_file(tmp_path: Path) -> None:
    key = MachineKey(15, "crane-15", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=15, dropout=0.0)
    now = time.time_ns()
    r0 = now // PERIOD - 1000
    j = FileJournal(tmp_path / "j")
    s = Sender(key, PERIOD, journal=j, batch_samples=50)
    v = src.read(r0, 150)
    v[60, 0] = 1e12  # datagram 1 holds an impossible value
    s.push(r0 * PERIOD, v)
    rx = Receiver({15: key})
    stored: list[int] = []
    for dg in s.datagrams_to_send(now):
        try:
            item = rx.receive(dg, now)
        except RefusedError as err:
            assert err.reason == "out_of_range"
            s.receive(rx.refusal(err, now), now)
            continue
        stored.append(item.seq)
        rx.mark_durable("crane-15", item.epoch, item.seq)
    s.receive(rx.ack("crane-15", s.epoch, now), now)
    assert stored == [0, 2] and s.idle and s.refused == 1 and len(j) == 0
    lines = [json.loads(x) for x in j.rejected_path.read_text().splitlines()]
    assert [(x["seq"], x["reason"]) for x in lines] == [(1, "out_of_range")]
    j.close()


# --- run_sender against a loopback server --------------------------------------------------------
class _Server(asyncio.DatagramProtocol):
    """A minimal daemon: receive, store idempotently, 'commit' every 50 ms, ack; re-ack replays,
    refuse what the receiver refuses; ``drop_first`` datagrams are lost, ``mute`` drops all."""

    def __init__(self, keys: dict[int, MachineKey], drop_first: int = 0) -> None:
        self.rx = Receiver(keys)
        self.stored: dict[tuple[str, int, int], SampleBlock | StatusReport] = {}
        self.copies = 0  # stored including duplicates
        self.pending: dict[tuple[str, int], tuple[list[int], tuple[str, int]]] = {}
        self.drop_first = drop_first
        self.mute = False
        self.received = 0
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.received += 1
        if self.received <= self.drop_first or self.mute:
            return  # a lossy link: the sender must retransmit
        assert self.transport
        now = time.time_ns()
        try:
            item = self.rx.receive(data, now)
        except ReplayedError as err:
            assert err.machine_id
            self.transport.sendto(self.rx.ack(err.machine_id, err.epoch, now), addr)
            return
        except RefusedError as err:
            self.transport.sendto(self.rx.refusal(err, now), addr)
            return
        self.stored[(item.machine_id, item.epoch, item.seq)] = item
        self.copies += 1
        seqs, _ = self.pending.setdefault((item.machine_id, item.epoch), ([], addr))
        seqs.append(item.seq)

    async def committer(self) -> None:
        while True:
            await asyncio.sleep(0.05)
            for (mid, epoch), (seqs, addr) in list(self.pending.items()):
                for s in seqs:
                    self.rx.mark_durable(mid, epoch, s)
                assert self.transport
                self.transport.sendto(self.rx.ack(mid, epoch, time.time_ns()), addr)
            self.pending.clear()

    def blocks(self, mid: str) -> list[SampleBlock]:
        return [b for (m, _, _), b in sorted(self.stored.items(), key=lambda kv: kv[0])
                if m == mid and isinstance(b, SampleBlock)]


async def _serve(keys: dict[int, MachineKey], port: int = 0,
                 **kw: int) -> tuple[_Server, int, asyncio.Task[None]]:
    loop = asyncio.get_running_loop()
    srv = _Server(keys, **kw)
    transport, _ = await loop.create_datagram_endpoint(lambda: srv,
                                                       local_addr=("127.0.0.1", port))
    port = transport.get_extra_info("sockname")[1]
    return srv, port, asyncio.create_task(srv.committer())


def _check_all_stored(srv: _Server, mid: str, src: SyntheticSource, n: int) -> None:
    blocks = srv.blocks(mid)
    assert sum(b.n for b in blocks) == n
    t = np.concatenate([b.t0_ns + np.arange(b.n) * PERIOD for b in blocks])
    assert np.unique(t).size == t.size  # nothing twice
    for b in blocks:
        assert np.array_equal(b.values, expected(src, b), equal_nan=True)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.timeout(30)
def test_run_sender_streams_everything_over_loopback(tmp_path: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    key = MachineKey(11, "crane-11", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=11)

    async def main() -> None:
        srv, port, task = await _serve({11: key}, drop_first=3)
        stats = await run_sender(key, ("127.0.0.1", port), src, journal_dir=tmp_path / "j",
                                 speed=25.0, duration_s=4.0, status_every_s=1.0, min_rto_s=0.2,
                                 tick_s=0.02)
        task.cancel()
        assert stats.unacked == 0 and stats.samples == 400 and stats.acked_samples == 400
        assert stats.retransmissions >= 1  # the first datagrams were dropped
        assert stats.resumed == 0 and stats.epoch == FileJournal(tmp_path / "j").epoch
        assert 1 <= stats.fsyncs <= 20 + 8  # one per batch of new datagrams (8 per data second)
        _check_all_stored(srv, "crane-11", src, 400)
        status = [b for b in srv.stored.values() if isinstance(b, StatusReport)]
        assert len(status) >= 4 and status[0].latitude_deg == pytest.approx(61.0)
        assert stats.bytes_per_sample < 20

    with caplog.at_level(logging.DEBUG):
        asyncio.run(main())
    assert SECRET.hex() not in caplog.text and "crane-11" in caplog.text


@pytest.mark.timeout(30)
def test_sender_survives_a_server_that_starts_late(tmp_path: Path) -> None:
    key = MachineKey(12, "crane-12", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=12)
    port = _free_port()

    async def main() -> None:
        sender = asyncio.create_task(run_sender(
            key, ("127.0.0.1", port), src, journal_dir=tmp_path / "j", speed=20.0,
            duration_s=3.0, min_rto_s=0.1, max_rto_s=0.4, max_unacked=4, status_every_s=0))
        await asyncio.sleep(0.8)  # server down: ICMP errors, the journal fills
        srv, _, task = await _serve({12: key}, port=port)
        stats = await sender
        task.cancel()
        assert stats.unacked == 0 and stats.max_spilled > 0
        _check_all_stored(srv, "crane-12", src, 300)

    asyncio.run(main())


@pytest.mark.timeout(40)
def test_unacked_datagrams_stay_in_the_journal_and_go_first_on_the_next_start(
        tmp_path: Path) -> None:
    """No drain deadline discards data: a run whose acks never come returns with the datagrams
    on disk; the next start (producing nothing new) sends them, exactly once."""
    key = MachineKey(16, "crane-16", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=16)
    d = tmp_path / "j"

    async def main() -> None:
        srv, port, task = await _serve({16: key})
        srv.mute = True  # the link is down
        t0 = time.monotonic()
        first = await run_sender(key, ("127.0.0.1", port), src, journal_dir=d, speed=50.0,
                                 duration_s=2.0, drain_timeout_s=0.5, min_rto_s=0.1,
                                 status_every_s=0)
        assert time.monotonic() - t0 < 5
        assert first.acked_samples == 0 and first.unacked == 4 and first.samples == 200
        assert srv.stored == {}
        srv.mute = False
        second = await run_sender(key, ("127.0.0.1", port), None, journal_dir=d,
                                  min_rto_s=0.1, status_every_s=0)
        task.cancel()
        assert second.resumed == 4 and second.unacked == 0 and second.samples == 0
        assert second.acked_samples == 200 and second.epoch == first.epoch
        _check_all_stored(srv, "crane-16", src, 200)
        third = await run_sender(key, ("127.0.0.1", port), None, journal_dir=d)
        assert third.resumed == 0 and third.datagrams == 0

    asyncio.run(main())


@pytest.mark.timeout(30)
def test_a_restart_continues_the_sample_clock_of_a_run_ahead_of_real_time(tmp_path: Path) -> None:
    """At --speed 50 the data runs ahead of the wall clock; the next run starts after the
    journal's newest sample time, so nothing is produced twice for the same time (which the
    server would refuse as an overlap)."""
    key = MachineKey(21, "crane-21", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=21)

    async def main() -> None:
        srv, port, task = await _serve({21: key})
        runs = [await run_sender(key, ("127.0.0.1", port), src, journal_dir=tmp_path / "j",
                                 speed=50.0, duration_s=3.0, status_every_s=1.0, min_rto_s=0.2)
                for _ in range(2)]
        task.cancel()
        assert [r.unacked for r in runs] == [0, 0] and [r.refused for r in runs] == [0, 0]
        blocks = srv.blocks("crane-21")
        assert len(blocks) == 12  # 6 per run
        assert blocks[6].t0_ns == blocks[5].t0_ns + 50 * PERIOD  # run 2 goes on after run 1
        _check_all_stored(srv, "crane-21", src, 600)

    asyncio.run(main())


@pytest.mark.timeout(30)
def test_stop_syncs_and_returns_at_once_and_the_rest_is_sent_later(tmp_path: Path) -> None:
    key = MachineKey(17, "crane-17", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=17)
    d = tmp_path / "j"

    async def main() -> None:
        srv, port, task = await _serve({17: key})
        srv.mute = True
        stop = asyncio.Event()
        run = asyncio.create_task(run_sender(key, ("127.0.0.1", port), src, journal_dir=d,
                                             speed=10.0, stop=stop, batch_samples=50,
                                             status_every_s=0, min_rto_s=0.1))
        await asyncio.sleep(1.0)
        stop.set()  # SIGTERM
        t0 = time.monotonic()
        first = await run
        assert time.monotonic() - t0 < 1.0  # no drain
        assert first.samples > 0 and first.unacked >= first.samples // 50
        j = FileJournal(d)
        pending = len(j)
        j.close()
        assert pending == first.unacked  # all of it on disk, the short last batch included
        srv.mute = False
        second = await run_sender(key, ("127.0.0.1", port), None, journal_dir=d,
                                  min_rto_s=0.1)
        task.cancel()
        assert second.unacked == 0
        _check_all_stored(srv, "crane-17", src, first.samples)

    asyncio.run(main())


@pytest.mark.timeout(30)
def test_run_sender_counts_refusals(tmp_path: Path) -> None:
    key = MachineKey(18, "crane-18", SECRET, LAYOUT)
    good = SyntheticSource(key, seed=18, dropout=0.0)

    class Poisoned:
        def read(self, i0: int, m: int) -> np.ndarray:
            v = good.read(i0, m)
            v[(i0 + np.arange(m)) % 250 == 0, 0] = 1e12  # one bad sample per 250
            return v

    async def main() -> None:
        srv, port, task = await _serve({18: key})
        stats = await run_sender(key, ("127.0.0.1", port), Poisoned(),
                                 journal_dir=tmp_path / "j", speed=50.0, duration_s=5.0,
                                 status_every_s=0, min_rto_s=0.2)
        task.cancel()
        assert stats.unacked == 0 and stats.refused == 2 and stats.refused_samples == 100
        assert stats.acked_samples == 400
        assert len((tmp_path / "j" / "rejected.log").read_text().splitlines()) == 2

    asyncio.run(main())


@pytest.mark.timeout(20)
def test_run_sender_needs_a_journal_and_refuses_one_of_another_key(tmp_path: Path) -> None:
    key = MachineKey(19, "crane-19", SECRET, LAYOUT)
    other = MachineKey(19, "crane-19", b"another-secret-0123456789", LAYOUT)

    async def main() -> None:
        with pytest.raises(SenderError, match="journal"):
            await run_sender(key, ("127.0.0.1", 9), None)
        await run_sender(key, ("127.0.0.1", 9), None, journal_dir=tmp_path / "j")
        with pytest.raises(SenderError, match="belongs to"):
            await run_sender(other, ("127.0.0.1", 9), None, journal_dir=tmp_path / "j")

    asyncio.run(main())
    assert SECRET.hex() not in journal_owner(key) and journal_owner(key) != journal_owner(other)


@pytest.mark.timeout(30)
def test_fleet_of_three_over_one_loop(tmp_path: Path) -> None:
    keys = [MachineKey(20 + i, f"f-{i}", SECRET, LAYOUT) for i in range(3)]
    srcs = [SyntheticSource(k, seed=i) for i, k in enumerate(keys)]

    async def main() -> None:
        srv, port, task = await _serve({k.wire_id: k for k in keys})
        stats = await run_fleet(keys, ("127.0.0.1", port), srcs, journal_dir=tmp_path,
                                speed=50.0, duration_s=2.0, status_every_s=0, tick_s=0.02)
        task.cancel()
        assert [s.unacked for s in stats] == [0, 0, 0]
        assert len({s.epoch for s in stats}) == 3
        for k, src in zip(keys, srcs, strict=True):
            _check_all_stored(srv, k.machine_id, src, 200)
            assert (tmp_path / k.machine_id / "state").exists()

    asyncio.run(main())


@pytest.mark.timeout(20)
def test_status_carries_the_optional_channels() -> None:
    key = MachineKey(13, "crane-13", SECRET, LAYOUT)
    src = SyntheticSource(key, seed=13, dropout=0.0)

    async def main() -> None:
        srv, port, task = await _serve({13: key})
        await run_sender(key, ("127.0.0.1", port), src, journal=MemoryJournal(), speed=50.0,
                         duration_s=1.0, status_every_s=0.5, tick_s=0.02)
        task.cancel()
        status = [b for b in srv.stored.values() if isinstance(b, StatusReport)]
        assert status and all(set(s.channels) == {"slew_angle"} for s in status)
        j = LAYOUT.index("slew_angle")
        for s in status:  # the status repeats the latest sample of the optional channel
            assert s.channels["slew_angle"] == pytest.approx(src.read(s.t_ns // PERIOD, 1)[0, j])

    asyncio.run(main())


# --- the command ---------------------------------------------------------------------------------
@pytest.mark.timeout(10)
def test_key_and_host_parsing() -> None:
    assert parse_key(SECRET.hex()) == SECRET
    assert parse_key("a-text-secret-of-20b") == b"a-text-secret-of-20b"
    with pytest.raises(CraneTwinError):
        parse_key("short")
    assert parse_host("127.0.0.1:5005") == ("127.0.0.1", 5005)
    assert parse_host("[::1]:7") == ("::1", 7)
    with pytest.raises(CraneTwinError):
        parse_host("localhost")


@pytest.mark.timeout(10)
def test_send_cli_refuses_without_a_key(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("CRANETWIN_MACHINE_KEY", raising=False)
    r = CliRunner().invoke(app, ["send", "--machine", "x", "--wire-id", "1", "--journal",
                                 str(tmp_path), "--scenario", "synthetic", "--duration", "0.1"])
    assert r.exit_code != 0
    assert "key" in (r.output + str(r.exception)).lower()


@pytest.mark.timeout(10)
def test_send_cli_refuses_a_secret_on_the_command_line_and_open_key_files(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delenv("CRANETWIN_MACHINE_KEY", raising=False)
    base = ["send", "--machine", "x", "--wire-id", "1", "--journal", str(tmp_path / "j"),
            "--scenario", "synthetic", "--duration", "0.1", "--host", "127.0.0.1:9"]
    r = CliRunner().invoke(app, [*base, "--key", SECRET.hex()])
    assert r.exit_code != 0 and isinstance(r.exception, CraneTwinError)
    assert "--key-file" in str(r.exception) and "CRANETWIN_MACHINE_KEY" in str(r.exception)
    assert SECRET.hex() not in str(r.exception)
    kf = tmp_path / "secret"
    kf.write_text(SECRET.hex())
    kf.chmod(0o644)
    r = CliRunner().invoke(app, [*base, "--key-file", str(kf)])
    assert isinstance(r.exception, CraneTwinError) and "chmod 600" in str(r.exception)
    assert not (tmp_path / "j").exists()  # refused before anything was started
    from cranetwin.cli.send import read_key_file

    kf.chmod(0o640)
    with caplog.at_level(logging.WARNING):
        assert read_key_file(kf) == SECRET.hex()
    assert "group" in caplog.text
    kf.chmod(0o600)
    assert read_key_file(kf) == SECRET.hex()


@pytest.mark.timeout(10)
def test_default_journal_root(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("CRANETWIN_STATE_DIR", str(tmp_path / "state"))
    assert default_journal_root() == tmp_path / "state" / "send"
    monkeypatch.delenv("CRANETWIN_STATE_DIR")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert default_journal_root() == tmp_path / "xdg" / "cranetwin" / "send"
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_journal_root() == tmp_path / "home" / ".local" / "state" / "cranetwin" / "send"


def _udp_server_thread(keys: dict[int, MachineKey]) -> tuple[
        int, dict[tuple[str, int, int], object], threading.Event, list[bool]]:
    """A blocking loopback server in a thread: receive, store, ack at once (unless muted)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    stored: dict[tuple[str, int, int], object] = {}
    done = threading.Event()
    mute = [False]
    rx = Receiver(keys)

    def loop() -> None:
        while not done.is_set():
            try:
                data, addr = sock.recvfrom(2048)
            except TimeoutError:
                continue
            if mute[0]:
                continue
            now = time.time_ns()
            try:
                item = rx.receive(data, now)
            except ReplayedError as err:
                assert err.machine_id
                sock.sendto(rx.ack(err.machine_id, err.epoch, now), addr)
                continue
            stored[(item.machine_id, item.epoch, item.seq)] = item
            rx.mark_durable(item.machine_id, item.epoch, item.seq)
            sock.sendto(rx.ack(item.machine_id, item.epoch, now), addr)
        sock.close()

    threading.Thread(target=loop, daemon=True).start()
    return sock.getsockname()[1], stored, done, mute


@pytest.mark.timeout(30)
def test_send_cli_streams_a_small_fleet(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    keys = {100 + i: MachineKey(100 + i, f"cli-{i}", SECRET, LAYOUT) for i in range(2)}
    port, stored, done, _ = _udp_server_thread(keys)
    monkeypatch.setenv("CRANETWIN_MACHINE_KEY", SECRET.hex())
    monkeypatch.setenv("CRANETWIN_STATE_DIR", str(tmp_path / "state"))
    try:
        r = CliRunner().invoke(app, ["send", "--machine", "cli", "--wire-id", "100",
                                     "--machines", "2", "--scenario", "synthetic",
                                     "--host", f"127.0.0.1:{port}", "--speed", "50",
                                     "--duration", "1", "--json"])
    finally:
        done.set()
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert [o["unacked"] for o in out] == [0, 0] and [o["samples"] for o in out] == [100, 100]
    assert all(o["fsyncs"] >= 1 for o in out)
    assert SECRET.hex() not in r.output
    for i in range(2):
        n = sum(b.n for (m, _, _), b in stored.items() if m == f"cli-{i}"
                and isinstance(b, SampleBlock))
        assert n == 100
        assert (tmp_path / "state" / "send" / f"cli-{i}" / "state").is_file()


@pytest.mark.timeout(30)
def test_send_cli_exits_2_with_the_data_kept_and_sends_it_on_the_next_start(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    key = MachineKey(110, "cli-x", SECRET, LAYOUT)
    port, stored, done, mute = _udp_server_thread({110: key})
    kf = tmp_path / "secret"
    kf.write_text(SECRET.hex() + "\n")
    kf.chmod(0o600)
    monkeypatch.delenv("CRANETWIN_MACHINE_KEY", raising=False)
    base = ["send", "--machine", "cli-x", "--wire-id", "110", "--key-file", str(kf),
            "--journal", str(tmp_path / "jr"), "--host", f"127.0.0.1:{port}"]
    mute[0] = True
    try:
        r = CliRunner().invoke(app, [*base, "--scenario", "synthetic", "--speed", "50",
                                     "--duration", "1", "--drain-timeout", "0.3"])
        assert r.exit_code == 2, r.output
        msg = r.stderr.strip().splitlines()[-1]
        assert msg == (f"3 datagrams not yet acknowledged, kept in {tmp_path / 'jr' / 'cli-x'}; "
                       "they are sent on the next start")
        assert not stored
        mute[0] = False
        r = CliRunner().invoke(app, [*base, "--from-journal-only", "--json"])
        assert r.exit_code == 0, r.output
        out = json.loads(r.stdout.strip().splitlines()[-1])
        assert out["resumed"] == 3  # 2 data, 1 status
        assert out["unacked"] == 0 and out["samples"] == 0
    finally:
        done.set()
    assert sum(b.n for b in stored.values() if isinstance(b, SampleBlock)) == 100
    r = CliRunner().invoke(app, [*base[:-4], "--journal", str(tmp_path / "none"), "--host",
                                 f"127.0.0.1:{port}", "--from-journal-only"])
    assert isinstance(r.exception, CraneTwinError) and "no journal" in str(r.exception)


# --- kill -9 of a real `cranetwin send` against a real daemon, restarted on its journal ---------
def _journal_records(d: Path) -> list[tuple[int, bytes]]:
    """Every (seq, datagram) in the journal's segment files, released ones included."""
    out: list[tuple[int, bytes]] = []
    for seg in sorted(d.glob("seg-*.log")):
        data, pos = seg.read_bytes(), 0
        while pos < len(data):
            n = int.from_bytes(data[pos:pos + 4], "big")
            out.append((int.from_bytes(data[pos + 8:pos + 16], "big"),
                        data[pos + 16:pos + 16 + n]))
            pos += 16 + n
    return out


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_kill_9_of_cranetwin_send_and_restart_store_every_sample_exactly_once(
        tmp_path: Path) -> None:
    """`cranetwin send` killed with SIGKILL twice mid-stream, restarted on the same journal each
    time: everything it journaled (the journal is synced before anything is sent) ends up stored
    exactly once, equal to what the deterministic source produced for those times."""
    import os
    import random
    import signal
    import sqlite3
    import subprocess
    import sys

    from conftest import running_daemon
    from cranetwin.protocol import TYPE_DATA, decode_data, peek_header
    from cranetwin.storage import Store

    mid, wire = "crane-k9", 4242
    key = MachineKey(wire, mid, SECRET, LAYOUT)
    db = tmp_path / "ct.db"
    store = Store.open(f"sqlite:///{db}")
    store.add_machine(mid, wire, SECRET)
    jroot = tmp_path / "journal"
    jdir = jroot / mid
    rng = random.Random(9)
    env = {**os.environ, "CRANETWIN_MACHINE_KEY": SECRET.hex()}

    with running_daemon(store) as daemon:
        host = f"{daemon.address[0]}:{daemon.address[1]}"
        cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "send",
               "--machine", mid, "--wire-id", str(wire), "--journal", str(jroot),
               "--host", host, "--scenario", "synthetic", "--batch", "50", "--speed", "20",
               "--log-level", "WARNING"]
        for run in range(2):
            with open(tmp_path / f"send-{run}.log", "wb") as err:
                p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
                try:
                    deadline = time.monotonic() + 60
                    seg0 = jdir / "seg-00000000000000000000.log"
                    while not (seg0.exists() and seg0.stat().st_size) and p.poll() is None:
                        assert time.monotonic() < deadline, "the sender never journaled"
                        time.sleep(0.02)
                    time.sleep(rng.uniform(0.3, 1.5))  # mid-stream, anywhere in the cycle
                    assert p.poll() is None, (tmp_path / f"send-{run}.log").read_text()
                finally:
                    p.send_signal(signal.SIGKILL)
                    p.wait(10)
        last = subprocess.run([*cmd, "--duration", "1", "--drain-timeout", "60", "--json"],
                              capture_output=True, text=True, env=env, timeout=120)
        assert last.returncode == 0, last.stderr[-2000:]
        out = json.loads(last.stdout.strip().splitlines()[-1])
        assert out["resumed"] > 0  # the killed runs' unacknowledged datagrams went out first
        assert out["unacked"] == 0
    assert not (jdir / "rejected.log").exists()  # nothing refused (e.g. as an overlap)
    j = FileJournal(jdir)
    epoch, end = j.epoch, j.end
    assert len(j) == 0
    j.close()
    records = _journal_records(jdir)
    assert [s for s, _ in records] == list(range(end))  # nothing released was deleted yet
    blocks = [decode_data(dg, key) for _, dg in records if peek_header(dg).type == TYPE_DATA]
    assert all(b.epoch == epoch for b in blocks)
    src = SyntheticSource(key, 0.01, seed=0)
    for b in blocks:  # the journal holds exactly what the source produced for those rows
        assert np.array_equal(b.values, expected(src, b), equal_nan=True)
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT b.epoch, b.seq, b.t_start_ns, b.n FROM sample_blocks b "
                           "JOIN machines m ON m.id = b.machine_pk WHERE m.machine_id = ? "
                           "ORDER BY b.t_start_ns", (mid,)).fetchall()
    assert sorted((e, s) for e, s, _, _ in rows) == sorted((b.epoch, b.seq) for b in blocks)
    assert sum(n for *_, n in rows) == sum(b.n for b in blocks)
    for (_, _, t0, n), (_, _, t1, _) in zip(rows, rows[1:], strict=False):
        assert t1 >= t0 + n * PERIOD  # no sample stored twice
    by_time = sorted(blocks, key=lambda b: b.t0_ns)
    t_exp = np.concatenate([b.t0_ns + np.arange(b.n) * PERIOD for b in by_time])
    v_exp = np.concatenate([b.values for b in by_time])
    got = store.read_samples(mid, t_exp[0] / 1e9, t_exp[-1] / 1e9 + 1)
    assert np.array_equal(np.round(got.t_s * 1e3).astype(np.int64), t_exp // 1_000_000)
    cols = [got.channels.index(n) for n in LAYOUT.names]
    assert np.array_equal(got.values[:, cols], v_exp, equal_nan=True)
    gaps = sum(1 for a, b in zip(by_time, by_time[1:], strict=False)
               if b.t0_ns != a.t0_ns + a.n * PERIOD)
    assert gaps <= 2  # contiguous within each of the three runs
    store.close()


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_sigterm_stops_cranetwin_send_at_once_with_the_data_kept(tmp_path: Path) -> None:
    """SIGTERM (or Ctrl-C) while the server does not answer: the sender stops streaming, syncs
    its journal and exits 2 at once (no drain), saying how many datagrams it kept and where."""
    import os
    import signal
    import subprocess
    import sys

    jroot = tmp_path / "journal"
    seg0 = jroot / "crane-t" / "seg-00000000000000000000.log"
    env = {**os.environ, "CRANETWIN_MACHINE_KEY": SECRET.hex()}
    cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "send",
           "--machine", "crane-t", "--wire-id", "7", "--journal", str(jroot),
           "--host", f"127.0.0.1:{_free_port()}", "--scenario", "synthetic", "--speed", "10",
           "--log-level", "WARNING"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 40
    while not (seg0.exists() and seg0.stat().st_size > 1000) and p.poll() is None:
        assert time.monotonic() < deadline, "the sender never journaled"
        time.sleep(0.02)
    p.send_signal(signal.SIGTERM)
    t0 = time.monotonic()
    _, err = p.communicate(timeout=20)
    assert time.monotonic() - t0 < 3
    assert p.returncode == 2, err
    msg = err.strip().splitlines()[-1]
    j = FileJournal(jroot / "crane-t")
    assert msg == (f"{len(j)} datagrams not yet acknowledged, kept in {jroot / 'crane-t'}; "
                   "they are sent on the next start")
    assert len(j) >= 3 and j.start == 0
    j.close()
