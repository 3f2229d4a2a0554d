"""Browser tests: Playwright (Python) driving Debian's Chromium against the real service.

``create_app`` on a temporary SQLite database: three registered cranes, ten minutes of exact
kinematic samples stored for crane-2 (the twin worker's derived summaries computed), crane-1 fed
"live" by writing samples to the store during a test. Skipped with a reason when Chromium or
Playwright is missing. Screenshots go to tests/artifacts/.
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
END = float(int(time.time() - 3600) // 60 * 60)  # end of the stored range: a whole minute [s]
SPAN = 600.0

pytestmark = [pytest.mark.browser]
if not Path(CHROMIUM).exists():
    pytestmark.append(pytest.mark.skip(reason="Chromium not installed (apt-get install chromium; "
                                              "`make system-deps` does it)"))
playwright_api = pytest.importorskip("playwright.sync_api",
                                     reason="playwright not installed (pip install -e '.[dev]')")
Image = pytest.importorskip("PIL.Image", reason="Pillow needed for pixel checks")


class Service:
    """The running app, its keys and a way to reach its store."""

    def __init__(self, srv: Any, app: Any, viewer: str, fleet: str) -> None:
        self.srv, self.app, self.viewer, self.fleet = srv, app, viewer, fleet

    @property
    def url(self) -> str:
        return str(self.srv.url)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    from cranetwin.api import create_app
    from cranetwin.api.preview import ServerThread
    from cranetwin.model import load_machine
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    url = f"sqlite:///{tmp_path_factory.mktemp('web') / 'web.db'}"
    app = create_app(Settings(database_url=url, worker_in_process=False))
    machine = load_machine("patu655")
    with ServerThread(app) as srv:
        services = app.state.services
        viewer = services.backend.create_key("viewer", "web tests")[1]
        admin = services.backend.create_key("admin", "web tests")[1]
        fleet = services.backend.create_key("fleet", "web tests")[1]
        for i in (1, 2, 3):
            r = httpx.post(f"{srv.url}/api/v1/machines", headers={"X-API-Key": admin},
                           json={"machine_id": f"crane-{i}", "model": "patu655",
                                 "name": f"Crane {i}"})
            assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        services.backend.store.write_blocks(list(tiled_blocks("crane-2", machine, END - SPAN,
                                                              SPAN, 1.0, base=base)))
        TwinWorker(services.backend, services.settings, services.metrics,
                   services.fleet.replayer).catch_up(services.backend.machine("crane-2"))
        yield Service(srv, app, viewer, fleet)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


def _sign_in(ctx: Any, server: Service, key: str | None = None) -> None:
    """The browser context signs in once (POST /api/v1/session); pages carry only the cookie."""
    from cranetwin.bench.web import sign_in

    sign_in(ctx, server.url, key or server.viewer)


@pytest.fixture()
def page(browser: Any, server: Service) -> Iterator[Any]:
    ctx = browser.new_context(viewport={"width": 1280, "height": 860})
    _sign_in(ctx, server)
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


def _wait_ready(page: Any) -> None:
    page.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)


def _boom_pixels(img: Any) -> Any:
    """Mask of the booms' yellow (#f2b01e, shaded) in an RGB image."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 140) & (g > 90) & (b < 90) & (r - b > 90)


def test_fleet_page_lists_machines(page: Any, server: Service) -> None:
    page.goto(f"{server.url}/")
    _wait_ready(page)
    rows = page.locator("#rows tr")
    assert rows.count() == 3
    text = page.locator("#rows").inner_text()
    for name in ("Crane 1", "Crane 2", "Crane 3"):
        assert name in text
    assert "offline" in page.locator("tr[data-machine-id=crane-3]").inner_text()
    assert "never" in page.locator("tr[data-machine-id=crane-3]").inner_text()
    assert "ago" in page.locator("tr[data-machine-id=crane-2]").inner_text()  # its data: 1 h ago
    assert "key=" not in page.url  # the key is remembered, not left in the address bar
    _shot(page, "fleet.png")
    page.locator("tr[data-machine-id=crane-1] a").click()
    page.wait_for_url("**/machines/crane-1**")
    assert not page.errors


