"""Offline-clean service pages: the interactive API docs (Swagger UI) with its assets served from
the installed ``swagger-ui-bundle-v2`` package (the ``[web]`` extra; it installs the module
``swagger_ui_bundle`` with Swagger UI 5, which reads the OpenAPI 3.1 documents FastAPI writes —
the older ``swagger-ui-bundle`` 1.x ships Swagger UI 4, which cannot) instead of a CDN, and the
favicon.

``create_app`` turns FastAPI's own ``/docs`` and ``/redoc`` off (their pages load scripts and
styles from a CDN and stay blank without internet) and includes this router instead:

* ``GET /docs``: Swagger UI on ``/openapi.json``, its script, style and icon from this server; when
  the package is missing, a page (no external reference either) that says how to install it and
  links the OpenAPI document.
* ``GET /docs/assets/{name}``: ``swagger-ui-bundle.js`` and ``swagger-ui.css`` of the package.
* ``GET /favicon.ico``: the web UI's icon (``web/favicon.svg``), so no page logs a 404 for it.
"""

from __future__ import annotations

import html
import re
from pathlib import Path

from fastapi import APIRouter, Request, Response
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse

router = APIRouter(include_in_schema=False)

ASSETS = {"swagger-ui-bundle.js": "text/javascript", "swagger-ui.css": "text/css"}
"""The Swagger UI files served, with their media types."""


MIN_SWAGGER_UI = 5
"""Oldest Swagger UI major version served (5 reads OpenAPI 3.1)."""


def swagger_ui_dir() -> Path | None:
    """Folder of the Swagger UI distribution (``swagger_ui_bundle`` module of the
    ``swagger-ui-bundle-v2`` package), or None when it is not installed or older than
    :data:`MIN_SWAGGER_UI`."""
    try:
        from swagger_ui_bundle import swagger_ui_path  # type: ignore[import-not-found,import-untyped,unused-ignore]
    except ImportError:
        return None
    path = Path(str(swagger_ui_path))
    version = re.match(r"swagger-ui-(\d+)", path.name)
    if version is None or int(version.group(1)) < MIN_SWAGGER_UI:
        return None
    return path if (path / "swagger-ui-bundle.js").is_file() else None


@router.get("/docs")
def docs(request: Request) -> Response:
    """Swagger UI, every file from this server."""
    title = f"{request.app.title} · API"
    openapi_url = request.app.openapi_url or "/openapi.json"
    if swagger_ui_dir() is None:
        body = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>"
                f"{html.escape(title)}</title><link rel='icon' href='/favicon.ico'></head><body "
                "style='font-family: sans-serif; max-width: 40em; margin: 2em auto'>"
                "<h1>API documentation</h1><p>The interactive documentation (Swagger UI) needs "
                "the optional package <code>swagger-ui-bundle-v2</code> (Swagger UI 5): "
                "<code>pip install 'cranetwin[web]'</code>. It is served from this machine, "
                "never from the internet.</p><p>The API's OpenAPI document: <a href='"
                f"{html.escape(openapi_url)}'>{html.escape(openapi_url)}</a>; its reference: "
                "<code>docs/API.md</code> in the repository.</p></body></html>")
        return HTMLResponse(body)
    return get_swagger_ui_html(openapi_url=openapi_url, title=title,
                               swagger_js_url="/docs/assets/swagger-ui-bundle.js",
                               swagger_css_url="/docs/assets/swagger-ui.css",
                               swagger_favicon_url="/favicon.ico",
                               oauth2_redirect_url=None)


@router.get("/docs/assets/{name}")
def docs_asset(name: str) -> Response:
    """A file of the Swagger UI distribution (:data:`ASSETS` only)."""
    folder = swagger_ui_dir()
    if name not in ASSETS or folder is None:
        return JSONResponse({"type": "about:blank", "title": "Not found", "status": 404,
                             "detail": f"no docs asset {name!r}" if folder is not None else
                             "the swagger-ui-bundle-v2 package is not installed "
                             "(pip install 'cranetwin[web]')"},
                            status_code=404, media_type="application/problem+json")
    return FileResponse(folder / name, media_type=ASSETS[name],
                        headers={"Cache-Control": "public, max-age=86400"})


@router.get("/favicon.ico")
def favicon(request: Request) -> Response:
    """The web UI's icon (SVG; browsers accept it under this name)."""
    try:
        from cranetwin.api.routes_web import _web_dir
    except ImportError:  # the web front end is optional
        return Response(status_code=204)
    path = _web_dir(request) / "favicon.svg"
    if not path.is_file():
        return Response(status_code=204)
    return FileResponse(path, media_type="image/svg+xml",
                        headers={"Cache-Control": "public, max-age=86400"})
