"""HTTP API: FastAPI app factory, routes, auth, live websocket, background twin worker.

Entry point: :func:`create_app` (``cranetwin serve`` runs it with uvicorn). See docs/API.md.
"""

from __future__ import annotations

from cranetwin.api.app import create_app
from cranetwin.api.settings import Settings

__all__ = ["Settings", "create_app"]
