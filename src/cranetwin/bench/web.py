"""``cranetwin bench web``: first meaningful paint, replay frame rate and live latency in Chromium.

Runs the web UI on the synthetic preview app (:mod:`cranetwin.api.preview`, real uvicorn on
loopback) and drives Debian's Chromium headless (software WebGL) with Playwright. Figures:

- ``first_paint_seconds``: navigation start → first crane frame drawn on the machine page, the
  first load after the server started (cold server, new browser context);
  ``first_paint_warm_seconds``: median of the next loads (new contexts, so no browser cache);
  ``first_paint_ms`` / ``first_paint_all_ms``: all of them [ms];
- ``replay_fps`` / ``replay_p95_frame_ms``: requestAnimationFrame rate while playing a 10-minute
  window (at 1× and 16×, which streams a new 60 s chunk every 3.75 s);
- ``live_p50_ms`` / ``live_p95_ms`` (= ``live_p95_latency_ms``): sample time (samples written
  to the store every 0.2 s, stamped now) → frame drawn in the page;
- ``demo_first_live_seconds``: ``cranetwin fleetdemo --machines 1`` started in a fresh empty
  directory → the demo reports its crane live (``--no-demo`` skips it);
- baseline: rAF rate of an empty page in the same browser (``blank_fps``), and the ratio
  ``replay_fps / blank_fps`` (1.0 = the crane costs no frames);
- ``render_frame_ms``: median time to draw one 3D frame and wait for it (60 frames), interleaved
  with ``render_frame_ms_baseline_gradient``, the same frame with meshcat's gradient background
  quad at pixel ratio 0.7 (what the page drew before; software rasterisers pay for every pixel).

The browser signs in the way a person does: the key is POSTed once to ``/api/v1/session`` and
the pages are opened with the session cookie only, never with a key in their URL.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from typing import Any

import typer

from cranetwin.bench import emit
from cranetwin.errors import MissingExtraError

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def sign_in(context: Any, base_url: str, key: str) -> None:
    """Sign a Playwright browser context in: the key is POSTed once to ``/api/v1/session``; the
    HttpOnly session cookie the server answers with lands in the context's cookie jar, so every
    page of the context is opened without a key in its URL."""
    resp = context.request.post(f"{base_url}/api/v1/session", data={"key": key})
    if not resp.ok:
        raise RuntimeError(f"sign-in refused: HTTP {resp.status} {resp.text()[:200]}")


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


LIVE_LINE = re.compile(r"is live \((\d+(?:\.\d+)?) s after the start\)")


def demo_first_live(timeout_s: float = 300.0) -> float | None:
    """Seconds from starting ``cranetwin fleetdemo --machines 1`` in a fresh empty directory
    (its own database, logs and free ports) to the demo reporting its crane live; None when it
    did not within ``timeout_s``. The demo is stopped (SIGINT, then SIGKILL) afterwards."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="cranetwin-bench-demo-") as d:
        env = {**os.environ, "CRANETWIN_DEMO_LOGS": os.path.join(d, "logs"),
               "PYTHONUNBUFFERED": "1"}  # its progress lines as they are printed
        cmd = [sys.executable, "-c", "from cranetwin.cli import main; main()", "fleetdemo",
               "--machines", "1",
               "--port", str(_free_port(socket.SOCK_STREAM)),
               "--udp-port", str(_free_port(socket.SOCK_DGRAM)),
               "--db", f"sqlite:///{d}/demo.db", "--start-timeout", str(timeout_s)]
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=d, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        lines: queue.Queue[str] = queue.Queue()

        def _read() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.put(line)

        threading.Thread(target=_read, daemon=True).start()
        found: float | None = None
        try:
            while found is None and time.monotonic() - t0 < timeout_s and proc.poll() is None:
                try:
                    line = lines.get(timeout=0.2)
                except queue.Empty:
                    continue
                if LIVE_LINE.search(line):
                    found = time.monotonic() - t0
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)
        return found


RENDER_AB_JS = """([n]) => {
  // One 3D frame drawn and waited for (readPixels of one pixel finishes the GPU work), n times
  // each, alternating: the page as it is, and meshcat's gradient background quad at 0.7x.
  const cr = window.__crane, v = cr.viewer, r = v.renderer, gl = r.getContext();
  const own = [v.scene.background, r.getPixelRatio()];
  v.handle_command({type: "set_property", path: "/Background", property: "top_color",
                    value: [0.87, 0.9, 0.94]});
  const baseline = [v.scene.background, 0.7];
  const px = new Uint8Array(4), out = {page: [], baseline: []};
  const cfgs = [["page", own], ["baseline", baseline]];
  for (let k = 0; k < n; k++) for (const [name, [bg, ratio]] of cfgs) {
    v.scene.background = bg;
    if (r.getPixelRatio() !== ratio) { r.setPixelRatio(ratio); cr.resize(); }
    const t0 = performance.now();
    v.render(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    out[name].push(performance.now() - t0);
  }
  v.scene.background = own[0]; r.setPixelRatio(own[1]); cr.resize(); v.set_dirty();
  const med = (a) => a.slice().sort((x, y) => x - y)[a.length >> 1];
  return {page: med(out.page), baseline: med(out.baseline), ratio: own[1]};
}"""
"""Render cost of one frame of the machine page against meshcat's default background, the two
interleaved in one page so both see the same load."""