@pytest.mark.timeout(60)
def test_sign_in_once_then_cookie_only(browser: Any, server: Service) -> None:
    """No key: the sign-in dialog. A wrong key says why and keeps the dialog; the right one
    becomes an HttpOnly, SameSite=Strict cookie that pages, REST calls and the live websocket
    carry (no key in any URL, in localStorage or readable by scripts); sign-out ends it."""
    ctx = browser.new_context()
    pg = ctx.new_page()
    urls: list[str] = []
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.on("request", lambda r: urls.append(r.url))
    pg.on("websocket", lambda ws: urls.append(ws.url))
    pg.goto(f"{server.url}/")
    pg.wait_for_selector("#key-dialog[open]", timeout=10000)
    pg.fill("#key-input", server.viewer[:-4] + "XXXX")
    pg.click("#key-form button")
    pg.wait_for_selector("#key-error:not([hidden])", timeout=10000)
    assert "not accepted" in pg.inner_text("#key-error")
    assert pg.locator("#key-dialog[open]").count() == 1
    pg.fill("#key-input", server.viewer)
    pg.click("#key-form button")
    pg.wait_for_function("window.cranetwin.ready === true", timeout=10000)
    assert pg.locator("#rows tr").count() == 3
    pg.wait_for_function("document.getElementById('who').textContent.includes('viewer')")
    cookie = {c["name"]: c for c in ctx.cookies()}["cranetwin_session"]
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict"
    assert server.viewer not in cookie["value"]
    assert "cranetwin_session" not in pg.evaluate("document.cookie")
    assert pg.evaluate("JSON.stringify(Object.assign({}, localStorage))") == "{}"
    # another page of the site, live: the websocket is authenticated by the cookie
    pg.goto(f"{server.url}/machines/crane-1?mode=live")
    pg.wait_for_function("window.cranetwin && window.cranetwin.mode === 'live'"
                         " && window.cranetwin.sceneMs !== null", timeout=30000)
    pg.wait_for_function("document.getElementById('who').textContent.includes('viewer')")
    assert any("/live" in u and u.startswith("ws") for u in urls), urls
    assert pg.locator("#key-dialog[open]").count() == 0
    assert not [u for u in urls if "key=" in u or server.viewer in u], urls
    # sign out: the cookie is gone, the next page asks again
    pg.click("#sign-out")
    pg.wait_for_selector("#key-dialog[open]", timeout=10000)
    assert "Signed out" in pg.inner_text("#key-note")
    assert "cranetwin_session" not in {c["name"] for c in ctx.cookies()}
    pg.goto(f"{server.url}/")
    pg.wait_for_selector("#key-dialog[open]", timeout=10000)
    assert not errors
    ctx.close()


@pytest.mark.timeout(90)
def test_address_bar_share_link_and_export_never_hold_the_key(browser: Any, server: Service,
                                                              tmp_path: Path) -> None:
    """Signed in through the dialog, a user goes fleet → machine → replay → seek → share →
    export → back: every address the page shows (each navigation and history entry), every
    request, the share link and the exported file (its text and the data it embeds) are free of
    the key."""
    ctx = browser.new_context(accept_downloads=True)
    pg = ctx.new_page()
    addresses: list[str] = []
    requests: list[str] = []
    pg.on("framenavigated", lambda f: addresses.append(f.url))
    pg.on("request", lambda r: requests.append(r.url))
    pg.on("websocket", lambda ws: requests.append(ws.url))
    pg.goto(f"{server.url}/")
    pg.wait_for_selector("#key-dialog[open]", timeout=10000)
    pg.fill("#key-input", server.fleet)
    pg.click("#key-form button")
    pg.wait_for_function("window.cranetwin.ready === true", timeout=15000)
    addresses.append(pg.url)
    pg.locator("tr[data-machine-id=crane-2] a").click()
    pg.wait_for_url("**/machines/crane-2**")
    pg.goto(f"{server.url}/machines/crane-2?mode=replay&from={END - 600}&to={END}"
            f"&t={END - 300}")
    _wait_ready(pg)
    pg.keyboard.press("PageDown")
    pg.wait_for_function(f"Math.abs(window.cranetwin.cursor - {END - 290}) < 0.01")
    addresses.append(pg.url)  # the replaced (replaceState) address
    pg.click("#share")
    pg.wait_for_function("document.getElementById('banner').textContent.includes('/machines/')")
    share = pg.inner_text("#banner")
    with pg.expect_download(timeout=60000) as info:
        pg.click("#export")
    path = tmp_path / "export.html"
    info.value.save_as(str(path))
    html = path.read_text()
    pg.go_back()
    addresses.append(pg.url)
    history = pg.evaluate("performance.getEntriesByType('navigation').map(e => e.name)")
    # the exported file: its text and its embedded (compressed) data
    off = ctx.new_page()
    off.goto(path.as_uri())
    off.wait_for_function("window.cranetwin && window.cranetwin.ready === true", timeout=30000)
    embedded = off.evaluate("JSON.stringify(window.CRANETWIN_EMBED)")
    assert "crane-2" in embedded and len(embedded) > 10000
    for what, texts in (("address", addresses), ("request", requests), ("history", history),
                        ("share link", [share]), ("export", [html, embedded])):
        for text in texts:
            assert server.fleet not in text and server.viewer not in text, (what, text[:200])
            assert "key=" not in text, (what, text[:200])
            assert "ctk_" not in text, (what, text[:200])
    assert len(addresses) >= 4 and any("t=" in a for a in addresses), addresses
    ctx.close()


