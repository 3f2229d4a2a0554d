"""``cranetwin bench web``: first meaningful paint, replay frame rate and live latency in Chromium.

Runs the web UI on the synthetic preview app (:mod:`cranetwin.api.preview`, real uvicorn on
loopback) and drives Debian's Chromium headless (software WebGL) with Playwright. Figures:

- ``first_paint_ms``: navigation start → first crane frame drawn on the machine page (median of 3
  cold loads, cache disabled);
- ``replay_fps`` / ``replay_p95_frame_ms``: requestAnimationFrame rate while playing a 10-minute
  window (at 1× and 16×, which streams a new 60 s chunk every 3.75 s);
- ``live_p50_ms`` / ``live_p95_ms``: frame generated on the server → drawn in the page (25 Hz);
- baseline: rAF rate of an empty page in the same browser (``blank_fps``), and the ratio
  ``replay_fps / blank_fps`` (1.0 = the crane costs no frames).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import typer

from cranetwin.bench import emit
from cranetwin.errors import MissingExtraError

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


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


def _real_app(tmpdir: str, end: float, history_s: float) -> tuple[Any, dict[str, Any]]:
    """create_app on a temporary SQLite database holding ``history_s`` of kinematic samples."""
    from cranetwin.api import create_app
    from cranetwin.settings import Settings

    url = f"sqlite:///{tmpdir}/bench-web.db"
    return create_app(Settings(database_url=url, worker_in_process=False)), {"url": url}


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
        server: str = "real") -> dict[str, Any]:
    """Measure the figures above; returns them as a dict.

    Args:
        seconds: Measuring time per figure [s].
        chromium: Chromium executable.
        server: ``real`` (create_app on SQLite with 15 min of stored samples) or ``preview``
            (synthetic data, no database).
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
        app, _ = _real_app(tmp.name, end, 900.0)
    else:
        app = create_preview_app(history_s=1800.0, end=end)
    out: dict[str, Any] = {"browser": "chromium (headless, swiftshader)", "server": server}
    with ServerThread(app) as srv, sync_playwright() as p:
        key = _fill(app, srv.url, end, 900.0) if server == "real" else PREVIEW_KEY
        if server == "real":
            feeder = _LiveFeeder(app, "crane-1")
            feeder.thread.start()
        browser = p.chromium.launch(executable_path=chromium, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 860})
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
        for _ in range(3):
            ctx = browser.new_context(viewport={"width": 1280, "height": 860})
            pg = ctx.new_page()
            pg.goto(f"{srv.url}/machines/crane-2?key={key}&mode=replay"
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
        out["first_paint_ms"] = statistics.median(paints)
        out["first_paint_all_ms"] = paints
        # replay of a 10-minute window
        for speed in (1, 16):
            page.goto(f"{srv.url}/machines/crane-2?key={key}&mode=replay"
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
        out["replay_fps_ratio_to_blank"] = out["replay_fps"] / out["blank_fps"]
        # live latency (server frame time -> drawn), 25 Hz stream
        page.goto(f"{srv.url}/machines/crane-1?key={key}&mode=live")
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=30000)
        page.evaluate("window.cranetwin.liveLatencyMs = []")
        page.wait_for_timeout(int(seconds * 1000))
        lat = sorted(page.evaluate("window.cranetwin.liveLatencyMs"))
        out["live_frames"] = len(lat)
        out["live_p50_ms"] = lat[len(lat) // 2] if lat else None
        out["live_p95_ms"] = lat[int(0.95 * (len(lat) - 1))] if lat else None
        browser.close()
        if feeder is not None:
            feeder.stop.set()
            feeder.thread.join(5)
    tmp.cleanup()
    return out


def register(bench_app: typer.Typer) -> None:
    """Add ``cranetwin bench web``."""

    @bench_app.command("web")
    def web(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        seconds: float = typer.Option(6.0, help="Measuring time per figure [s]."),
        chromium: str = typer.Option("/usr/bin/chromium", help="Chromium executable."),
        server: str = typer.Option("real", help="real (create_app + SQLite) or preview."),
    ) -> None:
        """Web UI: first paint, replay fps (10-min window), live latency in headless Chromium."""
        result = run(seconds, chromium, server)
        emit(result, as_json)
