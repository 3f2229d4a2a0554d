"""Web front end routes: pages, static files, the 3D scene and self-contained replay exports.

``create_app`` includes :data:`router`. Pages and static files carry no machine data and need no
key (the page's scripts send the key with every API call); the scene and export routes read
machine data and need a viewer key, which they check by calling the API's own routes
(``/api/v1/machines/{id}/model`` and friends) in-process with the caller's credentials, so the
role rules live in one place (the API's auth dependency).

Files of ``web/`` are found in the repository next to the package (``src/cranetwin`` →
``../../web``), which is where an editable install (``pip install -e .``) and the Docker image
keep them; the ``web_dir`` setting (``CRANETWIN_WEB_DIR``) overrides the location for other
layouts.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import httpx
import numpy as np
from fastapi import APIRouter, Depends, Query, Request, Security
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response

from cranetwin.api.auth import bearer_scheme, header_scheme, query_scheme
from cranetwin.api.params import AFTER_FROM
from cranetwin.errors import CraneTwinError, MissingExtraError
from cranetwin.model import Machine, load_machine, machine_from_dict
from cranetwin.physics.frames import rpy_matrix
from cranetwin.settings import Settings, load_settings
from cranetwin.viz.export import EXPORT_MAX_SECONDS, export_rate_hz, render_export
from cranetwin.viz.poses import rest_frame
from cranetwin.viz.scene import build_scene

log = logging.getLogger(__name__)

router = APIRouter(tags=["web"])

_SCENE_CACHE: dict[str, dict[str, Any]] = {}

WebMachineId = Annotated[str, PathParam(description="machine identifier", examples=["crane-1"],
                                        min_length=1, max_length=64)]


class WebError(CraneTwinError):
    """The web front end cannot serve a request (missing files, upstream API errors)."""

    def __init__(self, status: int, title: str, detail: str) -> None:
        self.status = status
        self.title = title
        self.detail = detail
        super().__init__(f"{title}: {detail}")


def web_dir(settings: Settings | None = None) -> Path:
    """Folder of the static web files: ``settings.web_dir`` (``CRANETWIN_WEB_DIR``) if set,
    else ``web/`` of the repository.

    Args:
        settings: The app's settings; None reads them from the environment (the preview app,
            tests).
    """
    cfg = settings if settings is not None else load_settings(Settings)
    if cfg.web_dir is not None:
        return cfg.web_dir
    return Path(__file__).resolve().parents[3] / "web"


def _web_dir(request: Request) -> Path:
    """:func:`web_dir` of the app serving ``request``."""
    settings = getattr(request.app.state, "settings", None)
    return web_dir(settings if isinstance(settings, Settings) else None)


def vendor_file(name: str) -> Path:
    """Path of a vendored browser library shipped inside a Python package.

    ``meshcat.min.js``: meshcat's three.js viewer bundle; ``plotly.min.js``: plotly.js.
    """
    package = {"meshcat.min.js": "meshcat", "plotly.min.js": "plotly"}.get(name)
    if package is not None:
        try:
            root = resources.files(package)
        except ModuleNotFoundError as exc:
            raise MissingExtraError("web", "the web UI's 3D view and charts") from exc
        if package == "meshcat":
            return Path(str(root / "viewer" / "dist" / "main.min.js"))
        return Path(str(root / "package_data" / "plotly.min.js"))
    raise WebError(404, "Not found", f"no vendored file {name!r}; expected meshcat.min.js or "
                   "plotly.min.js")


def _problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse({"type": "about:blank", "title": title, "status": status,
                         "detail": detail}, status_code=status,
                        media_type="application/problem+json")


def _page(request: Request, name: str) -> Response:
    path = _web_dir(request) / name
    if not path.is_file():
        return _problem(500, "Web files missing",
                        f"{path} not found: install cranetwin from its repository "
                        "(pip install -e .) or set CRANETWIN_WEB_DIR to the web/ folder")
    return FileResponse(path, media_type="text/html", headers={"Cache-Control": "no-cache"})


@router.get("/", include_in_schema=False)
def fleet_page(request: Request) -> Response:
    """The fleet page (HTML)."""
    return _page(request, "index.html")


@router.get("/machines/{machine_id}", include_in_schema=False)
def machine_page(machine_id: str, request: Request) -> Response:
    """The machine page (HTML); the machine id is read by the page's script from the path."""
    return _page(request, "machine.html")