@pytest.mark.timeout(30)
def test_a_key_in_an_old_link_is_exchanged_and_removed(browser: Any, server: Service) -> None:
    ctx = browser.new_context()
    pg = ctx.new_page()
    pg.goto(f"{server.url}/?key={server.viewer}")
    pg.wait_for_function("window.cranetwin.ready === true", timeout=10000)
    assert "key=" not in pg.url
    assert "cranetwin_session" in {c["name"] for c in ctx.cookies()}
    ctx.close()


def _replay(page: Any, server: Service, t: float, key: str | None = None) -> None:
    if key is not None:
        _sign_in(page.context, server, key)
    page.goto(f"{server.url}/machines/crane-2?mode=replay"
              f"&from={END - 600}&to={END}&t={t}")
    _wait_ready(page)
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {t}) < 0.01")
    page.wait_for_timeout(300)


def test_3d_view_draws_the_crane(page: Any, server: Service) -> None:
    _replay(page, server, END - 300)
    img = _shot(page.locator("#view3d"), "machine-3d.png")
    _shot(page, "machine-page.png")
    boom = _boom_pixels(img)
    # non-blank: the booms cover a real part of the view, and the picture is not one colour
    assert boom.mean() > 0.005, f"boom pixels {boom.mean():.4f}"
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 200
    assert not page.errors


def test_slider_moves_the_boom(page: Any, server: Service) -> None:
    _replay(page, server, END - 600)
    a = _shot(page.locator("#view3d"), "slider-a.png")
    slider = page.locator("#slider")
    slider.focus()
    # keyboard: move 10 s forward (PageDown), the boom moves
    page.keyboard.press("PageDown")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 590}) < 0.01")
    page.wait_for_timeout(300)
    b = _shot(page.locator("#view3d"), "slider-b.png")
    # and dragging the slider (input event) to another time
    slider.evaluate("(el) => { el.value = '200'; el.dispatchEvent(new Event('input'));"
                    " el.dispatchEvent(new Event('change')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 400}) < 0.01")
    page.wait_for_timeout(300)
    c = _shot(page.locator("#view3d"), "slider-c.png")
    for x, y in ((a, b), (b, c)):
        changed = np.abs(x - y).sum(axis=2) > 60
        assert changed.mean() > 0.002, f"only {changed.mean():.4f} of the pixels changed"
        # what moved is the crane: boom pixels appear or disappear
        assert (_boom_pixels(x) ^ _boom_pixels(y)).sum() > 50
    # the share link carries the time
    assert f"t={END - 400:.2f}" in page.url
    assert not page.errors


def test_play_advances_and_charts_follow(page: Any, server: Service) -> None:
    _replay(page, server, END - 500)
    page.wait_for_selector("#charts .main-svg", timeout=20000)
    page.select_option("#speed", "4")
    page.keyboard.press("Space")
    page.wait_for_timeout(1500)
    page.keyboard.press("Space")
    t = page.evaluate("window.cranetwin.cursor")
    assert END - 500 + 3 < t < END - 500 + 10, t  # ~4 s/s for ~1.5 s
    cursor_style = page.locator(".chart-cursor").evaluate("(el) => el.style.display")
    assert cursor_style == "block"
    assert "speed=4" in page.url
    assert not page.errors


