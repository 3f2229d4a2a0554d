"""The compare page in Chromium: 2–4 machines side by side on one timeline.

``create_app`` on SQLite: crane-2 with 10 min of stored samples, crane-3 with only the first
5 min of the same range and its motion 30 s out of phase (so the two cranes differ at any time,
and one of them has no data in the second half), crane-4 with [END-600, END-400] and
[END-200, END] (so crane-3 and crane-4 are both silent in [END-300, END-200], and crane-4 alone
in [END-400, END-300]). Skipped with a reason when Chromium or Playwright is missing.
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
END = float(int(time.time() - 3600) // 60 * 60)

pytestmark = [pytest.mark.browser]
if not Path(CHROMIUM).exists():
    pytestmark.append(pytest.mark.skip(reason="Chromium not installed (apt-get install chromium; "
                                              "`make system-deps` does it)"))
playwright_api = pytest.importorskip("playwright.sync_api",
                                     reason="playwright not installed (pip install -e '.[dev]')")
Image = pytest.importorskip("PIL.Image", reason="Pillow needed for pixel checks")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, Any]]:
    from cranetwin.api import create_app
    from cranetwin.api.preview import ServerThread
    from cranetwin.model import load_machine
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    url = f"sqlite:///{tmp_path_factory.mktemp('cmp') / 'cmp.db'}"
    app = create_app(Settings(database_url=url, worker_in_process=False))
    machine = load_machine("patu655")
    with ServerThread(app) as srv:
        services = app.state.services
        viewer = services.backend.create_key("viewer", "compare tests")[1]
        admin = services.backend.create_key("admin", "compare tests")[1]
        for i in (2, 3, 4, 5, 6):  # 5, 6: no stored data (the live test sends theirs)
            r = httpx.post(f"{srv.url}/api/v1/machines", headers={"X-API-Key": admin},
                           json={"machine_id": f"crane-{i}", "model": "patu655",
                                 "name": f"Crane {i}"})
            assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        store = services.backend.store
        store.write_blocks(list(tiled_blocks("crane-2", machine, END - 600, 600.0, 1.0,
                                             base=base)))
        store.write_blocks(list(tiled_blocks("crane-3", machine, END - 600, 300.0, 1.0,
                                             base=base, origin_s=END - 630)))
        store.write_blocks(list(tiled_blocks("crane-4", machine, END - 600, 200.0, 1.0,
                                             base=base, seq0=0, origin_s=END - 660)))
        store.write_blocks(list(tiled_blocks("crane-4", machine, END - 200, 200.0, 1.0,
                                             base=base, seq0=10_000, origin_s=END - 660)))
        for mid in ("crane-2", "crane-3", "crane-4"):
            TwinWorker(services.backend, services.settings, services.metrics,
                       services.fleet.replayer).catch_up(services.backend.machine(mid))
        yield str(srv.url), str(viewer), app


@pytest.fixture()
def page(server: tuple[str, str, Any]) -> Iterator[Any]:
    from cranetwin.bench.web import sign_in

    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        ctx = b.new_context(viewport={"width": 1280, "height": 900})
        sign_in(ctx, server[0], server[1])
        pg = ctx.new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.errors = errors
        yield pg
        b.close()


def _boom_pixels(img: Any) -> int:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 140) & (g > 90) & (b < 90) & (r - b > 90)).sum())


def _shot(locator: Any, name: str) -> Any:
    ARTIFACTS.mkdir(exist_ok=True)
    png = locator.screenshot(path=str(ARTIFACTS / name))
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def _reach(url: str, page: Any, mid: str, t: float) -> float:
    twin = page.request.get(f"{url}/api/v1/machines/{mid}/twin",
                            params={"from": t - 0.5, "to": t + 0.5, "rate_hz": 25}).json()
    i = int(np.argmin(np.abs(np.asarray(twin["t"]) - t)))
    tip = np.asarray(twin["tip"][i])
    return float(np.hypot(tip[0], tip[1]))  # patu655: vertical slew axis through the origin


def _cells(page: Any) -> dict[str, Any]:
    return dict(page.evaluate("window.cranetwin.cells"))


@pytest.mark.timeout(180)
def test_two_cranes_replay_on_one_timeline(page: Any, server: tuple[str, str, Any]) -> None:
    url = server[0]
    t = END - 500
    page.goto(f"{url}/compare?machines=crane-2,crane-3&mode=replay&from={END - 600}&to={END}&t={t}")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    page.wait_for_function(f"Object.values(window.cranetwin.cells).every(c => c.drawnT !== null"
                           f" && Math.abs(c.drawnT - {t}) < 0.01)", timeout=30000)
    # both scenes drawn, each its own machine at the same time (30 s out of phase: they differ)
    for mid in ("crane-2", "crane-3"):
        img = _shot(page.locator(f".cmp-cell[data-machine-id={mid}]"), f"compare-{mid}.png")
        assert _boom_pixels(img) > 500, mid
    cells = _cells(page)
    r2, r3 = _reach(url, page, "crane-2", t), _reach(url, page, "crane-3", t)
    assert abs(r2 - r3) > 0.05
    assert abs(cells["crane-2"]["envelope"]["reach_m"] - r2) < 0.02
    assert abs(cells["crane-3"]["envelope"]["reach_m"] - r3) < 0.02
    assert "Crane 2" in page.inner_text(".cmp-cell[data-machine-id=crane-2] header")
    # one play clock: after playing at 4x both were drawn at the same, later time
    page.select_option("#speed", "4")
    page.click("#play")
    page.wait_for_timeout(2000)
    page.click("#play")
    page.wait_for_timeout(300)
    cursor = page.evaluate("window.cranetwin.cursor")
    cells = _cells(page)
    assert cursor > t + 2
    assert cells["crane-2"]["drawnT"] == pytest.approx(cursor, abs=1e-6)
    assert cells["crane-3"]["drawnT"] == pytest.approx(cursor, abs=1e-6)
    # the shared slider: in the second half crane-3 has no data, crane-2 goes on
    page.locator("#slider").fill(str(500.0))
    page.wait_for_function(f"Math.abs(window.cranetwin.cells['crane-2'].drawnT - {END - 100})"
                           " < 0.05", timeout=30000)
    page.wait_for_function("window.cranetwin.cells['crane-3'].state === 'empty'", timeout=30000)
    assert "no data" in page.inner_text(".cmp-cell[data-machine-id=crane-3] .cell-note")
    # frame step moves both by one 25 Hz frame; the link keeps machines and time
    page.locator("#slider").focus()
    page.keyboard.press("ArrowLeft")
    page.wait_for_function(f"Math.abs(window.cranetwin.cursor - {END - 100 - 0.04}) < 1e-6")
    link = page.url
    assert "machines=crane-2%2Ccrane-3" in link or "machines=crane-2,crane-3" in link
    assert f"t={END - 100 - 0.04:.2f}" in link and "key=" not in link
    assert not page.errors


@pytest.mark.timeout(120)
def test_fleet_compare_button_and_wrong_links(page: Any, server: tuple[str, str, Any]) -> None:
    url = server[0]
    page.goto(f"{url}/")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)
    assert page.is_disabled("#compare")
    page.check("tr[data-machine-id=crane-2] .compare-pick")
    assert page.is_disabled("#compare")  # one machine is no comparison
    page.check("tr[data-machine-id=crane-3] .compare-pick")
    assert page.inner_text("#compare") == "Compare (2)"
    assert "/machines/" not in page.url  # ticking a row does not open the machine
    page.click("#compare")
    page.wait_for_url("**/compare?machines=crane-2,crane-3**")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    assert page.locator(".cmp-cell").count() == 2
    # one machine, or an unknown one: said so
    page.goto(f"{url}/compare?machines=crane-2")
    page.wait_for_selector("#banner:not([hidden])")
    assert "2 to 4 machines" in page.inner_text("#banner")
    page.goto(f"{url}/compare?machines=crane-2,nope")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    assert "unknown machine" in page.inner_text(".cmp-cell[data-machine-id=nope] .cell-note")
    assert not page.errors


GAP_ALL = (END - 300, END - 200)  # neither crane-3 nor crane-4 has data [s]


def _open_pair(page: Any, url: str, t: float, extra: str = "") -> None:
    page.goto(f"{url}/compare?machines=crane-3,crane-4&mode=replay&from={END - 600}&to={END}"
              f"&t={t}{extra}")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    page.wait_for_function("window.cranetwin.coverage.length > 0", timeout=30000)


@pytest.mark.timeout(120)
def test_compare_play_skips_only_what_all_machines_miss(page: Any,
                                                        server: tuple[str, str, Any]) -> None:
    url = server[0]
    # the union of where either machine has data: one silence, where both are silent
    _open_pair(page, url, END - 402)
    cov = page.evaluate("window.cranetwin.coverage")
    assert len(cov) == 2, cov
    assert cov[0][1] <= GAP_ALL[0] + 61 and cov[1][0] >= GAP_ALL[1] - 61, cov
    # from the samples (a raw channel), not from what the twin worker derived so far: the last
    # minute, not processed yet, is covered too
    assert cov[0][0] <= END - 598 and cov[1][1] >= END - 2, (cov[0][0] - END, cov[1][1] - END)
    page.wait_for_function("Object.values(window.cranetwin.cells).every(c => c.drawnT !== null)",
                           timeout=30000)
    # crane-4 alone falls silent at END-400: play runs on through it at 1×, no jump
    page.keyboard.press("Space")
    page.wait_for_timeout(2500)
    page.keyboard.press("Space")
    t = page.evaluate("window.cranetwin.cursor")
    assert END - 402 < t < END - 394, t - END
    assert page.evaluate("window.cranetwin.gapsSkipped") == 0
    # there crane-4 says "no data" (it does not hold its last pose), crane-3 is drawn
    page.locator("#slider").evaluate(
        f"(el) => {{ el.value = String({END - 390} - window.cranetwin.view.a);"
        " el.dispatchEvent(new Event('input')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.cells['crane-3'].drawnT - {END - 390})"
                           " < 0.05", timeout=30000)
    page.wait_for_function("window.cranetwin.cells['crane-4'].state === 'empty'", timeout=30000)
    assert "no data" in page.inner_text(".cmp-cell[data-machine-id=crane-4] .cell-note")
    # both silent after END-300: play jumps over the 100 s to where crane-4 resumes
    page.locator("#slider").evaluate(
        f"(el) => {{ el.value = String({GAP_ALL[0] - 3} - window.cranetwin.view.a);"
        " el.dispatchEvent(new Event('input')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.cursor - {GAP_ALL[0] - 3}) < 0.05")
    page.keyboard.press("Space")
    page.wait_for_function(f"window.cranetwin.cursor > {GAP_ALL[1]}", timeout=30000)
    page.keyboard.press("Space")
    t = page.evaluate("window.cranetwin.cursor")
    assert GAP_ALL[1] <= t < GAP_ALL[1] + 20, t - GAP_ALL[1]
    assert page.evaluate("window.cranetwin.gapsSkipped") >= 1
    page.wait_for_function("Math.abs(window.cranetwin.cells['crane-4'].drawnT - "
                           "window.cranetwin.cursor) < 1e-6", timeout=30000)
    assert not page.errors


def _chart_traces(page: Any, mid: str) -> dict[str, list[float | None]]:
    return dict(page.evaluate(
        f"Object.fromEntries((document.querySelector('.cmp-charts[data-machine-id={mid}] .charts')"
        ".data || []).filter(t => t.name).map(t => [t.name, t.y]))"))


def _chart_cursor_px(page: Any, mid: str, t: float) -> tuple[float, float]:
    """Where the cell's chart cursor is, and where time ``t`` is on its x axis [px]."""
    px = page.evaluate(
        f"(() => {{ const d = document.querySelector('.cmp-charts[data-machine-id={mid}] .charts');"
        " const xa = d._fullLayout.xaxis; const c = d.parentElement.querySelector('.chart-cursor');"
        " const m = /translate\\(([-0-9.]+)px/.exec(c.style.transform);"
        f" return [parseFloat(m[1]) - d.offsetLeft, xa._offset + xa.l2p({t * 1000})]; }})()")
    return float(px[0]), float(px[1])


