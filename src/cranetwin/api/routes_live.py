"""``WS /api/v1/machines/{id}/live``: poses and forces as they arrive, 20–50 frames/s.

Protocol: JSON text frames. The first is ``{"type": "hello", "machine_id", "model",
"rate_hz"}``; then frames ``{t, q, poses, cylinder_pins, cylinder_forces, utilisation,
payload_kg, pressures}`` (see docs/API.md). Authentication as for REST (the browser's session
cookie, or a key).
On a bad key or unknown machine the server sends ``{"type": "error", status, title, detail}``
and closes with code 4000 + status (4401, 4403, 4404).
"""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from cranetwin.api.auth import authorise
from cranetwin.api.errors import ApiError, http_status
from cranetwin.api.services import Services
from cranetwin.service.errors import ServiceError

router = APIRouter(tags=["live"])


@router.websocket("/api/v1/machines/{machine_id}/live")
async def live(websocket: WebSocket, machine_id: str) -> None:
    """Stream live frames of one machine (role viewer)."""
    services: Services = websocket.app.state.services
    await websocket.accept()
    try:
        authorise(services.keys.authenticate(websocket), "viewer")
        rec = await asyncio.to_thread(services.backend.machine, machine_id)
        follower_factory = services.follower_factory(rec)
    except (ApiError, ServiceError) as exc:
        status = exc.status if isinstance(exc, ApiError) else http_status(exc)
        await websocket.send_json({"type": "error", "status": status, "title": exc.title,
                                   "detail": exc.detail})
        await websocket.close(code=4000 + status)
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