def test_live_updates_within_a_second(page: Any, server: Service) -> None:
    """Samples stored now reach the page through the API's live websocket within a second."""
    from cranetwin.model import load_machine
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    machine = load_machine("patu655")
    base = kinematic_samples(machine, 120.0)
    store = server.app.state.services.backend.store
    page.goto(f"{server.url}/machines/crane-1?mode=live")
    page.wait_for_function("window.cranetwin && window.cranetwin.mode === 'live'"
                           " && window.cranetwin.sceneMs !== null", timeout=30000)
    page.wait_for_timeout(1000)
    latencies = []
    seq = 500_000
    start = 0.0
    for k in range(4):
        # whole seconds (sample-aligned block starts), each second once: storage refuses samples
        # whose times overlap stored ones
        start = max(float(int(time.time())), start + 1.0)
        blocks = list(tiled_blocks("crane-1", machine, start, 1.0, 1.0, base=base, seq0=seq))
        seq += len(blocks)
        sent = time.time()
        store.write_blocks(blocks)
        page.wait_for_function("window.cranetwin.lastLiveT !== null && "
                               f"window.cranetwin.lastLiveT >= {start + 0.9}", timeout=3000)
        latencies.append(time.time() - sent)
        if k == 0:  # first frame drawn: the page now loads its charts library; let it settle
            page.wait_for_selector("#charts .main-svg", timeout=20000)
            page.wait_for_timeout(1500)
    _shot(page, "live.png")
    assert max(latencies[1:]) < 1.0, latencies
    # no more samples: the page says so
    page.wait_for_function("document.getElementById('banner').textContent.includes('No live data')",
                           timeout=10000)
    assert not page.errors


def test_unknown_machine_says_so(page: Any, server: Service) -> None:
    page.goto(f"{server.url}/machines/nope")
    page.wait_for_function("document.getElementById('banner').textContent.includes('Unknown')")


def test_exported_file_replays_offline(page: Any, server: Service, tmp_path: Path) -> None:
    r = httpx.get(f"{server.url}/api/v1/machines/crane-2/export.html",
                  params={"from": END - 60, "to": END}, headers={"X-API-Key": server.viewer},
                  timeout=60.0)
    assert r.status_code == 200
    f = tmp_path / "replay.html"
    f.write_bytes(r.content)
    # block every network request: the file must not need any
    page.route("http://**", lambda route: route.abort())
    page.goto(f.as_uri())
    _wait_ready(page)
    img = _shot(page.locator("#view3d"), "export-3d.png")
    assert _boom_pixels(img).mean() > 0.005
    page.keyboard.press("PageDown")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 50}) < 0.01")
    page.wait_for_selector("#charts .main-svg", timeout=20000)
    assert not page.errors


def _verdicts_shown(page: Any) -> dict[str, dict[str, str | None]]:
    """Per cylinder row of the Now card: the visible badges' text and title (None: no badge)."""
    return page.evaluate("""() => {
      const out = {};
      for (const c of window.__crane.spec.cylinders) {
        const seen = (id) => { const el = document.getElementById(id);
          return el && el.checkVisibility()
          ? el.textContent.replace(/\u00a0/g, ' ') + ' | ' + el.title : null; };
        out[c] = {obs: seen('fo-' + c), con: seen('fc-' + c)};
      }
      return out; }""")


def _notes_shown(page: Any) -> list[str]:
    return page.evaluate("() => { const l = document.getElementById('force-notes');"
                         " return l.checkVisibility() ? [...l.children].map((li) =>"
                         " li.textContent) : []; }")


