"""Fault injection against the ingest daemon: each test injects one fault and checks that the
daemon goes on (or stops in bounded time), that nothing is acknowledged that is not stored, and
that the other machines are served throughout.

Faults: raw SQLAlchemy errors in the summary rollup and in writes, a database outage (in-process
and a locked SQLite file under a real ``cranetwin ingest`` process), SIGTERM during the outage,
threads dying, one machine's unstorable data, refused datagrams, a machine registered with a
bad model, and the configuration errors the CLI must report in one line.
"""

from __future__ import annotations

import json
import logging
import os
import select
import signal
import socket
import sqlite3
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy.exc import DataError, OperationalError
from typer.testing import CliRunner

from conftest import SECRET, running_daemon
from cranetwin.errors import StorageError
from cranetwin.protocol import TYPE_REFUSAL, decode_ack, decode_refusal
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store
from test_ingest_daemon import (
    LAYOUT,
    T0_NS,
    HookStore,
    datagram,
    grid_values,
    hook_store,
    key,
    udp,
    wait_for,
)

ROOT = Path(__file__).resolve().parents[1]


def outage_error() -> StorageError:
    """What the store raises when the server is gone (a wrapped OperationalError)."""
    try:
        raise OperationalError("INSERT …", {}, Exception("server closed the connection"))
    except OperationalError as exc:
        try:
            raise StorageError(f"could not store: {exc}") from exc
        except StorageError as wrapped:
            return wrapped


class Outage:
    """A switchable database outage for a :class:`HookStore` (counts write attempts)."""

    def __init__(self) -> None:
        self.down = threading.Event()
        self.attempts = 0

    def __call__(self, blocks: Sequence[SampleBlock]) -> None:
        if self.down.is_set():
            self.attempts += 1
            raise outage_error()


def recv_or_none(s: socket.socket, timeout_s: float) -> bytes | None:
    s.settimeout(timeout_s)
    try:
        return s.recv(2048)
    except TimeoutError:
        return None


