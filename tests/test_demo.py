"""The one-command demo: continuous simulated cranes (no pose jump, no false event), a guarded
start (lock, port probes, progress-following health wait), nothing of an earlier run deleted."""

from __future__ import annotations

import http.server
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cranetwin.demo import DemoConfig, DemoError, DemoLock, FleetDemo, demo_scenario

PERIOD_S = 0.01


def _key() -> Any:
    from cranetwin.model import load_machine
    from cranetwin.protocol import Layout, MachineKey

    m = load_machine("patu655")
    return m, MachineKey(1, "crane-1", b"k" * 16, Layout.from_channels(m.channels))


def _as_sender_reads(source: Any, n: int, batch: int = 5) -> np.ndarray:
    """``n`` rows read as the demo's sender reads them: 5 at a time from a wall-clock row, the
    last row re-read for a status datagram every so often."""
    row0 = 177_000_000_000
    parts = []
    for i in range(0, n, batch):
        parts.append(source.read(row0 + i, batch))
        if i % 6000 == 0 and i:
            np.testing.assert_array_equal(source.read(row0 + i + batch - 1, 1), parts[-1][-1:])
    return np.concatenate(parts)[:n]


def _pose_jumps(key: Any, v: np.ndarray, slew_limit: float) -> list[tuple[float, str, float]]:
    """Where the slewing angle or a rod position moves faster than a crane can, judged on means
    of 0.1 s (sensor noise averages out, a jump does not): (time [s], channel, speed)."""
    names = key.layout.names
    limits = {"slew_angle": 1.5 * slew_limit, "lift_s": 0.5, "jib_s": 0.5, "ext_s": 0.5}
    out = []
    n = v.shape[0] // 10 * 10
    for ch, lim in limits.items():
        x = v[:n, names.index(ch)].reshape(-1, 10)
        means = np.array([np.nanmean(r) for r in x])
        speed = np.abs(np.diff(means)) / (10 * PERIOD_S)
        out += [(float(i) * 0.1, ch, float(speed[i])) for i in np.flatnonzero(speed > lim)]
    return out


def _live_events(machine: Any, key: Any, v: np.ndarray) -> list[Any]:
    """What the twin worker's detector raises on these samples (replay, then
    :class:`EventDetector` on the load history, as ``service.worker`` does)."""
    from cranetwin.analytics import EventDetector
    from cranetwin.samples import SampleArrays
    from cranetwin.service.analytics import load_history
    from cranetwin.twin import replay

    t = 1.77e9 + np.arange(v.shape[0]) * PERIOD_S
    s = SampleArrays("crane-1", t, tuple(key.layout.names), v, period_ns=10_000_000)
    res = replay(s, machine, grid_hz=100.0)
    det = EventDetector(machine)
    det.update(load_history(machine, res, np.ones(res.t_s.shape, dtype=bool)))
    return list(det.all_events())


@pytest.mark.timeout(120)
def test_demo_cranes_move_continuously_and_raise_no_event(tmp_path: Path) -> None:
    """100 s of a demo crane as its sender streams it (several 27 s work cycles and past any
    cycle end): no pose jump and no event from the live detector. The same checks flag the
    replayed loop the sender used before (its restart jumps the crane back to the first pose)."""
    from cranetwin.ingest.sender import RecordingSource, simulator_source, simulator_stream

    machine, key = _key()
    sc = tmp_path / "scenario.json"
    # the heaviest demo logs (320 kg ± 15 %)
    sc.write_text(demo_scenario(max(DemoConfig().payloads_kg), 2, 3600.0).model_dump_json())
    stream, period = simulator_stream(key, machine, str(sc), seed=2)
    assert period == PERIOD_S
    v = _as_sender_reads(stream, 10_000)
    slew_limit = machine.joints[0].velocity_limit
    assert _pose_jumps(key, v, slew_limit) == []
    events = _live_events(machine, key, v)
    assert events == [], [(e.kind, e.severity, e.value, e.unit) for e in events]

    # the old way: 35 s simulated once, replayed cyclically
    values, _ = simulator_source(key, machine, str(sc), duration_s=35.0, seed=2)
    looped = _as_sender_reads(RecordingSource(values), 8000)
    jumps = _pose_jumps(key, looped, slew_limit)
    at = sorted({round(t) for t, ch, _ in jumps if ch == "slew_angle"})
    assert len(at) >= 2 and all(b - a == 35 for a, b in zip(at, at[1:], strict=False)), jumps


