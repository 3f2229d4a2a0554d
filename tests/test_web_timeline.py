"""Browser tests of the machine page's timeline, channel picker, live joint loads and 3D aids,
and of the fleet map.

``create_app`` on a temporary SQLite database; crane-2 has two stretches of stored samples with a
200 s silence between them ([END-600, END-400] and [END-200, END]), the twin worker's derived
channels computed. Chromium (Debian's, headless, software WebGL) through Playwright; skipped with
a reason when either is missing.
"""

from __future__ import annotations

import shutil
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
END = float(int(time.time() - 3600) // 60 * 60)  # end of the stored data: a whole minute [s]
GAP = (END - 400, END - 200)  # no data in between [s]

pytestmark = [pytest.mark.browser]
if not Path(CHROMIUM).exists():
    pytestmark.append(pytest.mark.skip(reason="Chromium not installed (apt-get install chromium; "
                                              "`make system-deps` does it)"))
playwright_api = pytest.importorskip("playwright.sync_api",
                                     reason="playwright not installed (pip install -e '.[dev]')")


class Service:
    def __init__(self, url: str, app: Any, viewer: str) -> None:
        self.url, self.app, self.viewer = url, app, viewer


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    from cranetwin.api import create_app
    from cranetwin.api.preview import ServerThread
    from cranetwin.model import load_machine
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    url = f"sqlite:///{tmp_path_factory.mktemp('tl') / 'tl.db'}"
    app = create_app(Settings(database_url=url, worker_in_process=False))
    machine = load_machine("patu655")
    with ServerThread(app) as srv:
        services = app.state.services
        viewer = services.backend.create_key("viewer", "timeline tests")[1]
        admin = services.backend.create_key("admin", "timeline tests")[1]
        for i, (lat, lon) in ((1, (62.24, 25.75)), (2, (61.50, 23.79))):  # Jyväskylä, Tampere
            r = httpx.post(f"{srv.url}/api/v1/machines", headers={"X-API-Key": admin},
                           json={"machine_id": f"crane-{i}", "model": "patu655",
                                 "location": {"lat": lat, "lon": lon}})
            assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        store = services.backend.store
        store.write_blocks(list(tiled_blocks("crane-2", machine, END - 600, 200.0, 1.0,
                                             base=base)))
        store.write_blocks(list(tiled_blocks("crane-2", machine, END - 200, 200.0, 1.0,
                                             base=base, seq0=10_000, origin_s=END - 600)))
        TwinWorker(services.backend, services.settings, services.metrics,
                   services.fleet.replayer).catch_up(services.backend.machine("crane-2"))
        yield Service(str(srv.url), app, viewer)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture()
def page(browser: Any, server: Service) -> Iterator[Any]:
    from cranetwin.bench.web import sign_in

    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    sign_in(ctx, server.url, server.viewer)
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.errors = errors
    yield pg
    ctx.close()


def _open(page: Any, server: Service, t: float, extra: str = "") -> None:
    page.goto(f"{server.url}/machines/crane-2?mode=replay&from={END - 600}&to={END}&t={t}"
              + extra)
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {t}) < 0.01", timeout=20000)


def _view(page: Any) -> tuple[float, float]:
    a, b = page.evaluate("window.cranetwin.view")
    return float(a), float(b)