def test_force_rows_flag_what_the_pressures_cannot_resolve(page: Any, server: Service) -> None:
    """The first minute's twin results say the first cylinder's force is not observable (noise
    share), the second's pressures disagree with the motion and the third's constant force is
    not observable either (systematic floor) — the service's answers rewritten on the way: those
    badges carry the reason, a short line each says it, no other badge is shown; a later minute
    whose verdicts are all fine shows none."""
    import json
    from urllib.parse import parse_qs, urlparse

    cyls: list[str] = []

    def rewrite(route: Any) -> None:
        resp = route.fetch()
        body = resp.json()
        if "cylinder_forces" not in body:  # a refused window: as it is
            route.fulfill(response=resp)
            return
        frm = float(parse_qs(urlparse(route.request.url).query)["from"][0])
        names = list(body["cylinder_forces"])
        cyls[:] = names
        first = frm < END - 540
        body["force_observability"] = [
            {"cylinder": c, "sigma_n": 1520.0, "source": "estimated noise", "range_n": 4000.0,
             "share": 0.38, "observable": not (first and k == 0), "systematic_n": 0.0,
             "systematic_share": 0.0,
             "causes": ["noise share", "flat pressures"] if first and k == 0 else []}
            for k, c in enumerate(names)]
        if first:  # the third: a constant force, with a floor from the stated accuracy
            body["force_observability"][2].update(
                source="stated accuracy", range_n=0.0, share=None, observable=False,
                systematic_n=120.0, systematic_share=None, causes=["systematic floor"])
        body["model_consistency"] = [
            {"cylinder": c, "typical_n": 2500.0, "residual_rms_n": 2600.0, "raw_rms_n": 3000.0,
             "range_n": 9000.0, "level_n": 10000.0, "share": 0.25, "noise_n": 300.0,
             "noise_ratio": 8.33, "consistent": not (first and k == 1), "c_a": 1.9,
             "c_b": 1.8, "r2": 0.9,
             "hint": "swapped chambers (p_A and p_B exchanged)" if first and k == 1 else None}
            for k, c in enumerate(names)]
        route.fulfill(response=resp, body=json.dumps(body),
                      headers={**resp.headers, "content-type": "application/json"})

    page.route("**/api/v1/machines/crane-2/twin?*", rewrite)
    _replay(page, server, END - 570)
    page.wait_for_function("document.getElementById('force-notes').children.length === 3",
                           timeout=20000)
    a, b, c3 = cyls
    shown = _verdicts_shown(page)
    obs = shown[a]["obs"]
    assert obs is not None and obs.startswith("± not resolved | ")
    assert ("a: force not resolved (noise share, flat pressures): pressure error ±1.5 kN "
            "(1σ, estimated noise) against a force range of 4.0 kN (38 %; limit 10 %)"
            ).replace("a:", f"{a}:", 1) in obs
    con = shown[b]["con"]
    assert con is not None and con.startswith("≠ model | ")
    assert "force residual 2.5 kN = 25 % of the force the motion needs (10.0 kN RMS; " in con
    assert "8.3× what sensor noise explains" in con and "likely swapped chambers" in con
    assert shown[c3] == {"obs": (
        "± not resolved | extension: force not resolved (systematic floor): pressure error "
        "±1.5 kN (1σ, stated accuracy) against a force that does not change in this window; "
        "systematic floor ±120 N (stated accuracy beyond the noise) (limit 4 %)"
        ).replace("extension:", f"{c3}:", 1), "con": None}
    assert shown[a]["con"] is None and shown[b]["obs"] is None
    notes = _notes_shown(page)
    assert notes == [
        f"{a}: force not resolved (noise share, flat pressures): error ±1.5 kN against a "
        "4.0 kN range (38 %)",
        f"{b}: pressures disagree with the motion: residual 2.5 kN = 25 % of the force needed, "
        "8.3× the noise; likely swapped chambers (p_A and p_B exchanged)",
        f"{c3}: force not resolved (systematic floor): error ±1.5 kN, systematic floor ±120 N "
        "on a force that does not change here"]
    _shot(page.locator(".side .card").first, "force-verdicts.png")
    # a later minute: every force resolved and consistent, no badge, no note
    page.locator("#slider").evaluate("(el) => { el.value = '570';"
                                     " el.dispatchEvent(new Event('input')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 30}) < 0.01",
                           timeout=20000)
    page.wait_for_function("document.getElementById('force-notes').hidden", timeout=20000)
    assert all(v == {"obs": None, "con": None} for v in _verdicts_shown(page).values())
    assert _notes_shown(page) == []
    assert not page.errors


def test_force_rows_agree_with_the_services_verdicts(page: Any, server: Service) -> None:
    """Unaltered: a row carries the badge exactly when the twin result of the minute at the
    cursor marks that cylinder's force not observable (or its pressures inconsistent)."""
    r = httpx.get(f"{server.url}/api/v1/machines/crane-2/twin",
                  params={"from": END - 300, "to": END - 240 + 1 / 25, "rate_hz": 25},
                  headers={"X-API-Key": server.viewer}, timeout=60.0)
    assert r.status_code == 200, r.text
    body = r.json()
    want = {v["cylinder"]: v["observable"] for v in body["force_observability"]}
    agree = {v["cylinder"]: v["consistent"] for v in body["model_consistency"]}
    assert set(want) == set(body["cylinder_forces"])
    _replay(page, server, END - 290)
    page.wait_for_function("window.cranetwin.drawnT !== null && document.getElementById"
                           "('force-rows').children.length > 0")
    page.wait_for_timeout(500)
    shown = _verdicts_shown(page)
    assert {c: v["obs"] is None for c, v in shown.items()} == want
    assert {c: v["con"] is None for c, v in shown.items()} == {c: agree.get(c, True)
                                                               for c in shown}
    assert len(_notes_shown(page)) == sum(not ok for ok in want.values()) + sum(
        not ok for ok in agree.values())
    assert not page.errors


