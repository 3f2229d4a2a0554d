"""HTTP API, and only HTTP: FastAPI app factory, routes, schemas, keys and roles, the live
websocket, problem JSON errors. What the routes call lives in :mod:`cranetwin.service`.

Entry point: :func:`create_app` (``cranetwin serve`` runs it with uvicorn). See docs/API.md.
:class:`Settings` is the one settings object of every command (:mod:`cranetwin.settings`).
"""

from __future__ import annotations

from cranetwin.api.app import create_app
from cranetwin.settings import Settings

__all__ = ["Settings", "create_app"]