def _chart_range(page: Any) -> tuple[float, float]:
    """The charts' x-axis range [s] (plotly keeps dates as strings or ms)."""
    r = page.evaluate("(() => { const r = document.getElementById('charts')._fullLayout.xaxis"
                      ".range; const ms = (x) => typeof x === 'number' ? x :"
                      " Date.parse(String(x).replace(' ', 'T') + 'Z'); return r.map(ms); })()")
    return r[0] / 1000.0, r[1] / 1000.0


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_brush_on_timeline_and_chart_zooms_wheel_pans(page: Any, server: Service) -> None:
    _open(page, server, END - 100)
    page.wait_for_selector("#charts .main-svg", timeout=30000)
    assert _view(page) == (END - 600, END)
    box = page.locator("#timeline .tl-track").bounding_box()
    y = box["y"] + box["height"] / 2
    # brush from 25 % to 50 % of the strip: the view is [END-450, END-300]
    page.mouse.move(box["x"] + 0.25 * box["width"], y)
    page.mouse.down()
    page.mouse.move(box["x"] + 0.40 * box["width"], y, steps=4)
    page.mouse.move(box["x"] + 0.50 * box["width"], y, steps=4)
    page.mouse.up()
    a, b = _view(page)
    px = 600.0 / box["width"]  # one pixel [s]
    assert abs(a - (END - 450)) < 3 * px and abs(b - (END - 300)) < 3 * px, (a - END, b - END)
    # slider, charts and URL follow the view; the cursor moved into it
    assert abs(float(page.eval_on_selector("#slider", "(el) => el.max")) - (b - a)) < 0.05
    page.wait_for_function(f"(() => {{ const r = document.getElementById('charts')._fullLayout"
                           f".xaxis.range; const ms = (x) => typeof x === 'number' ? x :"
                           f" Date.parse(String(x).replace(' ', 'T') + 'Z');"
                           f" return Math.abs(ms(r[0]) / 1000 - {a}) < 0.5; }})()")
    ca, cb = _chart_range(page)
    assert abs(ca - a) < 0.5 and abs(cb - b) < 0.5, (ca - END, cb - END)
    assert a <= page.evaluate("window.cranetwin.cursor") <= b
    page.wait_for_function("window.location.search.includes('vfrom=')")
    # the wheel pans by a tenth of the view
    page.mouse.move(box["x"] + 0.4 * box["width"], y)
    page.mouse.wheel(0, 100)
    page.wait_for_function(f"window.cranetwin.view[0] > {a + 1}")
    a2, b2 = _view(page)
    assert abs((a2 - a) - 0.1 * (b - a)) < 0.5 and abs((b2 - a2) - (b - a)) < 0.01
    # brushing on a chart zooms too (x only): drag across the middle of the plot area
    plot = page.locator("#charts .nsewdrag").first.bounding_box()
    cy = plot["y"] + plot["height"] / 2
    page.mouse.move(plot["x"] + 0.2 * plot["width"], cy)
    page.mouse.down()
    page.mouse.move(plot["x"] + 0.4 * plot["width"], cy, steps=5)
    page.mouse.move(plot["x"] + 0.6 * plot["width"], cy, steps=5)
    page.mouse.up()
    page.wait_for_function(f"window.cranetwin.view[1] - window.cranetwin.view[0] < "
                           f"{0.6 * (b2 - a2)}")
    a3, b3 = _view(page)
    assert a2 + 0.1 * (b2 - a2) < a3 < b3 < b2 - 0.1 * (b2 - a2), (a3 - END, b3 - END)
    # "Whole range" resets
    page.click("#zoom-out")
    assert _view(page) == (END - 600, END)
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_frame_step_buttons_and_arrow_keys(page: Any, server: Service) -> None:
    t0 = END - 100
    _open(page, server, t0)
    page.wait_for_selector("#charts .main-svg", timeout=30000)

    def at(t: float) -> None:
        page.wait_for_function(f"Math.abs(window.cranetwin.cursor - {t}) < 1e-4"
                               f" && Math.abs(window.cranetwin.drawnT - {t}) < 1e-4",
                               timeout=10000)

    page.click("#frame-fwd")
    at(t0 + 0.04)
    page.click("#frame-fwd")
    at(t0 + 0.08)
    page.click("#frame-back")
    at(t0 + 0.04)
    page.locator("#slider").focus()
    page.keyboard.press("ArrowRight")
    page.keyboard.press("ArrowRight")
    at(t0 + 0.12)
    page.keyboard.press("ArrowLeft")
    at(t0 + 0.08)
    page.keyboard.press("Shift+ArrowRight")
    at(t0 + 1.08)
    # one time cursor: the 3D view's time, the timeline's marker and the charts' line agree
    page.keyboard.press("PageDown")
    at(t0 + 11.08)
    page.wait_for_timeout(300)
    px = page.evaluate("(() => { const fl = document.getElementById('charts')._fullLayout;"
                       " const xa = fl.xaxis; const c = document.querySelector('.chart-cursor');"
                       " const m = /translate\\(([-0-9.]+)px/.exec(c.style.transform);"
                       f" return [parseFloat(m[1]) - document.getElementById('charts').offsetLeft,"
                       f" xa._offset + xa.l2p({(t0 + 11.08) * 1000})]; }})()")
    assert abs(px[0] - px[1]) < 1.5, px
    left = page.evaluate("parseFloat(document.querySelector('.tl-cursor').style.left)")
    assert abs(left - 100 * (600 - 100 + 11.08) / 600) < 0.05
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_channel_picker_charts_any_channel_and_the_link_keeps_it(page: Any,
                                                                 server: Service) -> None:
    _open(page, server, END - 100)
    page.wait_for_selector("#charts .main-svg", timeout=30000)
    page.click("#channel-picker summary")
    names = page.eval_on_selector_all("#channel-list input", "(els) => els.map(e => e.value)")
    for want in ("lift_pA", "lift_s", "slew_torque", "force:lift", "payload", "moment:theta1",
                 "torque:theta1", "torque:L"):
        assert want in names, names
    page.eval_on_selector_all("#channel-list input", "(els) => { for (const e of els) e.checked ="
                              " false; els[0].dispatchEvent(new Event('change')); }")
    page.wait_for_function("document.getElementById('charts-msg').textContent"
                           ".includes('No channel')")
    for want in ("lift_s", "torque:theta1", "moment:theta2"):
        page.check(f"#channel-list input[value='{want}']")
    page.wait_for_function(
        "(() => { const d = document.getElementById('charts').data || [];"
        " const n = d.filter(t => t.name).map(t => t.name);"
        " return n.includes('lift_s') && n.includes('theta1') && n.includes('theta2')"
        " && n.length === 3; })()", timeout=20000)
    titles = page.evaluate("(() => { const fl = document.getElementById('charts')._fullLayout;"
                           " return Object.keys(fl).filter(k => /^yaxis\\d*$/.test(k))"
                           ".map(k => fl[k].title.text); })()")
    assert sorted(titles) == sorted(["Rod position [mm]", "Joint reaction moment [kN·m]",
                                     "Joint torque [kN·m]"]), titles
    # values are real: rod positions in mm of the stored samples (0 … stroke)
    ys = page.evaluate("document.getElementById('charts').data.find(t => t.name === 'lift_s').y")
    vals = [v for v in ys if v is not None]
    assert vals and 0 <= min(vals) < max(vals) <= 1000, (min(vals), max(vals))
    page.wait_for_function("window.location.search.includes('ch=')")
    link = page.url
    page.goto(link)
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)
    page.wait_for_function("(document.getElementById('charts').data || []).length > 0",
                           timeout=30000)
    checked = page.eval_on_selector_all("#channel-list input:checked",
                                        "(els) => els.map(e => e.value)")
    assert sorted(checked) == ["lift_s", "moment:theta2", "torque:theta1"]
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_preset_is_clamped_to_the_data_and_play_skips_the_silence(page: Any,
                                                                  server: Service) -> None:
    _open(page, server, END - 100)
    page.select_option("#preset", "3600")  # last hour; 10 min stored
    page.wait_for_function(f"Math.abs(window.cranetwin.view[0] - {END - 600}) < 1")
    assert "Only 10 min of data" in page.inner_text("#banner")
    page.wait_for_function("(window.cranetwin.coverage || []).length === 2", timeout=20000)
    cov = page.evaluate("window.cranetwin.coverage")
    assert cov[0][1] <= GAP[0] + 61 and cov[1][0] >= GAP[1] - 61, cov
    # play at 1× from 3 s before the silence: the cursor jumps over its 200 s
    page.locator("#slider").evaluate(
        f"(el) => {{ el.value = String({GAP[0] - 3} - window.cranetwin.view[0]);"
        " el.dispatchEvent(new Event('input')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {GAP[0] - 3}) < 0.05",
                           timeout=20000)
    page.keyboard.press("Space")
    page.wait_for_function(f"window.cranetwin.cursor > {GAP[1]}", timeout=30000)
    page.keyboard.press("Space")
    assert page.evaluate("window.cranetwin.gapsSkipped") >= 1
    t = page.evaluate("window.cranetwin.cursor")
    assert GAP[1] <= t < GAP[1] + 20, t - GAP[1]
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_chart_lines_stop_at_the_silence(page: Any, server: Service) -> None:
    """The load history has no buckets in the 200 s silence: every chart line breaks there
    (a null point) instead of joining the two stretches, and no min-max band spans it."""
    _open(page, server, END - 100)
    page.wait_for_function("(document.getElementById('charts').data || []).some(t => t.name"
                           " === 'lift')", timeout=30000)
    traces = page.evaluate("document.getElementById('charts').data.map(t => [t.name || '',"
                           " t.x, t.y])")
    assert len(traces) > 6
    bands = 0
    for name, xs, ys in traces:
        inside = [y for x, y in zip(xs, ys, strict=True) if GAP[0] + 5 < x / 1000 < GAP[1] - 5]
        assert all(y is None for y in inside), (name, inside[:5])
        if name:  # the mean line: one trace, broken by a null point
            assert inside and sum(y is not None for y in ys) > 100, name
        else:  # a band's edge: one stretch, on one side of the silence
            bands += 1
            assert max(xs) / 1000 < GAP[0] + 5 or min(xs) / 1000 > GAP[1] - 5, name
    assert bands == 4 * sum(1 for n, _, _ in traces if n)  # two stretches, two edges each
    assert not page.errors