def _fps(intervals: list[float]) -> tuple[float, float]:
    xs = sorted(x for x in intervals if x > 0)
    if not xs:
        return 0.0, 0.0
    return 1000.0 / statistics.median(xs), xs[int(0.95 * (len(xs) - 1))]


class _LiveFeeder:
    """Writes 0.2 s sample blocks stamped "now" into the store every 0.2 s (a live machine)."""

    def __init__(self, app: Any, machine_id: str) -> None:
        import threading

        self.app, self.machine_id = app, machine_id
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        from cranetwin.model import load_machine
        from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

        machine = load_machine("patu655")
        base = kinematic_samples(machine, 120.0)
        store = self.app.state.services.backend.store
        seq = 10_000_000
        while not self.stop.is_set():
            start = round(time.time() - 0.2, 2)
            blocks = list(tiled_blocks(self.machine_id, machine, start, 0.2, 0.2, base=base,
                                       seq0=seq))
            seq += len(blocks)
            store.write_blocks(blocks)
            self.stop.wait(0.2)


def _real_app(tmpdir: str, web_dir: str | None = None) -> Any:
    """create_app on a temporary SQLite database (filled by :func:`_fill`), serving the web
    files of ``web_dir`` (None: the repository's)."""
    from pathlib import Path

    from cranetwin.api import create_app
    from cranetwin.settings import Settings

    url = f"sqlite:///{tmpdir}/bench-web.db"
    return create_app(Settings(database_url=url, worker_in_process=False,
                               web_dir=Path(web_dir) if web_dir else None))


def _fill(app: Any, srv_url: str, end: float, history_s: float) -> str:
    import httpx

    from cranetwin.model import load_machine
    from cranetwin.service.worker import TwinWorker
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    services = app.state.services
    viewer = services.backend.create_key("viewer", "bench web")[1]
    admin = services.backend.create_key("admin", "bench web")[1]
    machine = load_machine("patu655")
    for mid in ("crane-1", "crane-2"):
        httpx.post(f"{srv_url}/api/v1/machines", headers={"X-API-Key": admin},
                   json={"machine_id": mid, "model": "patu655"}).raise_for_status()
    base = kinematic_samples(machine, 120.0)
    services.backend.store.write_blocks(list(tiled_blocks("crane-2", machine, end - history_s,
                                                          history_s, 1.0, base=base)))
    TwinWorker(services.backend, services.settings, services.metrics,
               services.fleet.replayer).catch_up(services.backend.machine("crane-2"))
    return str(viewer)


