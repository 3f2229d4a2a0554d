"""Typed FastAPI dependencies: the routes read like signatures."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from fastapi import Depends, Path, Request, Security
from fastapi.security import HTTPAuthorizationCredentials

from cranetwin.api.auth import (
    ApiKey,
    Role,
    authorise,
    bearer_scheme,
    header_scheme,
    query_scheme,
)
from cranetwin.api.limits import admit
from cranetwin.settings import Settings

if TYPE_CHECKING:
    from cranetwin.api.services import Services
    from cranetwin.service.backend import Backend, MachineRecord


def get_services(request: Request) -> Services:
    """The app's services (opened by the lifespan)."""
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated["Services", Depends(get_services)]


def get_backend(request: Request) -> Backend:
    """The storage adapter."""
    return get_services(request).backend


def get_settings(request: Request) -> Settings:
    """The app's settings."""
    settings: Settings = request.app.state.settings
    return settings


StoreDep = Annotated["Backend", Depends(get_backend)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


def require_role(role: Role):  # type: ignore[no-untyped-def]
    """Dependency admitting keys of at least ``role``: no/unknown key → 401, lower role → 403,
    its rate limit used up → 429 (:func:`cranetwin.api.limits.admit`, if the middleware did not
    charge the request already).

    The three ``Security`` parameters only document the accepted key locations in OpenAPI; the
    key is read by :meth:`~cranetwin.api.auth.KeyVerifier.authenticate` (a presented key, else the
    browser's session cookie).
    """

    async def dependency(
        request: Request,
        _header: Annotated[str | None, Security(header_scheme)] = None,
        _bearer: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)] = None,
        _query: Annotated[str | None, Security(query_scheme)] = None,
    ) -> ApiKey:
        services = get_services(request)
        key = authorise(services.keys.authenticate(request), role)
        admit(services, request, key)
        return key

    dependency.__name__ = f"require_{role}"
    return dependency


CurrentKey = Annotated[ApiKey, Depends(require_role("viewer"))]
FleetKey = Annotated[ApiKey, Depends(require_role("fleet"))]
AdminKey = Annotated[ApiKey, Depends(require_role("admin"))]

MachineIdPath = Annotated[str, Path(description="machine identifier", examples=["crane-1"],
                                    min_length=1, max_length=64)]


def get_machine(request: Request, machine_id: MachineIdPath) -> MachineRecord:
    """The stored machine ``machine_id`` (unknown: 404 problem JSON, by the error handler)."""
    return get_backend(request).machine(machine_id)


MachineDep = Annotated["MachineRecord", Depends(get_machine)]