class _Feeder:
    """Writes 0.2 s sample blocks stamped now for crane-1 (a live machine)."""

    def __init__(self, app: Any) -> None:
        from cranetwin.model import load_machine
        from cranetwin.testing.blocks import kinematic_samples

        self.app = app
        self.machine = load_machine("patu655")
        self.base = kinematic_samples(self.machine, 120.0)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        from cranetwin.testing.blocks import tiled_blocks

        store = self.app.state.services.backend.store
        seq = 1_000_000
        while not self.stop.is_set():
            blocks = list(tiled_blocks("crane-1", self.machine, round(time.time() - 0.2, 2),
                                       0.2, 0.2, base=self.base, seq0=seq))
            seq += len(blocks)
            store.write_blocks(blocks)
            self.stop.wait(0.2)


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_live_charts_include_joint_loads(page: Any, server: Service) -> None:
    feeder = _Feeder(server.app)
    feeder.thread.start()
    try:
        page.goto(f"{server.url}/machines/crane-1?mode=live")
        page.wait_for_function("window.cranetwin && window.cranetwin.liveFrames > 5",
                               timeout=30000)
        page.wait_for_function(
            "(() => { const fl = (document.getElementById('charts') || {})._fullLayout;"
            " if (!fl) return false; return Object.keys(fl).filter(k => /^yaxis\\d*$/.test(k))"
            ".some(k => fl[k].title.text === 'Joint torque [kN·m]')"
            " && (document.getElementById('charts').data || []).some(t => t.name === 'theta1'"
            " && t.y.length > 3); })()", timeout=30000)
        ys = page.evaluate("document.getElementById('charts').data"
                           ".find(t => t.name === 'theta1').y")
        # the lift joint carries the boom's weight: a real, non-zero moment [kN·m]
        assert max(abs(v) for v in ys if v is not None) > 1.0
    finally:
        feeder.stop.set()
        feeder.thread.join(5)
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_envelope_utilisation_and_camera_follow(page: Any, server: Service) -> None:
    """The 3D view's rated-load figures equal the machine's chart at the twin's reach and
    payload; the envelope lies in the slew plane of the load; Follow keeps the orbit target on
    the load."""
    import numpy as np

    from cranetwin.model import load_machine

    t = END - 100
    _open(page, server, t)
    page.wait_for_function("window.cranetwin.envelope && window.cranetwin.envelope.rated_kg > 0")
    env = page.evaluate("window.cranetwin.envelope")
    twin = page.request.get(f"{server.url}/api/v1/machines/crane-2/twin",
                            params={"from": t - 0.5, "to": t + 0.5, "rate_hz": 25}).json()
    i = int(np.argmin(np.abs(np.asarray(twin["t"]) - t)))
    tip = np.asarray(twin["tip"][i])
    kg = float(np.interp(t, twin["payload"]["t"], twin["payload"]["kg"]))
    machine = load_machine("patu655")
    reach = float(np.hypot(tip[0], tip[1]))  # patu655: vertical slew axis through the origin
    rated = float(machine.rated_load.payload_at(np.array([reach]))[0])
    assert abs(env["reach_m"] - reach) < 0.02, (env, reach)
    assert abs(env["rated_kg"] - rated) < 0.01 * rated, (env, rated)
    assert abs(env["utilisation"] - max(kg, 0) / rated) < 0.02, (env, kg / rated)
    assert f"{round(100 * env['utilisation'])} % of rated" in page.inner_text("#now-util")
    # the marker and curve lie in the vertical plane through the slew axis and the load
    pts = page.evaluate("(() => { const e = window.__crane.envelope; const p = e.curve.attributes"
                        ".position.array; return {m: e.marker.position.toArray(), c: Array.from(p),"
                        " visible: e.group.visible}; })()")
    assert pts["visible"]
    d = tip[:2] / np.linalg.norm(tip[:2])
    curve = np.asarray(pts["c"]).reshape(-1, 3)
    cross = curve[:, 0] * d[1] - curve[:, 1] * d[0]
    assert np.abs(cross).max() < 0.01  # [m]: at most 1 cm off the plane at 7 m reach
    assert abs(np.asarray(pts["m"])[:2] @ d - reach) < 0.02
    # the curve's height follows the chart: the largest rated payload at the shortest reach
    heights = curve[:, 2]
    assert heights.max() == pytest.approx(2.5, abs=1e-3)
    # camera follow: the orbit target is on the load after a seek (it was not before)
    before = np.asarray(page.evaluate("window.__crane.viewer.controls.target.toArray()"))
    assert np.linalg.norm(before - [tip[0], tip[2], -tip[1]]) > 0.5
    page.click("#follow")
    page.locator("#slider").focus()
    page.keyboard.press("PageDown")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {t + 10}) < 0.01")
    target = page.evaluate("window.__crane.viewer.controls.target.toArray()")
    twin2 = page.request.get(f"{server.url}/api/v1/machines/crane-2/twin",
                             params={"from": t + 9.5, "to": t + 10.5, "rate_hz": 25}).json()
    j = int(np.argmin(np.abs(np.asarray(twin2["t"]) - (t + 10))))
    p = np.asarray(twin2["tip"][j])
    # (the page interpolates its own 60 s chunk: within millimetres of this 1 s window's tip)
    assert np.allclose(target, [p[0], p[2], -p[1]], atol=0.01), (target, p)
    assert not page.errors


