"""The web UI on the real service: ``create_app`` on SQLite, stored samples → twin → page.

Data: kinematic samples of the API's synthetic source (exact, known payload) stored for 4
minutes, twin-worker summaries computed, then the browser replays them; live: samples written to
the store now reach the page through the API's live fan-out and websocket.
"""

from __future__ import annotations

import io
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
ARTIFACTS = Path(__file__).parent / "artifacts"
MID = "crane-1"

pytestmark = [pytest.mark.browser, pytest.mark.slow]
if not Path(CHROMIUM).exists():
    pytestmark.append(pytest.mark.skip(reason="Chromium not installed (apt-get install chromium; "
                                              "`make system-deps` does it)"))
playwright_api = pytest.importorskip("playwright.sync_api",
                                     reason="playwright not installed (pip install -e '.[dev]')")
Image = pytest.importorskip("PIL.Image", reason="Pillow needed for pixel checks")


class Service:
    def __init__(self, srv: Any, app: Any, keys: dict[str, str], t0: float, span: float) -> None:
        self.srv, self.app, self.keys, self.t0, self.span = srv, app, keys, t0, span

    @property
    def url(self) -> str:
        return str(self.srv.url)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    from cranetwin.api import Settings, create_app
    from cranetwin.api.synthetic import kinematic_samples, tiled_blocks
    from cranetwin.api.worker import TwinWorker
    from cranetwin.model import load_machine
    from cranetwin.viz.preview import ServerThread

    url = f"sqlite:///{tmp_path_factory.mktemp('web_e2e') / 'web.db'}"
    app = create_app(Settings(database_url=url, worker_enabled=False))
    machine = load_machine("patu655")
    span = 240.0
    t0 = float(int(time.time() - 3600) // 60 * 60)  # a whole minute, an hour ago
    with ServerThread(app) as srv:
        services = app.state.services
        keys = {r: services.backend.create_key(r, f"web e2e {r}")[1]
                for r in ("viewer", "admin")}
        r = httpx.post(f"{srv.url}/api/v1/machines", headers={"X-API-Key": keys["admin"]},
                       json={"machine_id": MID, "model": "patu655", "name": "Crane 1"})
        assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        services.backend.store.write_blocks(list(tiled_blocks(MID, machine, t0, span, 1.0,
                                                              base=base)))
        worker = TwinWorker(services.backend, services.settings, services.metrics,
                            services.replayer)
        worker.catch_up(services.backend.machine_or_404(MID))
        yield Service(srv, app, keys, t0, span)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture()
def page(browser: Any) -> Iterator[Any]:
    ctx = browser.new_context(viewport={"width": 1280, "height": 860})
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.errors = errors
    yield pg
    ctx.close()


def _shot(locator: Any, name: str) -> Any:
    ARTIFACTS.mkdir(exist_ok=True)
    png = locator.screenshot(path=str(ARTIFACTS / name))
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def _boom(img: Any) -> Any:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 140) & (g > 90) & (b < 90) & (r - b > 90)


def test_fleet_page_lists_the_stored_machine(page: Any, service: Service) -> None:
    page.goto(f"{service.url}/?key={service.keys['viewer']}")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=20000)
    assert page.locator(f"tr[data-machine-id={MID}]").count() == 1
    assert "Crane 1" in page.locator("#rows").inner_text()
    assert not page.errors


def test_replay_of_stored_data_draws_and_moves_the_crane(page: Any, service: Service) -> None:
    t0, t1 = service.t0, service.t0 + service.span
    page.goto(f"{service.url}/machines/{MID}?key={service.keys['viewer']}&mode=replay"
              f"&from={t0}&to={t1}&t={t0 + 20}")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)
    page.wait_for_timeout(300)
    a = _shot(page.locator("#view3d"), "e2e-replay-a.png")
    assert _boom(a).mean() > 0.002
    page.locator("#slider").focus()
    page.keyboard.press("Shift+ArrowRight")
    page.wait_for_function(f"Math.abs(window.cranetwin.cursor - {t0 + 30}) < 0.01")
    page.wait_for_timeout(500)
    b = _shot(page.locator("#view3d"), "e2e-replay-b.png")
    assert (np.abs(a - b).sum(axis=2) > 60).mean() > 0.002
    # charts from the stored (derived) summaries
    page.wait_for_selector("#charts .main-svg", timeout=20000)
    page.wait_for_function("document.querySelectorAll('#charts .scatterlayer .trace').length > 3",
                           timeout=20000)
    _shot(page, "e2e-replay-page.png")
    payload = page.locator("#now-payload").inner_text()
    assert payload.endswith("kg")
    assert not page.errors