def test_the_first_seconds_window_says_nothing_about_the_forces(page: Any,
                                                               server: Service) -> None:
    """The crane is drawn from a one-second window before its minute arrives; a force's range
    over one second says nothing about whether the pressures resolve it, so that window's
    verdicts (here all "not resolved") are not shown, the minute's (all fine) are."""
    import json

    held: list[Any] = []
    release = False

    def hold_minutes(route: Any) -> None:
        q = {k: float(v) for k, v in (kv.split("=") for kv in
                                      route.request.url.split("?", 1)[1].split("&"))}
        if release:
            route.continue_()
            return
        if q["to"] - q["from"] > 2:  # a minute: answered later
            held.append(route)
            return
        resp = route.fetch()
        body = resp.json()
        for v in body["force_observability"]:
            v.update(observable=False, causes=["noise share"], share=0.5)
        route.fulfill(response=resp, body=json.dumps(body))

    page.route("**/api/v1/machines/crane-2/twin?*", hold_minutes)
    page.goto(f"{server.url}/machines/crane-2?mode=replay&from={END - 600}&to={END}"
              f"&t={END - 200}")
    _wait_ready(page)
    assert page.evaluate("window.cranetwin.drawnT") == pytest.approx(END - 200, abs=0.6)
    assert held, "the minute was answered before the first second's window"
    assert all(v == {"obs": None, "con": None} for v in _verdicts_shown(page).values())
    assert _notes_shown(page) == []
    release = True
    for route in held:
        route.fulfill(response=route.fetch())
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 200}) < 0.01")
    page.wait_for_timeout(300)
    assert all(v == {"obs": None, "con": None} for v in _verdicts_shown(page).values())
    assert not page.errors


def test_exported_file_flags_unresolved_forces_of_its_minute(page: Any, server: Service,
                                                             tmp_path: Path) -> None:
    """An exported replay keeps each minute's verdicts: with the second minute's saying the lift
    cylinder's force is not resolved, the offline page shows the badge there and not in the
    first minute."""
    import base64
    import gzip
    import json
    import re

    r = httpx.get(f"{server.url}/api/v1/machines/crane-2/export.html",
                  params={"from": END - 120, "to": END}, headers={"X-API-Key": server.viewer},
                  timeout=60.0)
    assert r.status_code == 200
    pattern = r'(<script type="text/plain" id="ct-data">)([A-Za-z0-9+/=]*)(</script>)'
    m = re.search(pattern, r.text)
    assert m
    embed = json.loads(gzip.decompress(base64.b64decode(m.group(2))))
    notes = embed["twin"]["notes"]
    assert len(notes) == 2 and all(v["observable"] for n in notes
                                   for v in n["force_observability"])
    (lift,) = [v for v in notes[1]["force_observability"] if v["cylinder"] == "lift"]
    lift.update(observable=False, sigma_n=900.0, range_n=3000.0, share=0.3,
                causes=["noise share"])
    blob = base64.b64encode(gzip.compress(json.dumps(embed).encode())).decode()
    f = tmp_path / "replay.html"
    f.write_text(r.text[:m.start(2)] + blob + r.text[m.end(2):])
    page.route("http://**", lambda route: route.abort())
    page.goto(f.as_uri())
    _wait_ready(page)
    page.wait_for_timeout(300)
    assert all(v == {"obs": None, "con": None} for v in _verdicts_shown(page).values())
    page.locator("#slider").evaluate("(el) => { el.value = '70';"
                                     " el.dispatchEvent(new Event('input')); }")
    page.wait_for_function(f"Math.abs(window.cranetwin.drawnT - {END - 50}) < 0.01")
    page.wait_for_function("!document.getElementById('force-notes').hidden", timeout=10000)
    shown = _verdicts_shown(page)
    assert shown["lift"]["obs"] == (
        "± not resolved | lift: force not resolved (noise share): pressure error ±900 N "
        "(1σ, estimated noise) against a force range of 3.0 kN (30 %; limit 10 %)")
    assert shown["jib"] == shown["extension"] == {"obs": None, "con": None}
    assert _notes_shown(page) == [
        "lift: force not resolved (noise share): error ±900 N against a 3.0 kN range (30 %)"]
    assert not page.errors


def test_range_without_data_says_so(page: Any, server: Service) -> None:
    a, b = END - 7200, END - 6600  # an hour before the stored data
    page.goto(f"{server.url}/machines/crane-2?mode=replay&from={a}&to={b}")
    page.wait_for_function("document.getElementById('banner').textContent.includes('No data')",
                           timeout=20000)
    page.wait_for_function("document.getElementById('charts-msg').textContent"
                           ".includes('No load history')", timeout=20000)
    _shot(page, "no-data.png")
    assert not page.errors


