"""``cranetwin ingest --processes N``: a SO_REUSEPORT group steered by the wire id inside the
datagram. Steering keeps a machine on its socket whatever its source port; a child killed with
SIGKILL mid-stream is restarted on its socket and nothing acknowledged is lost or doubled (with
the database, and with the children publishing to the NATS JetStream fleet bus)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import struct
import time
from collections import defaultdict
from pathlib import Path

import pytest
from sqlalchemy import text

from cranetwin.bench.ingest import (
    Fleet,
    free_udp_port,
    grid_values,
    make_sender,
    start_daemon,
)
from cranetwin.bus.subjects import BusConfig
from cranetwin.ingest.steering import bind_group, steer
from cranetwin.protocol import Sender
from cranetwin.storage import Store
from test_bus import delete_stream, fresh_bus, nats_unreachable_reason, run_writer
from test_ingest_faults import run_main
from test_ingest_reliability import LAYOUT, assert_stored_exactly, key, registered


def _fake_datagram(wire_id: int) -> bytes:
    """Enough of a version-2 header for the steering program: magic, version, type, wire id."""
    return b"CT\x02\x01" + struct.pack(">IQ", wire_id, 1) + bytes(16)


@pytest.mark.timeout(30)
def test_the_group_steers_by_wire_id_whatever_the_source_port() -> None:
    n = 3
    socks = bind_group("127.0.0.1", 0, n)
    try:
        addr = socks[0].getsockname()
        assert all(s.getsockname() == addr for s in socks)  # one address, three sockets
        for s in socks:
            s.setblocking(False)
        ports: set[int] = set()
        for w in (1, 2, 3, 4, 5, 6, 7, 1000, 2**31 + 5, 2**32 - 1):
            for _ in range(4):  # a new source port each time (a NAT rebinding, a restart)
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as c:
                    c.bind(("127.0.0.1", 0))
                    ports.add(c.getsockname()[1])
                    c.sendto(_fake_datagram(w), addr)
                got = []
                for i, s in enumerate(socks):
                    try:
                        got.append((i, s.recv(100)))
                    except BlockingIOError:
                        pass
                assert [i for i, _ in got] == [steer(w, n)] == [w % n], (w, got)
        assert len(ports) > 30
    finally:
        for s in socks:
            s.close()


def _record_acks(senders: list[Sender]) -> dict[int, set[int]]:
    """Every seq each machine has seen acknowledged, collected as acks arrive."""
    acked: dict[int, set[int]] = defaultdict(set)
    for s in senders:
        original = s.receive

        def receive(datagram: bytes, now_ns: int, s: Sender = s, original=original):  # type: ignore[no-untyped-def]
            out = original(datagram, now_ns)
            acked[s.key.wire_id].update(q for q, _ in s.last_acked)
            return out

        s.receive = receive  # type: ignore[method-assign]
    return acked


def _stored_seqs(store: Store, wire_id: int) -> list[int]:
    with store.engine.connect() as c:
        return [int(r[0]) for r in c.execute(text(
            "SELECT b.seq FROM sample_blocks b JOIN machines m ON m.id = b.machine_pk "
            "WHERE m.wire_id = :w ORDER BY b.seq"), {"w": wire_id})]


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_child_killed_mid_stream_loses_and_doubles_nothing(db_url: str, tmp_path: Path) -> None:
    wire_ids = [1, 2, 3, 4, 5, 6]
    store = registered(db_url, wire_ids)
    sent = {w: grid_values(LAYOUT, 3000, w) for w in wire_ids}
    port = free_udp_port()
    senders = [make_sender(key(w), sent[w], rto_s=0.2, max_unacked=8, max_burst=4)
               for w in wire_ids]
    acked = _record_acks(senders)
    fleet = Fleet(senders, ("127.0.0.1", port))
    proc = start_daemon(db_url, port, tmp_path, "--processes", "2")
    try:
        children = {c["index"]: c["pid"] for c in proc.info["children"]}
        assert sorted(children) == [0, 1] and len(set(children.values())) == 2
        total = sum(v.shape[0] for v in sent.values())
        assert fleet.run(timeout_s=90, until=lambda: sum(
            s.acked_samples for s in fleet.senders.values()) >= total // 3)
        os.kill(children[1], signal.SIGKILL)  # serves the odd wire ids: no flush, no goodbye
        acked_at_kill = {w: set(q) for w, q in acked.items()}
        for w, seqs in acked_at_kill.items():  # acked ⇒ committed, before any retransmission
            assert seqs <= set(_stored_seqs(store, w)), f"crane-{w}: acked but not stored"
        assert any(acked_at_kill[w] for w in (1, 3, 5))  # the dead child had acked some
        assert fleet.run(timeout_s=150), "not everything was acknowledged after the kill"
        final = proc.stop(60)
        assert proc.poll() == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        fleet.close()
    assert final["restarts"] == 1 and final["processes"] == 2
    assert_stored_exactly(store, sent)
    for w in wire_ids:
        seqs = _stored_seqs(store, w)
        assert len(seqs) == len(set(seqs)) and set(seqs) >= acked[w]
        assert seqs == list(range(1, senders[wire_ids.index(w)].next_seq))
    # each machine was stored by its own child only (the restarted one for the odd ids)
    by_child = {c["index"]: c for c in final["children"]}
    odd_blocks = sum(store.stats(f"crane-{w}").blocks for w in (1, 3, 5))
    assert by_child[0]["stored_blocks"] == sum(store.stats(f"crane-{w}").blocks
                                               for w in (2, 4, 6))
    assert 0 < by_child[1]["stored_blocks"] < odd_blocks  # the rest came before the kill


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_machines_stay_on_their_process_when_their_source_port_changes(
        sqlite_url: str, tmp_path: Path) -> None:
    even, odd = [2, 4, 8], [3]
    store = registered(sqlite_url, even + odd)
    sent = {w: grid_values(LAYOUT, 4000, w) for w in even + odd}
    port = free_udp_port()
    fleet = Fleet([make_sender(key(w), sent[w], rto_s=0.2, max_unacked=8, max_burst=4)
                   for w in even + odd], ("127.0.0.1", port))
    proc = start_daemon(sqlite_url, port, tmp_path, "--processes", "2")
    ports: set[int] = set()
    try:
        for _ in range(1500):
            ports.add(fleet.sock.getsockname()[1])
            if fleet.run(timeout_s=0.1):
                break
            new = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a NAT rebinding
            new.bind(("127.0.0.1", 0))
            new.setblocking(False)
            fleet.sock.close()
            fleet.sock = new
        assert fleet.idle(), "not everything was acknowledged"
        final = proc.stop(60)
    finally:
        if proc.poll() is None:
            proc.kill()
        fleet.close()
    assert len(ports) >= 4  # the machines really did change their source port mid-stream
    assert_stored_exactly(store, sent)
    by_child = {c["index"]: c for c in final["children"]}
    assert by_child[0]["stored_blocks"] == sum(store.stats(f"crane-{w}").blocks for w in even)
    assert by_child[1]["stored_blocks"] == store.stats("crane-3").blocks
    assert by_child[1]["received"] > 0 and final["restarts"] == 0


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a zombie (not reaped yet by its new parent) has stopped serving too
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    return True


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_child_whose_parent_is_killed_exits(sqlite_url: str, tmp_path: Path) -> None:
    registered(sqlite_url, [1]).close()
    proc = start_daemon(sqlite_url, free_udp_port(), tmp_path, "--processes", "2")
    pids = [int(c["pid"]) for c in proc.info["children"]]
    try:
        assert not any(_gone(p) for p in pids)
        proc.kill()  # SIGKILL: the parent cannot forward anything
        deadline = time.monotonic() + 60
        while not all(_gone(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(_gone(p) for p in pids), "a child outlived its parent"
    finally:
        for p in pids:
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)


@pytest.mark.timeout(60)
def test_processes_port_in_use_is_one_line_exit_2(
        sqlite_url: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:  # no SO_REUSEPORT
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        code, _, err = run_main(monkeypatch, capsys, "ingest", "--bind", f"127.0.0.1:{port}",
                                "--db", sqlite_url, "--metrics-bind", "0", "--processes", "2")
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and "already in use" in err, err


def _stream_keys(cfg: BusConfig) -> list[tuple[int, int]]:
    """(wire id, seq) of every message in the stream, read directly (nothing consumed)."""
    import nats

    async def run() -> list[tuple[int, int]]:
        nc = await nats.connect(cfg.url, connect_timeout=2, allow_reconnect=False)
        try:
            js = nc.jetstream()
            state = (await js.stream_info(cfg.stream)).state
            out = []
            for q in range(state.first_seq, state.last_seq + 1) if state.messages else ():
                msg = await js.get_msg(cfg.stream, q)
                machine, _epoch, seq = msg.headers["Nats-Msg-Id"].split("/")
                out.append((int(machine.removeprefix("crane-")), int(seq)))
            assert len(out) == state.messages
            return out
        finally:
            await nc.close()

    return asyncio.run(run())


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_child_killed_mid_stream_on_the_fleet_bus_loses_and_doubles_nothing(
        sqlite_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--processes 2 --bus nats://…``: each child publishes to JetStream; ``kill -9`` of one
    mid-stream; every seq acked is in the stream exactly once (at the kill and at the end), and
    a storage writer stores every sample exactly once."""
    reason = nats_unreachable_reason()
    if reason:
        pytest.skip(reason)
    cfg = fresh_bus(partitions=4, ack_wait_s=1.0)
    # the parent reads the bus settings from its environment; its children get them on stdin
    for k, v in {"CRANETWIN_BUS_STREAM": cfg.stream, "CRANETWIN_BUS_PREFIX": cfg.prefix,
                 "CRANETWIN_BUS_PARTITIONS": str(cfg.partitions),
                 "CRANETWIN_BUS_ACK_WAIT_S": str(cfg.ack_wait_s),
                 "CRANETWIN_BUS_PUBLISH_TIMEOUT_S": "10"}.items():  # no retry under load
        monkeypatch.setenv(k, v)
    wire_ids = [1, 2, 3, 4, 5, 6]
    store = registered(sqlite_url, wire_ids)
    sent = {w: grid_values(LAYOUT, 3000, w) for w in wire_ids}
    senders = [make_sender(key(w), sent[w], rto_s=0.2, max_unacked=8, max_burst=4)
               for w in wire_ids]
    acked = _record_acks(senders)
    port = free_udp_port()
    fleet = Fleet(senders, ("127.0.0.1", port))
    proc = None
    try:
        proc = start_daemon(sqlite_url, port, tmp_path, "--processes", "2", "--bus", cfg.url)
        children = {c["index"]: c["pid"] for c in proc.info["children"]}
        assert sorted(children) == [0, 1] and len(set(children.values())) == 2
        total = sum(v.shape[0] for v in sent.values())
        assert fleet.run(timeout_s=90, until=lambda: sum(
            s.acked_samples for s in fleet.senders.values()) >= total // 3)
        os.kill(children[1], signal.SIGKILL)  # serves the odd wire ids: no flush, no goodbye
        acked_at_kill = {w: set(q) for w, q in acked.items()}
        in_stream = _stream_keys(cfg)
        for w, seqs in acked_at_kill.items():  # acked ⇒ PubAcked, before any retransmission
            assert seqs <= {q for m, q in in_stream if m == w}, f"crane-{w}: acked, not in stream"
        assert any(acked_at_kill[w] for w in (1, 3, 5))  # the dead child had acked some
        assert stored_blocks_are_none(store, wire_ids)  # nothing went to the database itself
        assert fleet.run(timeout_s=150), "not everything was acknowledged after the kill"
        final = proc.stop(60)
        assert proc.poll() == 0
        assert final["restarts"] == 1 and final["processes"] == 2
        in_stream = _stream_keys(cfg)
        assert len(in_stream) == len(set(in_stream)), "a block is in the stream twice"
        for i, w in enumerate(wire_ids):
            seqs = sorted(q for m, q in in_stream if m == w)
            assert set(seqs) >= acked[w]
            assert seqs == list(range(1, senders[i].next_seq)), f"crane-{w}"
        # the restarted child published the odd machines' rest, child 0 all the even ones
        by_child = {c["index"]: c for c in final["children"]}
        odd = sum(1 for m, _ in in_stream if m % 2)
        assert by_child[0]["stored_blocks"] == len(in_stream) - odd
        assert 0 < by_child[1]["stored_blocks"] < odd
        got = run_writer(store, cfg, until=lambda: store.stats().samples >= total, timeout_s=90)
        assert not isinstance(got, BaseException), got
        assert got["refused"] == {} and got["bad_messages"] == 0
        assert_stored_exactly(store, sent)
        for i, w in enumerate(wire_ids):
            assert _stored_seqs(store, w) == list(range(1, senders[i].next_seq))
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        fleet.close()
        store.close()
        delete_stream(cfg)


def stored_blocks_are_none(store: Store, wire_ids: list[int]) -> bool:
    return all(not _stored_seqs(store, w) for w in wire_ids)