@pytest.mark.timeout(90)  # the first test also starts the module's server
def test_fleet_map_places_machines_offline_and_follows_the_filter(page: Any,
                                                                  server: Service) -> None:
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(f"{server.url}/")
    page.wait_for_function("window.cranetwin.mapReady === true && window.cranetwin.mapMarkers"
                           " === 2", timeout=30000)
    assert page.locator("#map path[data-country]").count() > 150
    # each marker sits inside Finland's outline (bounding box of its path on the map)
    fin = page.evaluate("(() => { const b = document.querySelector('#map path[data-country="
                        "\"Finland\"]').getBBox(); return [b.x, b.y, b.x + b.width,"
                        " b.y + b.height]; })()")
    for mid in ("crane-1", "crane-2"):
        c = page.locator(f".map-machine[data-machine-id='{mid}'] circle")
        x, y = float(c.get_attribute("cx")), float(c.get_attribute("cy"))
        assert fin[0] < x < fin[2] and fin[1] < y < fin[3], (mid, x, y, fin)
    # Jyväskylä is north-east of Tampere
    c1 = page.locator(".map-machine[data-machine-id='crane-1'] circle")
    c2 = page.locator(".map-machine[data-machine-id='crane-2'] circle")
    assert float(c1.get_attribute("cx")) > float(c2.get_attribute("cx"))
    assert float(c1.get_attribute("cy")) < float(c2.get_attribute("cy"))
    # the table's filter filters the map
    page.fill("#filter", "crane-1")
    page.wait_for_function("document.querySelectorAll('.map-machine').length === 1")
    assert page.locator("#rows tr").count() == 1
    page.hover("#rows tr[data-machine-id='crane-1']")
    assert page.locator(".map-machine.hl[data-machine-id='crane-1']").count() == 1
    page.fill("#filter", "")
    page.wait_for_function("document.querySelectorAll('.map-machine').length === 2")
    # nothing came from another host (basemap and its decoder are served with the page)
    assert all(u.startswith(server.url) for u in requests), [u for u in requests
                                                            if not u.startswith(server.url)]
    page.click(".map-machine[data-machine-id='crane-2'] circle")
    page.wait_for_url("**/machines/crane-2**")
    assert not page.errors