@pytest.mark.timeout(120)
def test_compare_charts_per_machine_on_the_shared_cursor(page: Any,
                                                         server: tuple[str, str, Any]) -> None:
    url = server[0]
    t = END - 500
    page.goto(f"{url}/compare?machines=crane-2,crane-3&mode=replay&from={END - 600}&to={END}"
              f"&t={t}")
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    for mid in ("crane-2", "crane-3"):
        page.wait_for_function(
            f"(document.querySelector('.cmp-charts[data-machine-id={mid}] .charts').data || [])"
            ".some(t => t.name === 'lift')", timeout=30000)
    # each machine's own history: cylinder forces [kN] that differ (30 s out of phase)
    f2, f3 = _chart_traces(page, "crane-2"), _chart_traces(page, "crane-3")
    assert {"payload", "lift"} <= set(f2) and {"payload", "lift"} <= set(f3), (f2.keys(), f3.keys())
    v2 = [v for v in f2["lift"] if v is not None]
    v3 = [v for v in f3["lift"] if v is not None]
    assert v2 and v3 and max(abs(v) for v in v2) > 1.0  # [kN]: the boom's weight
    assert v2[: len(v3) // 2] != v3[: len(v3) // 2]
    # crane-3 has no data in the second half: its chart ends there, crane-2's does not
    xs3 = page.evaluate("document.querySelector('.cmp-charts[data-machine-id=crane-3] .charts')"
                        ".data.find(t => t.name === 'lift').x")
    assert max(xs3) / 1000 <= END - 300 + 61
    # one cursor: both charts' lines are at the 3D views' time
    page.locator("#slider").focus()
    page.keyboard.press("Shift+ArrowRight")
    page.wait_for_function(f"Math.abs(window.cranetwin.cursor - {t + 1}) < 1e-6")
    page.wait_for_timeout(300)
    for mid in ("crane-2", "crane-3"):
        at, want = _chart_cursor_px(page, mid, t + 1)
        assert abs(at - want) < 1.5, (mid, at, want)
    # a brush on one machine's chart zooms the shared view; the other chart follows
    plot = page.locator(".cmp-charts[data-machine-id=crane-2] .nsewdrag").first.bounding_box()
    cy = plot["y"] + plot["height"] / 2
    page.mouse.move(plot["x"] + 0.3 * plot["width"], cy)
    page.mouse.down()
    page.mouse.move(plot["x"] + 0.45 * plot["width"], cy, steps=5)
    page.mouse.move(plot["x"] + 0.6 * plot["width"], cy, steps=5)
    page.mouse.up()
    page.wait_for_function("window.cranetwin.view.b - window.cranetwin.view.a < 400")
    view = page.evaluate("window.cranetwin.view")
    page.wait_for_function(
        "(() => { const r = document.querySelector('.cmp-charts[data-machine-id=crane-3] .charts')"
        "._fullLayout.xaxis.range; const ms = (x) => typeof x === 'number' ? x :"
        " Date.parse(String(x).replace(' ', 'T') + 'Z');"
        f" return Math.abs(ms(r[0]) / 1000 - {view['a']}) < 0.5"
        f" && Math.abs(ms(r[1]) / 1000 - {view['b']}) < 0.5; }})()", timeout=10000)
    # the channel picker of one machine: a joint torque chart for crane-3 only
    page.click(".cmp-charts[data-machine-id=crane-3] .channel-picker summary")
    page.check(".cmp-charts[data-machine-id=crane-3] .channel-list input[value='torque:theta1']")
    page.wait_for_function(
        "(document.querySelector('.cmp-charts[data-machine-id=crane-3] .charts').data || [])"
        ".some(t => t.name === 'theta1')", timeout=20000)
    assert "theta1" not in _chart_traces(page, "crane-2")
    # the link keeps the charted channels, one list for every machine
    page.wait_for_function("window.location.search.includes('ch=')")
    page.goto(page.url)
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=60000)
    for mid in ("crane-2", "crane-3"):
        page.wait_for_function(
            f"(document.querySelector('.cmp-charts[data-machine-id={mid}] .charts').data || [])"
            ".some(t => t.name === 'theta1')", timeout=30000)
        assert {"lift", "payload", "theta1"} <= set(_chart_traces(page, mid))
    assert not page.errors