def run(seconds: float = 6.0, chromium: str = "/usr/bin/chromium",
        server: str = "real", demo: bool = True, web_dir: str | None = None) -> dict[str, Any]:
    """Measure the figures above; returns them as a dict.

    Args:
        seconds: Measuring time per figure [s].
        chromium: Chromium executable.
        server: ``real`` (create_app on SQLite with 15 min of stored samples) or ``preview``
            (synthetic data, no database).
        demo: Also measure ``demo_first_live_seconds`` (starts a demo in a fresh directory).
        web_dir: Serve the pages from this copy of ``web/`` (A/B comparisons of front-end
            changes; real server only).
    """
    import tempfile

    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        raise MissingExtraError("dev", "the browser benchmark (playwright)") from exc

    from cranetwin.api.preview import PREVIEW_KEY, ServerThread, create_preview_app

    end = float(int(time.time()) - 60)
    tmp = tempfile.TemporaryDirectory()
    feeder = None
    if server == "real":
        app = _real_app(tmp.name, web_dir)
    else:
        app = create_preview_app(history_s=1800.0, end=end)
    out: dict[str, Any] = {"browser": "chromium (headless, swiftshader)", "server": server,
                           "web_dir": web_dir or "repository"}
    with ServerThread(app) as srv, sync_playwright() as p:
        key = _fill(app, srv.url, end, 900.0) if server == "real" else PREVIEW_KEY
        if server == "real":
            feeder = _LiveFeeder(app, "crane-1")
            feeder.thread.start()
        browser = p.chromium.launch(executable_path=chromium, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 860})
        sign_in(page.context, srv.url, key)
        # baseline: an empty page's animation-frame rate
        page.set_content("<html><body></body></html>")
        blank = page.evaluate(
            "() => new Promise(r => { const t = []; let last = null;"
            " function f(now) { if (last !== null) t.push(now - last); last = now;"
            f" if (t.length < {int(seconds * 60)}) requestAnimationFrame(f); else r(t); }}"
            " requestAnimationFrame(f); })")
        out["blank_fps"], _ = _fps(blank)
        # first meaningful paint (cold: new context each time, so no cache)
        paints = []
        for _ in range(4):
            ctx = browser.new_context(viewport={"width": 1280, "height": 860})
            sign_in(ctx, srv.url, key)
            pg = ctx.new_page()
            pg.goto(f"{srv.url}/machines/crane-2?mode=replay"
                    f"&from={end - 600}&to={end}&t={end - 300}")
            pg.wait_for_function("window.cranetwin && window.cranetwin.ready", timeout=30000)
            paints.append(pg.evaluate("window.cranetwin.firstFrameMs"))
            out["first_paint_breakdown_ms"] = pg.evaluate(
                "(() => { const c = window.cranetwin; const r = {module_start: c.moduleStartMs,"
                " scene_ready: c.moduleStartMs + c.sceneMs, first_frame: c.firstFrameMs};"
                " for (const e of performance.getEntriesByType('resource')) {"
                "  const n = e.name.split('?')[0].split('/').pop();"
                "  if (['meshcat.min.js', 'scene', 'twin', 'model', 'crane-2'].includes(n))"
                "   r[n + '_done'] = Math.max(r[n + '_done'] || 0, e.responseEnd); }"
                " for (const k in r) r[k] = Math.round(r[k]); return r; })()")
            ctx.close()
        out["first_paint_seconds"] = paints[0] / 1000.0
        out["first_paint_warm_seconds"] = statistics.median(paints[1:]) / 1000.0
        out["first_paint_ms"] = statistics.median(paints)
        out["first_paint_all_ms"] = paints
        # replay of a 10-minute window
        for speed in (1, 16):
            page.goto(f"{srv.url}/machines/crane-2?mode=replay"
                      f"&from={end - 600}&to={end}&t={end - 600}&speed={speed}")
            page.wait_for_function("window.cranetwin && window.cranetwin.ready", timeout=30000)
            page.wait_for_selector("#charts .main-svg", timeout=30000)
            page.evaluate("window.cranetwin.rafIntervals = []; window.__f0 ="
                          " window.cranetwin.framesRendered")
            page.keyboard.press("Space")
            page.wait_for_timeout(int(seconds * 1000))
            page.keyboard.press("Space")
            iv = page.evaluate("window.cranetwin.rafIntervals")
            drawn = page.evaluate("window.cranetwin.framesRendered - window.__f0")
            fps, p95 = _fps(iv)
            out[f"replay_{speed}x_fps"] = fps
            out[f"replay_{speed}x_p95_frame_ms"] = p95
            out[f"replay_{speed}x_drawn_fps"] = drawn / seconds
        out["replay_fps"] = min(out["replay_1x_fps"], out["replay_16x_fps"])
        ab = page.evaluate(RENDER_AB_JS, [60])
        out["render_frame_ms"] = ab["page"]
        out["render_frame_ms_baseline_gradient"] = ab["baseline"]
        out["render_pixel_ratio"] = ab["ratio"]
        out["replay_fps_ratio_to_blank"] = out["replay_fps"] / out["blank_fps"]
        # live latency (server frame time -> drawn), 25 Hz stream
        page.goto(f"{srv.url}/machines/crane-1?mode=live")
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=30000)
        page.evaluate("window.cranetwin.liveLatencyMs = []")
        page.wait_for_timeout(int(seconds * 1000))
        lat = sorted(page.evaluate("window.cranetwin.liveLatencyMs"))
        out["live_frames"] = len(lat)
        out["live_p50_ms"] = lat[len(lat) // 2] if lat else None
        out["live_p95_ms"] = lat[int(0.95 * (len(lat) - 1))] if lat else None
        out["live_p95_latency_ms"] = out["live_p95_ms"]
        browser.close()
        if feeder is not None:
            feeder.stop.set()
            feeder.thread.join(5)
    tmp.cleanup()
    if demo:
        out["demo_first_live_seconds"] = demo_first_live()
    return out


def register(bench_app: typer.Typer) -> None:
    """Add ``cranetwin bench web``."""

    @bench_app.command("web")
    def web(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        seconds: float = typer.Option(6.0, help="Measuring time per figure [s]."),
        chromium: str = typer.Option("/usr/bin/chromium", help="Chromium executable."),
        server: str = typer.Option("real", help="real (create_app + SQLite) or preview."),
        demo: bool = typer.Option(True, help="Also time a demo started in a fresh directory "
                                  "(demo_first_live_seconds)."),
        web_dir: str = typer.Option("", help="Serve the pages from this copy of web/ (A/B "
                                    "runs of front-end changes; default: the repository's)."),
    ) -> None:
        """Web UI: first paint (cold and warm server), replay fps (10-min window), live latency
        (sample → screen) in headless Chromium, and the demo's time to its first live crane."""
        result = run(seconds, chromium, server, demo, web_dir or None)
        emit(result, as_json)