@pytest.mark.timeout(10)
def test_simulator_stream_rereads_and_refuses_old_rows() -> None:
    from cranetwin.ingest.sender import SenderError, SimulatorStream

    class Session:
        def __init__(self) -> None:
            self.t = 0

        def advance(self, seconds: float) -> Any:
            n = int(round(seconds / PERIOD_S))
            rows = np.arange(self.t, self.t + n, dtype=float)[:, None] * [1.0, -1.0]
            self.t += n
            return type("S", (), {"values": rows})()

    src = SimulatorStream(Session(), [1, 0], PERIOD_S, keep=50)
    a = src.read(1000, 5)
    np.testing.assert_array_equal(a[:, 1], np.arange(5))  # first row read = session t = 0
    np.testing.assert_array_equal(src.read(1003, 4)[:, 1], np.arange(3, 7))
    np.testing.assert_array_equal(src.read(1500, 2)[:, 1], [500, 501])  # a gap: simulated through
    with pytest.raises(SenderError, match="older"):
        src.read(1000, 1)


@pytest.fixture()
def demo_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("CRANETWIN_DEMO_LOGS", str(tmp_path / "demo"))
    return tmp_path


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.timeout(10)
def test_second_demo_is_refused_and_the_first_ones_database_kept(demo_env: Path) -> None:
    db = demo_env / "demo.db"
    db.write_bytes(b"an earlier run's data")
    cfg = DemoConfig(db_url=f"sqlite:///{db}", port=_free_port(),
                     udp_port=_free_port(socket.SOCK_DGRAM))
    first = FleetDemo(cfg)
    first.preflight()
    try:
        with pytest.raises(DemoError, match="already running on the directory .*pid"):
            FleetDemo(cfg).preflight()
        # another directory, same database: refused by the database's lock
        other = DemoConfig(db_url=cfg.db_url, port=_free_port(),
                           udp_port=_free_port(socket.SOCK_DGRAM))
        second = FleetDemo(other)
        second.logdir = demo_env / "other"
        with pytest.raises(DemoError, match=f"already running on the database {db}"):
            second.preflight()
        second.stop()
    finally:
        first.stop()
    assert db.read_bytes() == b"an earlier run's data"
    # stopped: the lock is free again
    again = FleetDemo(cfg)
    again.preflight()
    again.stop()


@pytest.mark.timeout(10)
def test_ports_in_use_are_named_before_anything_starts(demo_env: Path) -> None:
    with socket.socket() as tcp:
        tcp.bind(("127.0.0.1", 0))
        tcp.listen()
        demo = FleetDemo(DemoConfig(db_url=None, port=tcp.getsockname()[1],
                                    udp_port=_free_port(socket.SOCK_DGRAM)))
        with pytest.raises(DemoError, match="TCP port .* is in use.*--port"):
            demo.preflight()
        demo.stop()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        demo = FleetDemo(DemoConfig(db_url=None, port=_free_port(),
                                    udp_port=udp.getsockname()[1]))
        with pytest.raises(DemoError, match="UDP port .* is in use.*--udp-port"):
            demo.preflight()
        demo.stop()
    assert demo.children == []


@pytest.fixture()
def health_server() -> Iterator[tuple[int, list[int]]]:
    """A /healthz that answers the codes in the list, one per request (the last one repeats)."""
    codes = [503, 503, 200]

    class H(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802
            code = codes.pop(0) if len(codes) > 1 else codes[0]
            self.send_response(code)
            self.end_headers()
            self.wfile.write(b"{}")

        def log_message(self, *args: Any) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), H)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield srv.server_address[1], codes
    srv.shutdown()
    srv.server_close()


