"""End to end: ``cranetwin fleetdemo`` (simulator → sender → UDP → ingest daemon → SQLite →
API → live websocket) → Chromium, then Ctrl-C stops every process. (The UI features are tested
on the real app in ``test_web_browser.py``.)"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
ARTIFACTS = Path(__file__).parent / "artifacts"

pytestmark = [pytest.mark.browser, pytest.mark.slow]
if not Path(CHROMIUM).exists():
    pytestmark.append(pytest.mark.skip(reason="Chromium not installed (apt-get install chromium; "
                                              "`make system-deps` does it)"))
playwright_api = pytest.importorskip("playwright.sync_api",
                                     reason="playwright not installed (pip install -e '.[dev]')")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


def _shot(locator: Any, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    locator.screenshot(path=str(ARTIFACTS / name))


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
         "--sim-hours", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path)
    try:
        url = key = None
        t_start = time.time()
        deadline = t_start + 120
        lines = []
        assert proc.stdout is not None
        while key is None and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("open  "):
                url = line.split()[1]
            if line.startswith("key   "):
                key = line.split()[1]
        assert url and key, "".join(lines)
        assert "key=" not in url and key not in url  # no key in the printed URL
        ctx = browser.new_context(viewport={"width": 1280, "height": 860})
        page = ctx.new_page()
        page.goto(url)  # a first visit: sign in once with the printed key
        page.wait_for_selector("#key-dialog[open]", timeout=30000)
        page.fill("#key-input", key)
        page.click("#key-form button")
        page.wait_for_function("window.cranetwin && window.cranetwin.ready === true",
                               timeout=30000)
        page.goto(f"http://127.0.0.1:{port}/machines/crane-1?mode=live")
        # the sender simulates continuously from its first sample: frames come at once
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=150_000)
        print(f"demo: command to first live frames on the page {time.time() - t_start:.1f} s")
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