def test_scene_and_export_use_the_api_keys(server: Service) -> None:
    """On the real app the web data routes apply the API's auth: 401 without a key, 200 with."""
    for path in ("/api/v1/machines/crane-2/scene",
                 f"/api/v1/machines/crane-2/export.html?from={END - 20}&to={END}"):
        r = httpx.get(f"{server.url}{path}")
        assert r.status_code == 401 and r.headers["content-type"].startswith(
            "application/problem+json"), path
        r = httpx.get(f"{server.url}{path}", headers={"X-API-Key": "ctk_000000000000_nope"})
        assert r.status_code == 401, path
        r = httpx.get(f"{server.url}{path}", headers={"X-API-Key": server.viewer})
        assert r.status_code == 200, (path, r.text[:200])
    r = httpx.get(f"{server.url}/api/v1/machines/nope/scene",
                  headers={"X-API-Key": server.viewer})
    assert r.status_code == 404


def test_export_button_downloads_the_window(page: Any, server: Service, tmp_path: Path) -> None:
    _replay(page, server, END - 300)
    with page.expect_download(timeout=60000) as info:
        page.click("#export")
    path = tmp_path / "export.html"
    info.value.save_as(str(path))
    html = path.read_text()
    assert 'id="ct-data"' in html and 'id="ct-meshcat"' in html
    assert 1_000_000 < len(html) < 5_000_000
    page.wait_for_function("document.getElementById('banner').textContent.includes('Exported')")
    assert not page.errors


def test_report_button_downloads_the_maintenance_report(page: Any, server: Service,
                                                       tmp_path: Path) -> None:
    pypdf = pytest.importorskip("pypdf", reason="pypdf needed to read the report")
    _replay(page, server, END - 300, key=server.fleet)
    with page.expect_download(timeout=120000) as info:
        page.click("#report")
    path = tmp_path / "report.pdf"
    info.value.save_as(str(path))
    text = "".join(p.extract_text() or "" for p in pypdf.PdfReader(str(path)).pages)
    assert "Load spectrum" in text
    page.wait_for_function(
        "document.getElementById('banner').textContent.includes('Report downloaded')")
    assert not page.errors


def test_report_button_with_a_viewer_key_explains_the_role(page: Any, server: Service) -> None:
    _replay(page, server, END - 300)
    page.click("#report")
    page.wait_for_function(
        "document.getElementById('banner').textContent.includes('fleet or admin key')",
        timeout=60000)
    assert not page.errors


def test_no_data_message_survives_a_slow_scene(page: Any, server: Service) -> None:
    """The empty replay chunk answers before the 3D scene has loaded: the message still shows."""
    def slow_scene(route: Any) -> None:
        time.sleep(2.0)
        route.continue_()

    page.route("**/scene*", slow_scene)
    a, b = END - 7200, END - 6600
    page.goto(f"{server.url}/machines/crane-2?mode=replay&from={a}&to={b}")
    page.wait_for_function("document.getElementById('banner').textContent.includes('No data')",
                           timeout=20000)
    assert not page.errors


@pytest.mark.timeout(60)
def test_alarms_acknowledge_and_clear_in_the_fleet_page(browser: Any, server: Service) -> None:
    """The fleet page lists alarms; a viewer is told it needs a fleet key; a fleet user
    acknowledges (who and when shown) and clears (gone from the active list, shown under
    'cleared')."""
    from cranetwin.storage import Event

    t = END - 30.0
    server.app.state.services.backend.store.add_events([Event(
        "crane-2", t, "overload", "critical",
        {"value": 2.84e4, "limit": 2.0e4, "unit": "N*m", "component": "load"})])
    ctx = browser.new_context()
    _sign_in(ctx, server)
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(f"{server.url}/")
    pg.wait_for_function("window.cranetwin.alarmsReady === true", timeout=15000)
    pg.select_option("#f-machine", "crane-2")
    row = pg.locator("#alarm-rows tr", has_text="28.4 kN·m")
    row.wait_for(timeout=10000)
    assert "overload on load: 28.4 kN·m (limit 20 kN·m, 142 % of it)" in row.inner_text()
    assert "new" in row.locator(".state").inner_text()
    state = f"#alarm-rows tr[data-alarm-id='{row.get_attribute('data-alarm-id')}'] .state"
    row.locator("button.ack").click()
    pg.wait_for_selector("#alarm-note:not([hidden])", timeout=10000)
    assert "fleet or admin key" in pg.inner_text("#alarm-note")
    # sign in again with a fleet key
    pg.click("#sign-out")
    pg.wait_for_selector("#key-dialog[open]", timeout=10000)
    pg.fill("#key-input", server.fleet)
    pg.click("#key-form button")
    pg.wait_for_function("document.getElementById('who').textContent.includes('fleet')")
    row.locator("button.ack").click()
    pg.wait_for_function(f"document.querySelector(\"{state}\").textContent"
                         ".includes('acknowledged by web tests (fleet)')", timeout=10000)
    assert row.locator("button.ack").count() == 0
    row.locator("button.clear").click()
    pg.wait_for_function(f"!document.querySelector(\"{state}\")", timeout=10000)
    pg.select_option("#f-state", "cleared")
    pg.wait_for_function(f"(document.querySelector(\"{state}\") || {{}}).textContent"
                         "?.includes('cleared by web tests (fleet)')", timeout=10000)
    _shot(pg, "alarms.png")
    assert not errors
    ctx.close()