@pytest.mark.timeout(10)
def test_health_wait_reports_what_it_waits_for(demo_env: Path,
                                               health_server: tuple[int, list[int]]) -> None:
    port, _ = health_server
    notes: list[str] = []
    demo = FleetDemo(DemoConfig(attach=True, api_url=f"http://127.0.0.1:{port}"),
                     progress=notes.append)
    demo.wait_healthy()
    assert any("/healthz answers HTTP 503" in n for n in notes), notes
    assert "answers at" in notes[-1]

    notes.clear()
    closed = FleetDemo(DemoConfig(attach=True, api_url=f"http://127.0.0.1:{_free_port()}",
                                  start_timeout_s=0.5), progress=notes.append)
    with pytest.raises(DemoError, match=r"not become healthy in 0 s \(--start-timeout\): its "
                                        "port is not open"):
        closed.wait_healthy()
    assert "port is not open yet" in notes[0]


@pytest.mark.timeout(10)
def test_demo_lock_is_released_when_its_holder_dies(tmp_path: Path) -> None:
    import subprocess
    import sys

    path = tmp_path / "demo.lock"
    code = ("import sys, time; from pathlib import Path; from cranetwin.demo import DemoLock; "
            "DemoLock(Path(sys.argv[1])).acquire('x'); print('held', flush=True); time.sleep(30)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        with pytest.raises(DemoError, match="already running"):
            DemoLock(path).acquire("x")
    finally:
        proc.kill()
        proc.wait()
    lock = DemoLock(path)
    lock.acquire("x")  # a killed demo leaves no stale lock
    lock.release()


@pytest.mark.timeout(60)
def test_units_in_brackets_survive_every_help_text() -> None:
    """Units written as "[kg]", "[s]", "[h]" in option help appear in ``--help`` (Rich markup
    used to swallow them as tags: "Payload on the hook .")."""
    import re

    import typer
    from typer.testing import CliRunner

    from cranetwin.cli import app

    root = typer.main.get_command(app)
    checked = 0

    def walk(cmd: Any, path: list[str]) -> None:
        nonlocal checked
        if hasattr(cmd, "commands"):  # typer's groups are not click.Group subclasses
            for name, sub in cmd.commands.items():
                walk(sub, [*path, name])
            return
        units = {u for p in cmd.params for u in re.findall(r"\[[^\]\s]{1,8}\]",
                                                            getattr(p, "help", None) or "")}
        if not units:
            return
        out = CliRunner().invoke(app, [*path, "--help"], terminal_width=200).output
        flat = " ".join(out.split())
        for u in units:
            assert u in flat, f"cranetwin {' '.join(path)} --help lost {u}"
        checked += 1

    walk(root, [])
    assert checked >= 5


@pytest.mark.timeout(10)
def test_demo_api_gets_no_replay_process_unless_the_environment_asks(
        demo_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import cranetwin.demo as demo_mod

    envs: list[dict[str, str]] = []

    class Recorder:
        pid = 1

        def __init__(self, args: list[str], **kw: Any) -> None:
            envs.append(kw["env"])

    monkeypatch.setattr(demo_mod.subprocess, "Popen", Recorder)
    demo = FleetDemo(DemoConfig(attach=True, api_url="http://127.0.0.1:1"))
    monkeypatch.delenv("CRANETWIN_HEAVY_PROCESSES", raising=False)
    demo._spawn("api", ["serve"], defaults={"CRANETWIN_HEAVY_PROCESSES": "0"})
    monkeypatch.setenv("CRANETWIN_HEAVY_PROCESSES", "2")
    demo._spawn("api", ["serve"], defaults={"CRANETWIN_HEAVY_PROCESSES": "0"})
    assert [e["CRANETWIN_HEAVY_PROCESSES"] for e in envs] == ["0", "2"]