@router.get("/compare", include_in_schema=False)
def compare_page(request: Request) -> Response:
    """2–4 machines side by side (HTML): ``/compare?machines=a,b[,c,d]``, live or replaying one
    time range on one timeline; the page's script reads the machines from the query."""
    return _page(request, "compare.html")


_MEDIA = {".js": "text/javascript", ".css": "text/css", ".html": "text/html",
          ".svg": "image/svg+xml", ".png": "image/png", ".json": "application/json"}


MAX_STATIC_PATH = 256
"""Longest static file path served [characters]; the files of ``web/`` have short names."""


def _static_path_problem(path: str) -> JSONResponse | None:
    """A 400/404 answer for a path that can never name a static file, or None."""
    if len(path) > MAX_STATIC_PATH:
        return _problem(404, "Not found", f"no static file (path of {len(path)} characters; "
                        f"at most {MAX_STATIC_PATH})")
    if any(ord(ch) < 0x20 or ch in "\\\x7f" for ch in path):
        return _problem(400, "Bad path", "static file paths contain no control characters "
                        "(NUL, ...) or backslashes")
    if any(part in ("", ".", "..") for part in path.split("/")):
        return _problem(404, "Not found", f"no static file {path!r}")
    return None


@router.get("/static/{path:path}", include_in_schema=False)
def static_file(path: str, request: Request) -> Response:
    """Files of ``web/`` and the vendored viewer/chart libraries under ``/static/vendor/``.

    A path that cannot name one (NUL or other control characters, ``..``, empty segments,
    longer than :data:`MAX_STATIC_PATH`) is a 400 or 404, never an error of the file system.
    """
    bad = _static_path_problem(path)
    if bad is not None:
        return bad
    if path.startswith("vendor/"):
        try:
            file = vendor_file(path.removeprefix("vendor/"))
        except WebError as exc:
            return _problem(exc.status, exc.title, exc.detail)
        return FileResponse(file, media_type="text/javascript",
                            headers={"Cache-Control": "public, max-age=86400"})
    try:
        root = _web_dir(request).resolve()
        file = (root / path).resolve()
        found = root in file.parents and file.is_file()
    except (OSError, ValueError):  # name too long for the file system, ...
        found = False
    if not found:
        return _problem(404, "Not found", f"no static file {path!r}")
    return FileResponse(file, media_type=_MEDIA.get(file.suffix, "application/octet-stream"),
                        headers={"Cache-Control": "no-cache"})


# --- auth and calls to the API's own routes, with the caller's credentials ----------------------


async def require_viewer(request: Request) -> None:
    """The API's key check (role viewer) when the app has the API's services.

    Apps without them (the synthetic preview of :mod:`cranetwin.api.preview`) check keys in their
    own middleware; the data these routes read comes from the API's routes, called with the
    caller's credentials, so a key that may not read a machine gets its 401/403 either way.
    """
    if getattr(request.app.state, "services", None) is None:
        return
    from cranetwin.api.deps import require_role

    await require_role("viewer")(request)


ViewerDep = Depends(require_viewer)
KEY_SCHEMES = [Security(header_scheme), Security(bearer_scheme), Security(query_scheme)]
"""Where the key may travel, for the OpenAPI document (``require_viewer`` reads it)."""

_WEB_PROBLEMS = (401, 403, 404, 422, 429, 503)
"""Problem JSON statuses of the scene and export routes (the API's own, passed through)."""


def _problems() -> dict[int | str, dict[str, Any]]:
    from cranetwin.api.errors import problem_responses

    return problem_responses(*_WEB_PROBLEMS)


def _auth_headers(request: Request) -> dict[str, str]:
    headers = {"accept": "application/json"}
    services = getattr(request.app.state, "services", None)
    limiter = getattr(services, "limiter", None)
    if limiter is not None:  # the outer request paid: its in-process calls are not charged
        from cranetwin.api.limits import INTERNAL_HEADER

        headers[INTERNAL_HEADER] = limiter.internal_token
    for name in ("x-api-key", "authorization", "cookie"):
        if name in request.headers:
            headers[name] = request.headers[name]
    key = request.query_params.get("key")
    if key and "x-api-key" not in headers and "authorization" not in headers:
        headers["x-api-key"] = key
    return headers


