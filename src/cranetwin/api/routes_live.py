"""``WS /api/v1/machines/{id}/live``: poses and forces as they arrive, 20–50 frames/s.

Protocol: JSON text frames. The first is ``{"type": "hello", "machine_id", "model",
"rate_hz"}``; then frames ``{t, q, poses, cylinder_pins, cylinder_forces, utilisation,
payload_kg, pressures}`` (see docs/API.md). Authentication as for REST (the browser's session
cookie, or a key).
A connection is charged to its key's rate limit as a cheap request
(:func:`~cranetwin.api.limits.admit`).
On a bad key, an unknown machine or a used-up rate limit the server sends ``{"type": "error",
status, title, detail}`` (a refusal for the rate limit also ``retry_after`` [s], sent after
min(retry_after, ``rate_limit_delay_s``) as an HTTP refusal is) and closes with code
4000 + status and the title as reason (4401, 4403, 4404, 4429).
"""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from cranetwin.api.auth import authorise
from cranetwin.api.errors import ApiError, http_status
from cranetwin.api.limits import admit
from cranetwin.api.services import Services
from cranetwin.service.errors import ServiceError

router = APIRouter(tags=["live"])


@router.websocket("/api/v1/machines/{machine_id}/live")
async def live(websocket: WebSocket, machine_id: str) -> None:
    """Stream live frames of one machine (role viewer)."""
    services: Services = websocket.app.state.services
    await websocket.accept()
    try:
        key = authorise(services.keys.authenticate(websocket), "viewer")
        admit(services, websocket, key)  # a connection costs what a cheap request does
        rec = await asyncio.to_thread(services.backend.machine, machine_id)
        follower_factory = services.follower_factory(rec)
    except (ApiError, ServiceError) as exc:
        status = exc.status if isinstance(exc, ApiError) else http_status(exc)
        error: dict[str, object] = {"type": "error", "status": status, "title": exc.title,
                                    "detail": exc.detail}
        if status == 429:  # as an HTTP refusal: told when to retry, answered after a delay
            retry = int((getattr(exc, "headers", None) or {}).get("Retry-After", "1"))
            error["retry_after"] = retry
            await asyncio.sleep(min(retry, services.settings.rate_limit_delay_s))
        await websocket.send_json(error)
        await websocket.close(code=4000 + status, reason=exc.title[:120])
        return
    await websocket.send_json({"type": "hello", "machine_id": rec.machine_id,
                               "model": rec.model, "rate_hz": services.settings.live_rate_hz})
    client = services.live.subscribe(rec.machine_id, follower_factory)
    services.metrics.live_clients.inc()

    async def drain_incoming() -> None:
        while True:
            await websocket.receive_text()  # clients may send pings; raises on disconnect

    reader = asyncio.create_task(drain_incoming())
    try:
        while not reader.done():
            getter = asyncio.create_task(client.queue.get())
            done, _ = await asyncio.wait({getter, reader}, return_when=asyncio.FIRST_COMPLETED)
            if getter not in done:
                getter.cancel()
                break
            await websocket.send_text(getter.result())
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        reader.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await reader
        services.live.unsubscribe(rec.machine_id, client)
        services.metrics.live_clients.dec()
