"""``cranetwin bench web``: first meaningful paint, replay frame rate and live latency in Chromium.

Runs the web UI on the synthetic preview app (:mod:`cranetwin.viz.preview`, real uvicorn on
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

import json
import statistics
import time
from typing import Any

import typer

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def _fps(intervals: list[float]) -> tuple[float, float]:
    xs = sorted(x for x in intervals if x > 0)
    if not xs:
        return 0.0, 0.0
    return 1000.0 / statistics.median(xs), xs[int(0.95 * (len(xs) - 1))]


def run(seconds: float = 6.0, chromium: str = "/usr/bin/chromium") -> dict[str, Any]:
    """Measure the figures above; returns them as a dict."""
    from playwright.sync_api import sync_playwright

    from cranetwin.viz.preview import ServerThread, create_preview_app

    end = time.time()
    app = create_preview_app(history_s=1800.0, end=end)
    out: dict[str, Any] = {"browser": "chromium (headless, swiftshader)", "server": "preview"}
    with ServerThread(app) as srv, sync_playwright() as p:
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
            pg.goto(f"{srv.url}/machines/crane-2?key=viewer-key&mode=replay"
                    f"&from={end - 600}&to={end}&t={end - 300}")
            pg.wait_for_function("window.cranetwin && window.cranetwin.ready", timeout=30000)
            paints.append(pg.evaluate("window.cranetwin.firstFrameMs"))
            ctx.close()
        out["first_paint_ms"] = statistics.median(paints)
        out["first_paint_all_ms"] = paints
        # replay of a 10-minute window
        for speed in (1, 16):
            page.goto(f"{srv.url}/machines/crane-2?key=viewer-key&mode=replay"
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
        page.goto(f"{srv.url}/machines/crane-1?key=viewer-key&mode=live")
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=30000)
        page.evaluate("window.cranetwin.liveLatencyMs = []")
        page.wait_for_timeout(int(seconds * 1000))
        lat = sorted(page.evaluate("window.cranetwin.liveLatencyMs"))
        out["live_frames"] = len(lat)
        out["live_p50_ms"] = lat[len(lat) // 2] if lat else None
        out["live_p95_ms"] = lat[int(0.95 * (len(lat) - 1))] if lat else None
        browser.close()
    return out


def register(bench_app: typer.Typer) -> None:
    """Add ``cranetwin bench web``."""

    @bench_app.command("web")
    def web(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        seconds: float = typer.Option(6.0, help="Measuring time per figure [s]."),
        chromium: str = typer.Option("/usr/bin/chromium", help="Chromium executable."),
    ) -> None:
        """Web UI: first paint, replay fps (10-min window), live latency in headless Chromium."""
        result = run(seconds, chromium)
        if as_json:
            typer.echo(json.dumps(result))
        else:
            for k, v in result.items():
                typer.echo(f"{k:32s} {v}")