# --- the writer never dies -----------------------------------------------------------------------
@pytest.mark.timeout(60)
def test_rollup_raising_raw_sqlalchemy_errors_never_stops_ingest(
        db_url: str, caplog: pytest.LogCaptureFixture) -> None:
    class BadRollup(HookStore):
        calls = 0

        def rollup(self, before_s: float | None = None) -> int:
            self.calls += 1
            raise OperationalError("SELECT …", {}, Exception("poison row in summary_dirty"))

    st = BadRollup(Store.open(db_url).engine)
    st.add_machine("crane-1", 1, SECRET)
    caplog.set_level(logging.ERROR, "cranetwin.ingest.daemon")
    with running_daemon(st, rollup_interval_s=0.05) as d:
        s = udp()
        for seq in range(5):
            s.sendto(datagram(1, seq, seed=seq), d.address)
            assert decode_ack(s.recv(2048), key(1)).covers(seq)
            time.sleep(0.1)  # rollups run (and fail) between the writes
        s.close()
        wait_for(lambda: d.snapshot()["rollup_errors"] >= 3)
    m = d.snapshot()
    assert m["stored_blocks"] == 5 and m["writer_restarts"] == 0
    assert st.calls >= 3
    assert sum("summary rollup failed" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.timeout(60)
def test_unexpected_write_exception_is_counted_and_the_writer_goes_on(db_url: str) -> None:
    st = hook_store(db_url, [1])
    broken = threading.Event()
    broken.set()

    def hook(blocks: Sequence[SampleBlock]) -> None:
        if broken.is_set():
            raise RuntimeError("a bug in the storage layer")

    st.hook = hook
    with running_daemon(st) as d:
        s = udp()
        s.sendto(datagram(1, 0), d.address)
        # an unexplained failure neither acks nor refuses (no data lost): the sender retransmits
        assert recv_or_none(s, 0.5) is None
        wait_for(lambda: d.snapshot()["dropped"].get("write_error") == 1)
        broken.clear()
        s.sendto(datagram(1, 0), d.address)  # the retransmission
        assert decode_ack(s.recv(2048), key(1)).covers(0)
        s.sendto(datagram(1, 1), d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(1)
        s.close()
    m = d.snapshot()
    assert m["write_errors"] >= 1 and m["stored_blocks"] == 2 and m["writer_restarts"] == 0
    assert m["dropped"] == {"write_error": 1} and m["refusals_sent"] == 0


@pytest.mark.timeout(60)
def test_outage_retries_with_backoff_acks_nothing_and_resumes(db_url: str) -> None:
    st = hook_store(db_url, [1, 2])
    outage = Outage()
    st.hook = outage
    with running_daemon(st) as d:
        s = udp()
        outage.down.set()
        s.sendto(datagram(1, 0), d.address)
        s.sendto(datagram(2, 0), d.address)
        assert recv_or_none(s, 1.6) is None  # nothing is acknowledged during the outage
        assert d.storage_outage
        attempts = outage.attempts
        # backoff 50, 100, 200, 400, 800 ms …: a handful of attempts in 1.6 s, not a busy loop
        assert 3 <= attempts <= 7, attempts
        outage.down.clear()
        acked: set[int] = set()
        for _ in range(2):  # one ack per machine once the database is back
            reply = recv_or_none(s, 10)
            assert reply is not None, "not acknowledged after the outage"
            acked |= {w for w in (1, 2) if _acks(reply, w)}
        assert acked == {1, 2}
        s.close()
        wait_for(lambda: not d.storage_outage)
    assert st.stats().blocks == 2 and st.stats().samples == 40
    m = d.snapshot()
    assert m["write_errors"] >= attempts
    assert m["acks_sent"] == 2 and m["stored_blocks"] == 2


def _acks(reply: bytes, wire_id: int) -> bool:
    try:
        decode_ack(reply, key(wire_id))
    except Exception:
        return False
    return True


@pytest.mark.timeout(60)
def test_a_locked_sqlite_database_is_an_outage_and_ingest_resumes_after_it(tmp_path: Path) -> None:
    """A real outage: another process holds the SQLite write lock for 2 s."""
    db = tmp_path / "locked.db"
    st = Store.open(f"sqlite:///{db}", busy_timeout_s=0.2)
    st.add_machine("crane-1", 1, SECRET)
    with running_daemon(st) as d:
        s = udp()
        s.sendto(datagram(1, 0), d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(0)
        lock = sqlite3.connect(db, timeout=1, isolation_level=None)
        lock.execute("BEGIN EXCLUSIVE")
        try:
            s.sendto(datagram(1, 1, seed=1), d.address)
            assert recv_or_none(s, 2.0) is None  # locked: not durable, not acknowledged
            assert d.storage_outage and d.snapshot()["write_errors"] >= 2
        finally:
            lock.execute("ROLLBACK")
            lock.close()
        ack = recv_or_none(s, 10)
        assert ack is not None and decode_ack(ack, key(1)).covers(1)
        s.close()
    assert st.stats().blocks == 2 and not d.storage_outage


@pytest.mark.timeout(60)
def test_stop_during_an_outage_gives_up_unacked_batches_within_seconds(db_url: str) -> None:
    st = hook_store(db_url, [1])
    outage = Outage()
    st.hook = outage
    outage.down.set()
    s = udp()
    with running_daemon(st) as d:
        for seq in range(3):
            s.sendto(datagram(1, seq, seed=seq), d.address)
        wait_for(lambda: outage.attempts >= 2)
        t = time.monotonic()
        d.stop()
        # (the context manager joins the daemon thread)
    stopped_in = time.monotonic() - t
    assert stopped_in < 5.0, stopped_in
    assert recv_or_none(s, 0.2) is None  # never acknowledged
    s.close()
    m = d.snapshot()
    assert m["dropped"].get("unwritten_at_shutdown", 0) >= 1 and m["acks_sent"] == 0
    assert st.stats().blocks == 0


def _ingest_cmd(*args: str) -> list[str]:
    return [sys.executable, "-c", "from cranetwin.cli import main; main()", "ingest", *args]


def _read_ready(proc: subprocess.Popen[bytes], timeout_s: float) -> dict[str, Any]:
    """The daemon's readiness line (stdout), without ever blocking past ``timeout_s``."""
    assert proc.stdout is not None
    end = time.monotonic() + timeout_s
    buf = b""
    while b"\n" not in buf:
        left = end - time.monotonic()
        if left <= 0 or proc.poll() is not None:
            raise AssertionError(f"no readiness line (exit {proc.poll()})")
        r, _, _ = select.select([proc.stdout], [], [], min(left, 0.2))
        if r:
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                raise AssertionError("stdout closed before the readiness line")
            buf += chunk
    ready: dict[str, Any] = json.loads(buf.split(b"\n", 1)[0])
    return ready


@pytest.fixture
def daemon_proc(tmp_path: Path) -> Iterator[list[subprocess.Popen[bytes]]]:
    procs: list[subprocess.Popen[bytes]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait(10)


@pytest.mark.timeout(90)
def test_sigterm_while_the_sqlite_database_is_locked_exits_within_10_s(
        tmp_path: Path, daemon_proc: list[subprocess.Popen[bytes]]) -> None:
    db = tmp_path / "ingest.db"
    url = f"sqlite:///{db}"
    with Store.open(url) as st:
        st.add_machine("crane-1", 1, SECRET)
    log_path = tmp_path / "daemon.log"
    with log_path.open("wb") as err:  # a file, not a pipe: a chatty child can never block
        proc = subprocess.Popen(_ingest_cmd("--bind", "127.0.0.1:0", "--db", url,
                                            "--metrics-bind", "127.0.0.1:0"),
                                stdout=subprocess.PIPE, stderr=err)
    daemon_proc.append(proc)
    ready = _read_ready(proc, 60)
    assert ready["event"] == "ready" and ready["metrics"].startswith("http://127.0.0.1:")
    host, port = ready["udp"].rsplit(":", 1)
    addr = (host, int(port))
    s = udp()
    s.sendto(datagram(1, 0), addr)
    assert decode_ack(s.recv(2048), key(1)).covers(0)  # healthy first
    lock = sqlite3.connect(db, timeout=1, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")  # another process holds the database: writes block
    try:
        s.sendto(datagram(1, 1, seed=1), addr)
        assert recv_or_none(s, 1.5) is None  # not durable: not acknowledged
        t = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(10)  # raises TimeoutExpired (test fails) if it hangs
        stopped_in = time.monotonic() - t
    finally:
        lock.execute("ROLLBACK")
        lock.close()
        s.close()
    assert rc == 0, log_path.read_text()[-2000:]
    assert stopped_in < 10
    assert proc.stdout is not None
    final = json.loads(proc.stdout.read().decode().splitlines()[-1])  # the process has exited
    assert final["event"] == "stopped" and final["stored_blocks"] == 1
    assert final["dropped"] == {"unwritten_at_shutdown": 1} and final["acks_sent"] == 1
    with Store.open(url) as st:
        assert st.stats().blocks == 1  # the unacknowledged block was given up, not half-stored
    text = log_path.read_text()
    assert "Traceback" not in text, text[-3000:]


@pytest.mark.timeout(60)
def test_a_dead_writer_thread_is_restarted_and_counted(db_url: str,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    class Die(BaseException):
        """Escapes the loop's ``except Exception`` (like a KeyboardInterrupt would)."""

    st = hook_store(db_url, [1])
    die = threading.Event()
    die.set()

    def hook(blocks: Sequence[SampleBlock]) -> None:
        if die.is_set():
            die.clear()
            raise Die()

    st.hook = hook
    caplog.set_level(logging.CRITICAL, "cranetwin.ingest.daemon")
    with running_daemon(st, supervise_interval_s=0.05) as d:
        s = udp()
        s.sendto(datagram(1, 0), d.address)
        assert recv_or_none(s, 1.0) is None  # the batch died with the thread: not acked
        wait_for(lambda: d.snapshot()["writer_restarts"] == 1)
        s.sendto(datagram(1, 0), d.address)  # the sender's retransmission
        assert decode_ack(s.recv(2048), key(1)).covers(0)
        s.close()
    assert d.snapshot()["writer_restarts"] == 1 and st.stats().blocks == 1
    assert any("writer thread died" in r.getMessage() for r in caplog.records)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("supervise_s", [0.05, 3600.0])
def test_a_dead_decoder_thread_is_restarted_and_counted(store_1: Store,
                                                        supervise_s: float) -> None:
    """A decoder thread ended by a BaseException is restarted, counted, and the sender's
    retransmission is stored once; with the periodic check effectively off (3600 s) too: a
    dying thread asks for its restart at once."""
    with running_daemon(store_1, supervise_interval_s=supervise_s) as d:
        original = d._decode
        calls = {"n": 0}

        def dying(raw: Any) -> Any:
            calls["n"] += 1
            if calls["n"] == 1:
                raise SystemExit("decoder killed")  # a BaseException: ends the thread
            return original(raw)

        d._decode = dying  # type: ignore[method-assign]
        s = udp()
        s.sendto(datagram(1, 0), d.address)
        wait_for(lambda: d.snapshot()["decoder_restarts"] == 1)
        s.sendto(datagram(1, 0), d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(0)
        s.close()
    assert store_1.stats().blocks == 1


@pytest.fixture
def store_1(sqlite_url: str) -> Store:
    st = Store.open(sqlite_url)
    st.add_machine("crane-1", 1, SECRET)
    return st


# --- isolation -----------------------------------------------------------------------------------
@pytest.mark.timeout(90)
@pytest.mark.parametrize("poison", ["overlap", "database_error"])
def test_one_machines_unstorable_blocks_never_delay_another(db_url: str, poison: str) -> None:
    """crane-9 sends 20 poison datagrams per second while crane-1 streams, one datagram at a
    time, each waiting for its ack. Poison ``overlap``: every crane-9 block covers the same
    time span (storage refuses all but the first, and crane-9 gets refusals); poison
    ``database_error``: the database raises a data error for any write holding a crane-9 block
    (crane-9 is never acknowledged). Either way crane-1 is never held up."""
    st = hook_store(db_url, [1, 9])
    if poison == "database_error":
        def hook(blocks: Sequence[SampleBlock]) -> None:
            if any(b.machine_id == "crane-9" for b in blocks):
                raise StorageError("could not store") from DataError(
                    "INSERT …", {}, Exception("bigint out of range"))

        st.hook = hook
    sock9 = udp()
    replies9: list[bytes] = []
    latency: list[float] = []
    n = 60
    with running_daemon(st) as d:
        stop = threading.Event()

        def poison_machine() -> None:
            seq = 0
            while not stop.is_set():
                sock9.sendto(datagram(9, seq, seed=seq, t0_ns=T0_NS), d.address)
                seq += 1
                r, _, _ = select.select([sock9], [], [], 0.05)
                if r:
                    replies9.append(sock9.recv(2048))

        t = threading.Thread(target=poison_machine, daemon=True)
        t.start()
        s = udp()
        try:
            time.sleep(0.3)  # the poison is flowing
            for seq in range(n):
                t0 = time.monotonic()
                s.sendto(datagram(1, seq, seed=seq), d.address)
                while True:
                    reply = recv_or_none(s, 5)
                    assert reply is not None, f"crane-1 seq {seq} not acknowledged in 5 s"
                    if decode_ack(reply, key(1)).covers(seq):
                        break
                latency.append(time.monotonic() - t0)
        finally:
            stop.set()
            t.join(5)
            # replies to crane-9's last datagrams may still be on their way or queued
            while select.select([sock9], [], [], 0.5)[0]:
                replies9.append(sock9.recv(2048))
            sock9.close()
            s.close()
    assert st.stats("crane-1").blocks == n
    m = d.snapshot()
    if poison == "overlap":
        assert st.stats("crane-9").blocks == 1
        refusals = [decode_refusal(r, key(9)) for r in replies9 if r[3] == TYPE_REFUSAL]
        assert len(refusals) >= 5 and {r.reason for r in refusals} == {"overlap"}
        assert m["dropped"]["overlap"] == m["refusals_sent"] == len(refusals)
        assert all(r.seq > 0 for r in refusals)  # seq 0 was stored (and acked)
    else:
        assert st.stats("crane-9").blocks == 0 and replies9 == []
        assert m["dropped"]["write_error"] >= 5 and m["refusals_sent"] == 0
    # crane-1 was never held up (before isolation its median was 25 s at this poison rate)
    lat = np.sort(latency)
    assert lat[n // 2] < 0.3 and lat[-1] < 2.0, lat


@pytest.mark.timeout(60)
def test_refused_datagrams_get_a_refusal_and_nothing_is_stored(store_1: Store) -> None:
    hi = np.array([c.max for c in LAYOUT.channels])
    lo = np.array([c.min for c in LAYOUT.channels])
    wild = grid_values(20, 0)
    wild[3, 0] = hi[0] + (hi[0] - lo[0])  # a whole span above the sensor's maximum
    future = time.time_ns() + 3600 * 10**9
    with running_daemon(store_1) as d:
        s = udp()
        s.sendto(datagram(1, 0, values=wild), d.address)
        r1 = decode_refusal(s.recv(2048), key(1))
        s.sendto(datagram(1, 1, t0_ns=future), d.address)
        r2 = decode_refusal(s.recv(2048), key(1))
        s.sendto(datagram(1, 2), d.address)  # a good one is still stored and acked
        assert decode_ack(s.recv(2048), key(1)).covers(2)
        s.close()
    assert (r1.seq, r1.reason, r1.epoch) == (0, "out_of_range", 7)
    assert (r2.seq, r2.reason) == (1, "bad_time")
    assert store_1.stats().blocks == 1
    m = d.snapshot()
    assert m["dropped"] == {"out_of_range": 1, "bad_time": 1} and m["refusals_sent"] == 2


@pytest.mark.timeout(60)
def test_daemon_limits_come_from_its_config(store_1: Store) -> None:
    from cranetwin.protocol import Limits

    old = time.time_ns() - 2 * 86400 * 10**9  # two days ago
    with running_daemon(store_1, limits=Limits(max_past_s=86400.0)) as d:
        s = udp()
        s.sendto(datagram(1, 0, t0_ns=old), d.address)
        assert decode_refusal(s.recv(2048), key(1)).reason == "bad_time"
        s.close()
    assert store_1.stats().blocks == 0


# --- bad machine models --------------------------------------------------------------------------
BAD_TOML = '[machine]\nname = "broken"\n[[bodies]]\nname = 3\n'


@pytest.mark.timeout(60)
@pytest.mark.parametrize("model", ["not = [valid toml", BAD_TOML, "no-such-builtin"])
def test_a_machine_with_a_bad_model_never_stops_the_daemon(
        sqlite_url: str, model: str, caplog: pytest.LogCaptureFixture) -> None:
    st = Store.open(sqlite_url)
    st.add_machine("crane-1", 1, SECRET)
    st.add_machine("crane-5", 5, SECRET, model=model)  # registered before validation existed
    caplog.set_level(logging.ERROR, "cranetwin.ingest.daemon")
    with running_daemon(st, key_refresh_s=0.0) as d:
        s = udp()
        for seq in range(3):
            s.sendto(encode_for(5, seq), d.address)
        s.sendto(datagram(1, 0), d.address)
        assert decode_ack(s.recv(2048), key(1)).covers(0)  # the others are served
        wait_for(lambda: d.snapshot()["dropped"].get("bad_model", 0) == 3)
        assert recv_or_none(s, 0.3) is None
        s.close()
    assert st.stats("crane-5").blocks == 0
    logged = [r.getMessage() for r in caplog.records if "crane-5" in r.getMessage()]
    assert len(logged) == 1 and "bad_model" in logged[0]


def encode_for(wire_id: int, seq: int) -> bytes:
    from cranetwin.protocol import MachineKey, encode_data

    k = MachineKey(wire_id, f"crane-{wire_id}", SECRET, LAYOUT)
    return encode_data(k, seq, time.time_ns() - 10**9, 10_000_000, grid_values(10, seq),
                       epoch=3)


# --- the CLI: settings, secrets, validation, one-line errors --------------------------------------
def run_main(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
             *argv: str) -> tuple[int, str, str]:
    """``cranetwin ARGV`` through the console-script entry point, in-process."""
    from cranetwin.cli import main

    monkeypatch.setattr(sys, "argv", ["cranetwin", *argv])
    code: int | str | None = 0
    try:
        main()
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return int(code or 0), out.out, out.err


@pytest.mark.timeout(60)
def test_ingest_port_in_use_is_one_line_exit_2(sqlite_url: str, monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    port = busy.getsockname()[1]
    try:
        code, _, err = run_main(monkeypatch, capsys, "ingest", "--bind", f"127.0.0.1:{port}",
                                "--db", sqlite_url, "--metrics-bind", "0")
    finally:
        busy.close()
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"port {port} is already in use" in err


@pytest.mark.timeout(60)
def test_metrics_port_in_use_is_one_line_exit_2(sqlite_url: str, monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        code, _, err = run_main(monkeypatch, capsys, "ingest", "--bind", "127.0.0.1:0",
                                "--db", sqlite_url, "--metrics-bind", f"127.0.0.1:{port}")
    finally:
        busy.close()
    assert code == 2 and err.count("\n") == 1 and "--metrics-bind" in err
    assert "already in use" in err


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("bind", "expected"), [
    ("no-such-host.invalid:5005", "cannot resolve host"),
    ("192.0.2.1:5005", "not an address of this machine"),  # TEST-NET-1: never local
    ("127.0.0.1:99999", "outside 0..65535"),
    ("localhost", "must be HOST:PORT"),
])
def test_bad_bind_address_is_one_line_exit_2(
        sqlite_url: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        bind: str, expected: str) -> None:
    code, _, err = run_main(monkeypatch, capsys, "ingest", "--bind", bind, "--db", sqlite_url,
                            "--metrics-bind", "0")
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and expected in err, err


@pytest.mark.timeout(60)
def test_ingest_honours_the_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import cranetwin.ingest.daemon as daemon_mod
    from cranetwin.cli import app

    seen: dict[str, Any] = {}

    def fake_serve(db_url: str, config: Any, bus: Any = None, on_ready: Any = None,
                   busy_timeout_s: float = 0.0) -> dict[str, Any]:
        seen.update(db=db_url, config=config, busy=busy_timeout_s)
        return {"stored_samples": 0}

    monkeypatch.setattr(daemon_mod, "serve", fake_serve)
    url = f"sqlite:///{tmp_path / 'from-env.db'}"
    monkeypatch.setenv("CRANETWIN_DATABASE_URL", url)
    monkeypatch.setenv("CRANETWIN_INGEST_METRICS_BIND", "0")
    monkeypatch.setenv("CRANETWIN_INGEST_MAX_FUTURE_S", "5")
    monkeypatch.setenv("CRANETWIN_INGEST_BUSY_TIMEOUT_S", "1.5")
    out = CliRunner().invoke(app, ["ingest", "--bind", "0.0.0.0:6000", "--range-margin", "0.2",
                                   "--max-past", "3600"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.output.splitlines()[-1]) == {"event": "stopped", "stored_samples": 0}
    cfg = seen["config"]
    assert str(getattr(seen["db"], "url", seen["db"])) == url and seen["busy"] == 1.5
    assert (cfg.host, cfg.port, cfg.metrics_host) == ("0.0.0.0", 6000, None)
    assert (cfg.limits.max_past_s, cfg.limits.max_future_s, cfg.limits.range_margin) == \
        (3600.0, 5.0, 0.2)
    out = CliRunner().invoke(app, ["ingest", "--db", "sqlite:///given.db"])
    assert out.exit_code == 0 and \
        str(getattr(seen["db"], "url", seen["db"])) == "sqlite:///given.db"  # the option wins
    assert (seen["config"].metrics_host, seen["config"].port) == (None, 5005)


@pytest.mark.timeout(60)
def test_invalid_environment_setting_is_one_line_exit_2(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("CRANETWIN_INGEST_QUEUE_MAX", "lots")
    code, _, err = run_main(monkeypatch, capsys, "ingest")
    assert code == 2 and err.count("\n") == 1 and "CRANETWIN_INGEST_QUEUE_MAX" in err


@pytest.mark.timeout(60)
def test_machines_commands_honour_the_database_url_from_the_environment(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cranetwin.cli import app

    url = f"sqlite:///{tmp_path / 'env.db'}"
    monkeypatch.setenv("CRANETWIN_DATABASE_URL", url)
    monkeypatch.chdir(tmp_path)  # the default sqlite:///cranetwin.db would land here
    r = CliRunner()
    assert r.invoke(app, ["machines", "add", "crane-3", "--wire-id", "3"]).exit_code == 0
    listing = r.invoke(app, ["machines", "list", "--json"])
    assert [m["machine_id"] for m in json.loads(listing.output)] == ["crane-3"]
    assert not (tmp_path / "cranetwin.db").exists()
    with Store.open(url) as st:
        assert 3 in st.machine_keys()


@pytest.mark.timeout(60)
def test_secret_on_the_command_line_is_refused(sqlite_url: str) -> None:
    from cranetwin.cli import app

    out = CliRunner().invoke(app, ["machines", "add", "crane-1", "--wire-id", "1", "--db",
                                   sqlite_url, "--secret", "00112233445566778899aabbccddeeff"])
    assert out.exit_code == 2
    assert "--secret-file" in out.output and "CRANETWIN_MACHINE_SECRET" in out.output
    assert "00112233445566778899aabbccddeeff" not in out.output
    with Store.open(sqlite_url) as st:
        assert st.machine_keys() == {}


@pytest.mark.timeout(60)
def test_secret_from_file_or_environment_is_never_printed(
        sqlite_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cranetwin.cli import app

    r = CliRunner()
    f = tmp_path / "crane-1.key"
    f.write_text("00112233445566778899aabbccddeeff\n")
    f.chmod(0o600)
    out = r.invoke(app, ["machines", "add", "crane-1", "--wire-id", "1", "--db", sqlite_url,
                         "--secret-file", str(f)])
    assert out.exit_code == 0, out.output
    assert "0011223344" not in out.output and "warning" not in out.output
    env = "ffeeddccbbaa99887766554433221100"
    monkeypatch.setenv("CRANETWIN_MACHINE_SECRET", env)
    out = r.invoke(app, ["machines", "add", "crane-2", "--wire-id", "2", "--db", sqlite_url])
    assert out.exit_code == 0 and env not in out.output
    with Store.open(sqlite_url) as st:
        keys = st.machine_keys()
    assert keys[1][1].hex() == "00112233445566778899aabbccddeeff" and keys[2][1].hex() == env


@pytest.mark.timeout(60)
def test_generated_secret_is_printed_once_or_written_to_a_0600_file(
        sqlite_url: str, tmp_path: Path) -> None:
    from cranetwin.cli import app

    r = CliRunner()
    out = r.invoke(app, ["machines", "add", "crane-1", "--wire-id", "1", "--db", sqlite_url])
    printed = out.output.split("shown once): ")[1].strip()
    target = tmp_path / "crane-2.key"
    out2 = r.invoke(app, ["machines", "add", "crane-2", "--wire-id", "2", "--db", sqlite_url,
                          "--secret-out", str(target)])
    assert out2.exit_code == 0, out2.output
    written = target.read_text().strip()
    assert written not in out2.output and len(bytes.fromhex(written)) == 32
    assert stat.S_IMODE(target.stat().st_mode) == 0o600
    again = r.invoke(app, ["machines", "add", "crane-3", "--wire-id", "3", "--db", sqlite_url,
                           "--secret-out", str(target)])
    assert again.exit_code != 0 and target.read_text().strip() == written  # never overwritten
    with Store.open(sqlite_url) as st:
        keys = st.machine_keys()
    assert keys[1][1].hex() == printed and keys[2][1].hex() == written and 3 not in keys


@pytest.mark.timeout(60)
def test_machines_add_refuses_a_malformed_model_file_with_the_field_path(
        sqlite_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(BAD_TOML)
    code, _, err = run_main(monkeypatch, capsys, "machines", "add", "crane-4", "--wire-id", "4",
                            "--db", sqlite_url, "--model", str(bad))
    assert code == 2 and "Traceback" not in err
    assert "bodies.0.name" in err, err
    code, _, err = run_main(monkeypatch, capsys, "machines", "add", "crane-4", "--wire-id", "4",
                            "--db", sqlite_url, "--model", str(tmp_path / "missing.toml"))
    assert code == 2 and "no such file" in err
    with Store.open(sqlite_url) as st:
        assert st.machine_keys() == {}
    good = tmp_path / "good.toml"
    from cranetwin.model.loader import builtin_machines

    assert "patu655" in builtin_machines()
    import importlib.resources as res

    good.write_text((res.files("cranetwin") / "machines" / "patu655.toml").read_text())
    code, out, err = run_main(monkeypatch, capsys, "machines", "add", "crane-4", "--wire-id", "4",
                              "--db", sqlite_url, "--model", str(good))
    assert code == 0, err
    with Store.open(sqlite_url) as st:
        assert "[machine]" in st.get_machine("crane-4").model


@pytest.mark.timeout(60)
def test_api_registration_refuses_an_unknown_model_with_the_field_path(sqlite_url: str) -> None:
    from fastapi.testclient import TestClient

    from cranetwin.api import Settings, create_app
    from cranetwin.service.backend import Backend

    settings = Settings(database_url=sqlite_url, worker_enabled=False, warm_up=False)
    backend = Backend.open(sqlite_url)
    _, token = backend.create_key("admin", "test")
    backend.close()
    with TestClient(create_app(settings)) as client:
        h = {"X-API-Key": token}
        r = client.post("/api/v1/machines", headers=h,
                        json={"machine_id": "crane-8", "model": "no-such-model"})
        assert r.status_code == 422, r.text
        body = r.json()
        assert body["errors"][0]["loc"] == ["body", "model"]
        assert "no-such-model" in body["detail"]
        ok = client.post("/api/v1/machines", headers=h,
                         json={"machine_id": "crane-8", "model": "patu655"})
        assert ok.status_code == 201, ok.text