def _machine_url(machine_id: str) -> str:
    """``/api/v1/machines/{machine_id}`` with the id percent-encoded (an id may hold any
    character; the in-process call's URL must stay a URL)."""
    from urllib.parse import quote

    return f"/api/v1/machines/{quote(machine_id, safe='')}"


async def _api_get(request: Request, path: str, params: dict[str, Any] | None = None) -> Any:
    transport = httpx.ASGITransport(app=request.app)
    async with httpx.AsyncClient(transport=transport, base_url="http://cranetwin.internal",
                                 timeout=60.0) as client:
        resp = await client.get(path, params=params, headers=_auth_headers(request))
    if resp.status_code >= 400:
        try:
            body = resp.json()
            title, detail = str(body.get("title", resp.reason_phrase)), str(body.get("detail", ""))
        except (ValueError, AttributeError):
            title, detail = resp.reason_phrase, resp.text[:200]
        raise WebError(resp.status_code, title, detail)
    return resp.json()


async def _scene_for(request: Request, machine_id: str) -> dict[str, Any]:
    model_json = await _api_get(request, f"{_machine_url(machine_id)}/model")
    key = hashlib.sha256(json.dumps(model_json, sort_keys=True).encode()).hexdigest()
    if key in _SCENE_CACHE:
        return _SCENE_CACHE[key]
    try:
        machine = machine_from_dict(model_json, source=f"machine {machine_id}")
    except CraneTwinError:
        # the API may return a summary rather than the full description: use the named model
        name = str(model_json.get("model") or model_json.get("machine", {}).get("name", ""))
        machine = load_machine(name)
    commands, spec = build_scene(machine)
    scene = {
        "commands": commands,
        "spec": {**spec.to_json(),
                 "load_point": {"body": machine.load_point.body,
                                "point_m": list(machine.load_point.point_m)},
                 "rest_frame": rest_frame(machine),
                 **_envelope_spec(machine)},
    }
    if len(_SCENE_CACHE) > 32:
        _SCENE_CACHE.clear()
    _SCENE_CACHE[key] = scene
    return scene


def _envelope_spec(machine: Machine) -> dict[str, Any]:
    """What the 3D view needs to draw the rated-load envelope and the utilisation: the chart
    (payload [kg] at horizontal reach [m], linear in between and held beyond its ends, as
    ``RatedLoad.payload_at``) and the slew axis (the first joint's origin [m] and unit axis in
    the base frame), from which the reach is measured."""
    j0 = machine.joints[0]
    axis = rpy_matrix(j0.origin_rpy_rad) @ np.asarray(j0.axis, dtype=float)
    rl = machine.rated_load  # None: no chart, the view draws no envelope
    return {"rated_load": None if rl is None else {"reach_m": list(rl.reach_m),
                                                   "payload_kg": list(rl.payload_kg)},
            "slew_axis": {"origin_m": [float(x) for x in j0.origin_m],
                          "axis": [float(x) for x in axis / np.linalg.norm(axis)]}}


@router.get("/api/v1/machines/{machine_id}/scene", dependencies=[ViewerDep, *KEY_SCHEMES],
            responses={200: {"description": "the scene commands and spec",
                             "content": {"application/json": {"schema": {"type": "object"}}}},
                       **_problems()}, response_class=JSONResponse)
async def machine_scene(machine_id: WebMachineId, request: Request) -> Response:
    """meshcat ``set_object`` commands for every body, cylinder, the tool and payload, plus the
    spec the browser needs to animate them (node paths, barrel lengths, load point). Role viewer.
    """
    try:
        return JSONResponse(await _scene_for(request, machine_id),
                            headers={"Cache-Control": "private, max-age=3600"})
    except WebError as exc:
        return _problem(exc.status, exc.title, exc.detail)
    except CraneTwinError as exc:
        return _problem(422, "Cannot draw this machine", str(exc))


TimeParam = Annotated[str, Query(description="ISO 8601 or epoch seconds")]


def _epoch(value: str, name: str) -> float:
    try:
        v = float(value)
    except ValueError:
        from datetime import datetime

        try:
            v = datetime.fromisoformat(value.replace("Z", "+00:00")).timestamp()
        except ValueError as exc:
            raise WebError(422, "Invalid time", f"{name}={value!r}: expected ISO 8601 "
                           "(2026-11-23T10:42:00Z) or epoch seconds") from exc
    if not math.isfinite(v):
        raise WebError(422, "Invalid time", f"{name}={value!r} is not finite")
    return v


