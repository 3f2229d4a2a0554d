"""The compare page in Chromium: 2–4 machines side by side on one timeline.

``create_app`` on SQLite: crane-2 with 10 min of stored samples, crane-3 with only the first
5 min of the same range and its motion 30 s out of phase (so the two cranes differ at any time,
and one of them has no data in the second half). Skipped with a reason when Chromium or
Playwright is missing.
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
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
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
        for i in (2, 3):
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
        for mid in ("crane-2", "crane-3"):
            TwinWorker(services.backend, services.settings, services.metrics,
                       services.fleet.replayer).catch_up(services.backend.machine(mid))
        yield str(srv.url), str(viewer)


@pytest.fixture()
def page(server: tuple[str, str]) -> Iterator[Any]:
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
def test_two_cranes_replay_on_one_timeline(page: Any, server: tuple[str, str]) -> None:
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
def test_fleet_compare_button_and_wrong_links(page: Any, server: tuple[str, str]) -> None:
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