def test_live_sample_reaches_the_page_within_a_second(page: Any, service: Service) -> None:
    from cranetwin.api.synthetic import kinematic_samples, tiled_blocks
    from cranetwin.model import load_machine

    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    page.goto(f"{service.url}/machines/{MID}?key={service.keys['viewer']}&mode=live")
    page.wait_for_function("window.cranetwin && window.cranetwin.mode === 'live'"
                           " && window.cranetwin.sceneMs !== null", timeout=30000)
    page.wait_for_timeout(1000)
    store = service.app.state.services.backend.store
    latencies = []
    seq = 500_000
    for k in range(4):
        start = float(int(time.time()))  # whole seconds: tiled_blocks wants sample-aligned starts
        blocks = list(tiled_blocks(MID, machine, start, 1.0, 1.0, base=base, seq0=seq))
        seq += len(blocks)
        sent = time.time()
        store.write_blocks(blocks)
        page.wait_for_function(f"window.cranetwin.lastLiveT !== null && "
                               f"window.cranetwin.lastLiveT >= {start + 0.9}", timeout=3000)
        latencies.append(time.time() - sent)
        if k == 0:  # first frame drawn: the page now loads its charts library; let it settle
            page.wait_for_selector("#charts .main-svg", timeout=20000)
            page.wait_for_timeout(1500)
    _shot(page, "e2e-live.png")
    assert max(latencies[1:]) < 1.0, latencies
    assert not page.errors


def _processes_with(text: str) -> list[int]:
    """PIDs whose command line contains ``text`` (read from /proc)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if text in cmd:
                pids.append(int(entry.name))
    return pids


def test_demo_simulator_udp_daemon_db_api_websocket_page(browser: Any,
                                                          tmp_path: Path) -> None:
    """The whole chain: `cranetwin fleetdemo` (simulator → sender → UDP → ingest daemon →
    SQLite → API → live websocket) → Chromium; then Ctrl-C stops every process."""
    import os
    import signal
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        udp = s.getsockname()[1]
    db = tmp_path / "demo-e2e.db"
    env = {**os.environ, "CRANETWIN_DEMO_LOGS": str(tmp_path / "logs")}
    proc = subprocess.Popen(
        [sys.executable, "-c", "from cranetwin.cli import main; main()", "fleetdemo",
         "--machines", "1", "--port", str(port), "--udp-port", str(udp), "--db", f"sqlite:///{db}",
         "--cycle-seconds", "40"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path)
    try:
        url = None
        deadline = time.time() + 120
        lines = []
        assert proc.stdout is not None
        while url is None and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("open  "):
                url = line.split()[1]
        assert url, "".join(lines)
        key = url.split("key=")[1]
        ctx = browser.new_context(viewport={"width": 1280, "height": 860})
        page = ctx.new_page()
        page.goto(f"http://127.0.0.1:{port}/machines/crane-1?key={key}&mode=live")
        # the sender simulates first (JIT + 40 s of crane at > 20x real time), then streams
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=150_000)
        page.wait_for_selector("#charts .main-svg", timeout=30000)
        page.wait_for_timeout(1500)
        page.evaluate("window.cranetwin.liveLatencyMs = []")
        f0 = page.evaluate("window.cranetwin.liveFrames")
        page.wait_for_timeout(4000)
        lat = sorted(page.evaluate("window.cranetwin.liveLatencyMs"))
        frames = page.evaluate("window.cranetwin.liveFrames") - f0
        _shot(page, "e2e-demo-live.png")
        ctx.close()
        assert frames >= 20, f"only {frames} live frames in 4 s"
        p95 = lat[int(0.95 * (len(lat) - 1))]
        print(f"demo live: {frames / 4:.0f} frames/s, sample→screen p50 {lat[len(lat) // 2]:.0f} "
              f"ms, p95 {p95:.0f} ms")
        assert p95 < 1000, lat  # a sample reaches the screen within a second
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 0, out
    assert "stopped." in out
    assert _processes_with(str(db)) == []  # daemon, API and sender all gone
