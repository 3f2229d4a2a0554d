"""A stand-alone preview of the web UI on synthetic data (no database, no ingest).

``create_preview_app()`` serves the real web router (:mod:`cranetwin.api.routes_web`) next to
stand-in JSON routes that follow the HTTP contract v1 with data from
:mod:`cranetwin.testing.views`. Front-end work and the browser tests use it; it is not the
service (see :func:`cranetwin.api.create_app`).

Keys: ``viewer-key`` (role viewer) is accepted; no key → 401, any other key → 403.
Live: every machine streams the scripted cycle at ``live_hz``; frames pushed with
:meth:`PreviewState.push` (the tests' "a sample was sent") go out immediately.
"""

from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import FastAPI, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse, Response

from cranetwin.model import Machine, load_machine
from cranetwin.testing.views import synthetic_frame, synthetic_history, synthetic_twin

PREVIEW_KEY = "viewer-key"
PREVIEW_SESSION = "preview-session"
"""The preview's session cookie value after signing in with :data:`PREVIEW_KEY`."""
Time = Annotated[str | None, Query()]
From = Annotated[str | None, Query(alias="from")]


@dataclass
class PreviewMachine:
    """One simulated machine: id, payload of its cycle [kg], phase [s], status."""

    machine_id: str
    name: str
    payload_kg: float
    phase: float = 0.0
    status: str = "live"
    alarms: int = 0


@dataclass
class PreviewState:
    """State shared by the preview routes."""

    machine: Machine
    machines: dict[str, PreviewMachine]
    start: float
    end: float | None = None
    live_hz: float = 25.0
    auto_live: bool = True
    queues: list[asyncio.Queue[dict[str, Any]]] = field(default_factory=list)

    def now(self) -> float:
        return self.end if self.end is not None else time.time()

    def push(self, frame: dict[str, Any]) -> None:
        """Send one frame to every open live websocket at once."""
        for q in self.queues:
            q.put_nowait(frame)


def _problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse({"type": "about:blank", "title": title, "status": status,
                         "detail": detail}, status_code=status,
                        media_type="application/problem+json")


def _key(request: Request | WebSocket) -> str | None:
    """The presented key, else the key of a preview session cookie."""
    from cranetwin.api.auth import SESSION_COOKIE

    auth = request.headers.get("authorization", "")
    session = PREVIEW_KEY if request.cookies.get(SESSION_COOKIE) == PREVIEW_SESSION else None
    return (request.headers.get("x-api-key") or
            (auth[7:] if auth.lower().startswith("bearer ") else None) or
            request.query_params.get("key") or session)


def _t(v: str | None, default: float) -> float:
    if v is None or v == "":
        return default
    try:
        return float(v)
    except ValueError:
        from datetime import datetime

        return datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()