@pytest.mark.timeout(60)
def test_fleet_table_sorts_filters_and_shows_fleet_figures(page: Any, server: Service) -> None:
    from dataclasses import replace

    from cranetwin.service.backend import Progress

    backend = server.app.state.services.backend
    for mid, hours, lifts, kg in (("crane-1", 1.0, 30, 9000.0), ("crane-3", 5.0, 4, 1500.0)):
        if backend.progress(mid) is None:
            backend.save_progress(replace(Progress.empty(mid), operating_s=hours * 3600,
                                          load_count=lifts, payload_total_kg=kg), None)
    page.goto(f"{server.url}/")
    _wait_ready(page)
    assert page.inner_text("#fig-machines") == "3"
    assert "offline" in page.inner_text("#fig-status")
    assert page.inner_text("#fig-lifts") != "–" and page.inner_text("#fig-tonnes").endswith(" t")
    # the figures are the service's, formatted for people (en-US: grouping commas)
    tot = page.request.get(f"{server.url}/api/v1/fleet/figures").json()["total"]
    assert page.inner_text("#fig-hours") == f"{tot['operating_h']:,.1f} h"
    assert page.inner_text("#fig-lifts") == f"{tot['lifts']:,.0f}"
    assert page.inner_text("#fig-tonnes") == f"{tot['tonnes']:,.1f} t"
    assert page.inner_text("#fig-alarms") == f"{tot['alarms_today']:,}"
    assert page.inner_text("#fig-critical") == f"{tot['critical_today']} critical"
    # the table's column counts the critical events of the last 24 h, as its header says
    machines = {m["machine_id"]: m for m in page.request.get(f"{server.url}/api/v1/machines")
                .json()}
    for mid, m in machines.items():
        crit = [e for e in page.request.get(f"{server.url}/api/v1/machines/{mid}/events",
                                            params={"from": time.time() - 86400,
                                                    "to": time.time()}).json()
                if e["severity"] == "critical"]
        assert m["alarms"] == len(crit), (mid, m["alarms"], len(crit))
        assert page.inner_text(f"tr[data-machine-id={mid}] td:nth-child(9)") == str(len(crit))
    assert "Critical 24 h" in page.inner_text("th[data-sort=alarms]")

    def order() -> list[str]:
        return page.eval_on_selector_all("#rows tr", "rs => rs.map(r => r.dataset.machineId)")

    page.click("th[data-sort=lifts] button")
    assert page.get_attribute("th[data-sort=lifts]", "aria-sort") == "ascending"
    asc = order()
    assert asc.index("crane-3") < asc.index("crane-1")  # 4 lifts before 30
    page.click("th[data-sort=lifts] button")
    assert page.get_attribute("th[data-sort=lifts]", "aria-sort") == "descending"
    assert order() == asc[::-1]
    page.click("th[data-sort=name] button")
    assert order() == ["crane-1", "crane-2", "crane-3"]
    page.select_option("#status-filter", "offline")
    classes = page.eval_on_selector_all("#rows tr", "rs => rs.map(r => r.className)")
    assert "crane-3" in order() and all("offline" in c for c in classes), classes
    page.select_option("#status-filter", "")
    page.fill("#filter", "Crane 2")
    assert order() == ["crane-2"]
    _shot(page, "fleet-figures.png")
    assert not page.errors
