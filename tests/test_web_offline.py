"""Offline-clean pages: /docs (Swagger UI) served from the installed swagger-ui-bundle-v2 package,
never a CDN; a favicon on every page; the docs page without the package says how to get it."""

from __future__ import annotations

import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.routes_docs import swagger_ui_dir
from cranetwin.settings import Settings

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
needs_bundle = pytest.mark.skipif(swagger_ui_dir() is None, reason="swagger-ui-bundle-v2 not "
                                  "installed (pip install -e '.[web]')")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    url = f"sqlite:///{tmp_path_factory.mktemp('offline') / 'o.db'}"
    with TestClient(create_app(Settings(database_url=url, worker_in_process=False))) as c:
        yield c


def _external_refs(page: str) -> list[str]:
    """src/href values and url(...) of a page that point to another host."""
    refs = re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url\(["']?([^"')]+)""", page)
    urls = [a or b for a, b in refs] + re.findall(r"""['"](https?://[^'"]+)['"]""", page)
    return [u for u in urls if re.match(r"(https?:)?//", u)]


@needs_bundle
@pytest.mark.timeout(20)
def test_docs_page_and_assets_are_served_locally(client: TestClient) -> None:
    r = client.get("/docs")
    assert r.status_code == 200
    assert "swagger-ui" in r.text and "/openapi.json" in r.text
    assert _external_refs(r.text) == []
    for name, kind in (("swagger-ui-bundle.js", "text/javascript"),
                       ("swagger-ui.css", "text/css")):
        a = client.get(f"/docs/assets/{name}")
        assert a.status_code == 200 and a.headers["content-type"].startswith(kind)
        assert len(a.content) > 10_000
    assert client.get("/docs/assets/index.html").status_code == 404
    assert client.get("/docs/assets/..%2F..%2F__init__.py").status_code == 404
    assert client.get("/redoc").status_code == 404  # FastAPI's CDN-only ReDoc is off


@pytest.mark.timeout(20)
def test_docs_without_the_package_says_how_to_get_it(client: TestClient,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import cranetwin.api.routes_docs as rd

    monkeypatch.setattr(rd, "swagger_ui_dir", lambda: None)
    r = client.get("/docs")
    assert r.status_code == 200
    assert "pip install 'cranetwin[web]'" in r.text and "/openapi.json" in r.text
    assert _external_refs(r.text) == []
    assert client.get("/docs/assets/swagger-ui-bundle.js").status_code == 404


@pytest.mark.timeout(20)
def test_favicon_everywhere(client: TestClient) -> None:
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"] == "image/svg+xml"
    assert r.content.startswith(b"<svg")
    for page in ("/", "/machines/crane-1"):
        assert 'rel="icon" href="/favicon.ico"' in client.get(page).text


@needs_bundle
@pytest.mark.browser
@pytest.mark.timeout(40)
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Chromium not installed")
def test_docs_render_with_the_network_cut_off(tmp_path: Path) -> None:
    """Swagger UI renders in Chromium with every request to another host refused."""
    playwright_api = pytest.importorskip("playwright.sync_api")
    from cranetwin.api.preview import ServerThread

    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'd.db'}",
                              worker_in_process=False))
    outside: list[str] = []
    with ServerThread(app) as srv, playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox"])
        page = b.new_page()
        host = str(srv.url).split("//")[1].split("/")[0]

        def gate(route: Any) -> None:
            if route.request.url.split("//")[1].split("/")[0] == host:
                route.continue_()
            else:
                outside.append(route.request.url)
                route.abort()

        page.route("**/*", gate)
        failed: list[str] = []
        page.on("response", lambda r: failed.append(r.url) if r.status >= 400 else None)
        page.goto(f"{srv.url}/docs")
        page.wait_for_selector(".swagger-ui .info .title", timeout=20000)
        assert "cranetwin" in page.inner_text(".swagger-ui .info .title")
        page.wait_for_selector(".opblock-tag", timeout=10000)  # the operations are listed
        b.close()
    assert outside == [] and failed == [], (outside, failed)