async def _twin_window(request: Request, machine_id: str, t0: float, t1: float,
                       rate_hz: float) -> dict[str, Any]:
    """The API's twin result for [t0, t1], fetched in ≤ 60 s pieces and joined."""
    parts: list[dict[str, Any]] = []
    a = t0
    while a < t1 - 1e-9:
        b = min(t1, a + 60.0)
        parts.append(await _api_get(request, f"{_machine_url(machine_id)}/twin",
                                    {"from": a, "to": b, "rate_hz": rate_hz}))
        a = b
    from cranetwin.viz.export import join_twin

    return join_twin(parts)


@router.get("/api/v1/machines/{machine_id}/export.html", dependencies=[ViewerDep, *KEY_SCHEMES],
            responses={200: {"description": "the self-contained HTML file (attachment)",
                             "content": {"text/html": {"schema": {"type": "string"}}}},
                       **_problems()}, response_class=HTMLResponse)
async def machine_export(
    machine_id: WebMachineId, request: Request,
    from_: Annotated[str, Query(alias="from", description="ISO 8601 or epoch seconds")],
    to: Annotated[str, Query(description=f"ISO 8601 or epoch seconds; {AFTER_FROM}")],
) -> Response:
    """One self-contained HTML file replaying [from, to] (≤ 10 min): 3D animation, charts,
    events. Opens offline; no server needed. Role viewer.
    """
    try:
        t0, t1 = _epoch(from_, "from"), _epoch(to, "to")
        if not t1 > t0:
            raise WebError(422, "Invalid range", f"to ({to}) must be after from ({from_})")
        if t1 - t0 > EXPORT_MAX_SECONDS:
            raise WebError(422, "Range too long",
                           f"{t1 - t0:.0f} s requested; exports hold at most "
                           f"{EXPORT_MAX_SECONDS:.0f} s (choose a shorter window)")
        base = _machine_url(machine_id)
        machine = await _api_get(request, base)
        model = await _api_get(request, f"{base}/model")
        scene = await _scene_for(request, machine_id)
        twin = await _twin_window(request, machine_id, t0, t1, export_rate_hz(t1 - t0))
        channels = ",".join(_history_channels(model))
        try:
            history = await _api_get(request, f"{base}/history",
                                     {"from": t0, "to": t1, "channels": channels,
                                      "max_points": 800})
        except WebError:
            history = {"channels": {}}
        try:
            events = await _api_get(request, f"{base}/events", {"from": t0, "to": t1})
        except WebError:
            events = []
    except WebError as exc:
        return _problem(exc.status, exc.title, exc.detail)
    html = await _render(request, {
        "machine": machine, "model": model, "scene": scene, "twin": twin,
        "history": history, "events": events, "from": t0, "to": t1,
    })
    name = f"cranetwin-{machine_id}-{int(t0)}.html"
    return Response(html, media_type="text/html",
                    headers={"Content-Disposition": f'attachment; filename="{name}"'})


async def _render(request: Request, data: dict[str, Any]) -> str:
    """:func:`render_export` off the event loop: on the API's heavy threads (503 when they are
    full), or a worker thread in an app without the API's services."""
    import asyncio

    services = getattr(request.app.state, "services", None)
    if services is None:
        return await asyncio.to_thread(render_export, _web_dir(request), data)
    from cranetwin.api.limits import run_heavy

    return await run_heavy(services, None, render_export, _web_dir(request), data)


def _history_channels(model: dict[str, Any]) -> list[str]:
    out = [str(c["name"]) for c in model.get("channels", [])
           if c.get("quantity") in ("pressure_a", "pressure_b")]
    out += [f"force:{c['name']}" for c in model.get("cylinders", [])]
    out.append("payload")
    out += [f"moment:{j['name']}" for j in model.get("joints", []) if j.get("kind") == "revolute"]
    out += [f"torque:{j['name']}" for j in model.get("joints", [])]
    out += [str(c["name"]) for c in model.get("channels", [])
            if c.get("quantity") in ("position", "angle", "torque")]
    return out