def create_preview_app(machines: list[PreviewMachine] | None = None, *,
                       history_s: float = 3600.0, end: float | None = None,
                       auto_live: bool = True) -> FastAPI:
    """The preview app: web routes + contract-shaped synthetic JSON routes.

    Args:
        machines: Simulated machines (default: three cranes with 250/450/700 kg logs, one offline).
        history_s: Length of the stored data range, ending now (or at ``end``) [s].
        end: Fixed end of the stored range [epoch s]; None = now (moves with the clock).
        auto_live: Stream the scripted cycle on the live websockets.
    """
    from cranetwin.api.routes_web import router as web_router

    machine = load_machine("patu655")
    if machines is None:
        machines = [PreviewMachine("crane-1", "Crane 1 (Forwarder A)", 250.0, 0.0),
                    PreviewMachine("crane-2", "Crane 2 (Forwarder B)", 450.0, 13.0, alarms=2),
                    PreviewMachine("crane-3", "Crane 3 (yard)", 700.0, 27.0, status="offline")]
    now = end if end is not None else time.time()
    state = PreviewState(machine, {m.machine_id: m for m in machines}, start=now - history_s,
                         end=end, auto_live=auto_live)
    app = FastAPI(title="cranetwin web preview")
    app.state.preview = state
    app.include_router(web_router)

    @app.middleware("http")
    async def auth(request: Request, call_next: Any) -> Response:
        path = request.url.path
        if (path.startswith("/api/") and not path.startswith("/api/v1/_preview")
                and not (path == "/api/v1/session" and request.method in ("POST", "DELETE"))):
            key = _key(request)
            if not key:
                return _problem(401, "Unauthorized", "an API key is required (X-API-Key)")
            if key != PREVIEW_KEY:
                return _problem(403, "Forbidden", "this key does not have role viewer")
        response: Response = await call_next(request)
        return response

    def get(mid: str) -> PreviewMachine:
        if mid not in state.machines:
            raise KeyError(mid)
        return state.machines[mid]

    def summary(m: PreviewMachine) -> dict[str, Any]:
        t = state.now()
        frame = synthetic_frame(machine, t, m.payload_kg, m.phase)
        last = t if m.status == "live" else state.start + 0.5 * (t - state.start)
        return {"machine_id": m.machine_id, "name": m.name, "model": "patu655",
                "status": m.status,
                "last_seen": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(last)),
                "payload_kg": frame["payload_kg"] if m.status == "live" else None,
                "alarms": m.alarms, "location": {"lat": 62.6, "lon": 29.76}}

    @app.get("/api/v1/machines")
    def list_machines() -> list[dict[str, Any]]:
        return [summary(m) for m in state.machines.values()]

    @app.get("/api/v1/machines/{mid}")
    def one(mid: str) -> Response:
        if mid not in state.machines:
            return _problem(404, "Not found", f"unknown machine {mid!r}")
        m = get(mid)
        iso = "%Y-%m-%dT%H:%M:%SZ"
        return JSONResponse({**summary(m), "data_range": {
            "from": time.strftime(iso, time.gmtime(state.start)),
            "to": time.strftime(iso, time.gmtime(state.now()))}})

    @app.get("/api/v1/machines/{mid}/model")
    def model(mid: str) -> Response:
        if mid not in state.machines:
            return _problem(404, "Not found", f"unknown machine {mid!r}")
        return JSONResponse(machine.model_dump(mode="json"))

    @app.get("/api/v1/machines/{mid}/twin")
    def twin(mid: str, from_: From = None,
             to: Time = None, rate_hz: float = 50.0) -> Response:
        m = get(mid)
        a = max(_t(from_, state.now() - 10), state.start)
        b = min(_t(to, state.now()), state.now())
        if b <= a:
            return JSONResponse({"t": [], "q": [], "tip": [], "poses": {}, "cylinder_pins": {},
                                 "cylinder_forces": {}, "utilisation": {},
                                 "payload": {"t": [], "kg": []}})
        return JSONResponse(synthetic_twin(machine, a, b, rate_hz, m.payload_kg, m.phase))

    @app.get("/api/v1/machines/{mid}/history")
    def history(mid: str, from_: From = None,
                to: Time = None, channels: str = "payload", max_points: int = 2000) -> Response:
        m = get(mid)
        a = max(_t(from_, state.start), state.start)
        b = min(_t(to, state.now()), state.now())
        if b <= a:
            return JSONResponse({"channels": {}})
        return JSONResponse(synthetic_history(machine, a, b, channels.split(","), max_points,
                                              m.payload_kg, m.phase))

    @app.get("/api/v1/machines/{mid}/events")
    def events(mid: str, from_: From = None,
               to: Time = None) -> list[dict[str, Any]]:
        get(mid)
        a, b = _t(from_, state.start), _t(to, state.now())
        out = []
        k = int(a // 120) + 1
        while k * 120 + 7 < b:
            out.append({"t": k * 120 + 7.0, "kind": "overload", "severity": "warning",
                        "message": "payload above rated load at this reach", "evidence": {}})
            k += 1
        return out

    @app.post("/api/v1/session")
    async def sign_in(request: Request) -> Response:
        from cranetwin.api.auth import SESSION_COOKIE

        try:
            key = str((await request.json()).get("key", "")).strip()
        except (ValueError, AttributeError):
            key = ""
        if key != PREVIEW_KEY:
            return _problem(401, "Invalid API key", f"the preview's key is {PREVIEW_KEY!r}")
        resp = JSONResponse({"key_id": "preview", "name": "preview viewer", "role": "viewer",
                             "expires": None})
        resp.set_cookie(SESSION_COOKIE, PREVIEW_SESSION, httponly=True, samesite="strict",
                        path="/")
        return resp

    @app.get("/api/v1/session")
    async def who() -> dict[str, Any]:
        return {"key_id": "preview", "name": "preview viewer", "role": "viewer",
                "expires": None}

    @app.delete("/api/v1/session")
    async def sign_out() -> Response:
        from cranetwin.api.auth import SESSION_COOKIE

        resp = Response(status_code=204)
        resp.delete_cookie(SESSION_COOKIE, path="/")
        return resp

    @app.websocket("/api/v1/machines/{mid}/live")
    async def live(ws: WebSocket, mid: str) -> None:
        if _key(ws) != PREVIEW_KEY:
            await ws.close(code=1008)
            return
        m = get(mid)
        await ws.accept()
        await ws.send_json({"type": "hello", "machine_id": mid, "model": "patu655"})
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        state.queues.append(queue)
        try:
            while True:
                try:
                    frame = await asyncio.wait_for(queue.get(), timeout=1.0 / state.live_hz)
                except TimeoutError:
                    if not state.auto_live or m.status != "live":
                        continue
                    frame = synthetic_frame(machine, time.time(), m.payload_kg, m.phase)
                await ws.send_json(frame)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            state.queues.remove(queue)

    @app.post("/api/v1/_preview/push/{mid}")
    def push(mid: str, t: float | None = None) -> dict[str, Any]:
        m = get(mid)
        frame = synthetic_frame(machine, time.time() if t is None else t, m.payload_kg, m.phase)
        state.push(frame)
        return {"t": frame["t"]}

    return app


class ServerThread:
    """uvicorn serving an ASGI app on a free loopback port in a background thread.

    Use as a context manager; ``url`` is the base URL. For tests and benchmarks.
    """

    def __init__(self, app: Any, port: int = 0) -> None:
        import socket

        import uvicorn

        if port == 0:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = int(s.getsockname()[1])
        self.port = port
        config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                ws="websockets-sansio")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> ServerThread:
        self.thread.start()
        deadline = time.time() + 30
        while not self.server.started:
            if time.time() > deadline or not self.thread.is_alive():
                raise RuntimeError(f"uvicorn did not start on port {self.port}")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(10)

    @property
    def url(self) -> str:
        """Base URL, e.g. ``http://127.0.0.1:41234``."""
        return f"http://127.0.0.1:{self.port}"