@pytest.mark.timeout(120)
def test_compare_live_charts_per_machine(page: Any, server: tuple[str, str, Any]) -> None:
    """Live: each machine's frames reach its own 3D view and its own rolling charts (cylinder
    forces from the live stream, not the stored history)."""
    import threading

    from cranetwin.model import load_machine
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    store = server[2].state.services.backend.store
    stop = threading.Event()
    origin = round(time.time(), 2)

    def feed() -> None:
        seq = 0
        while not stop.is_set():
            now = round(time.time() - 0.2, 2)
            for k, mid in enumerate(("crane-5", "crane-6")):
                # continuous motion; crane-6 30 s out of phase, so the two charts differ
                store.write_blocks(list(tiled_blocks(mid, machine, now, 0.2, 0.2, base=base,
                                                     seq0=seq, origin_s=origin - 30 * k)))
            seq += 1
            stop.wait(0.2)

    th = threading.Thread(target=feed, daemon=True)
    th.start()
    try:
        page.goto(f"{server[0]}/compare?machines=crane-5,crane-6&mode=live")
        page.wait_for_function("window.cranetwin && window.cranetwin.mode === 'live' && Object"
                               ".values(window.cranetwin.cells).every(c => c.liveFrames > 5)",
                               timeout=60000)
        for mid in ("crane-5", "crane-6"):
            page.wait_for_function(
                f"(document.querySelector('.cmp-charts[data-machine-id={mid}] .charts').data"
                " || []).some(t => t.name === 'lift' && t.y.length > 3)", timeout=30000)
        f5, f6 = _chart_traces(page, "crane-5"), _chart_traces(page, "crane-6")
        assert {"lift", "payload"} <= set(f5) and {"lift", "payload"} <= set(f6)
        assert max(abs(v) for v in f5["lift"] if v is not None) > 1.0  # [kN]
        assert f5["lift"][:3] != f6["lift"][:3]
    finally:
        stop.set()
        th.join(5)
    assert not page.errors
