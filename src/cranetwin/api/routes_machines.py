"""Machines: list, register, update, one machine, its description (geometry for the 3D view)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError

from cranetwin.api.deps import AdminKey, CurrentKey, MachineDep, MachineIdPath, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.api.schemas import (
    MachineCreate,
    MachineCreated,
    MachineDetail,
    MachinePublic,
    MachineUpdate,
)

router = APIRouter(prefix="/api/v1/machines", tags=["machines"], responses=PROBLEM_RESPONSES)


def check_registered_model(model: str) -> None:
    """Refuse a model the ingest daemon could not serve, the way the request schema refuses a
    bad field: 422 problem JSON with one ``errors`` entry per problem, located at
    ``body.model`` (and the path inside the machine description, when it loads but is invalid).

    The same check as ``cranetwin machines add`` (:func:`cranetwin.protocol.machine.check_model`).

    Raises:
        RequestValidationError: the model is unknown or does not load.
    """
    from cranetwin.errors import MachineFileError
    from cranetwin.model import builtin_machines
    from cranetwin.protocol.machine import check_model

    known = builtin_machines()
    if model not in known:
        raise RequestValidationError([{
            "loc": ("body", "model"), "type": "unknown_model",
            "msg": f"unknown model {model!r}: expected one of {', '.join(known)}"}])
    try:
        check_model(model, model)
    except MachineFileError as exc:
        errors = []
        for p in exc.problems:
            path, _, msg = p.partition(": ")
            loc = ("body", "model", *(x for x in path.split(".") if x and x != "(file)"))
            errors.append({"loc": loc, "msg": msg or p, "type": "machine_description"})
        raise RequestValidationError(errors) from exc


def _names(text: str | None, what: str, allowed: tuple[str, ...] | None = None
           ) -> tuple[str, ...] | None:
    """Comma-separated names as a tuple (None: no filter); 422 for a name not in ``allowed``."""
    if text is None:
        return None
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    bad = [n for n in names if allowed is not None and n not in allowed]
    if not names or bad:
        raise RequestValidationError([{
            "loc": ("query", what), "type": "value_error",
            "msg": f"{what}={text!r}: expected comma-separated "
                   f"{', '.join(allowed) if allowed else 'names'}"}])
    return names


@router.get("", response_model=list[MachinePublic], summary="Machines with their status",
            responses={200: {"headers": {
                "Link": {"description": 'next page: `<url>; rel="next"` (absent on the last)',
                         "schema": {"type": "string"}},
                "X-Total-Count": {"description": "machines the filters keep (absent with a "
                                  "status filter or a cursor)", "schema": {"type": "integer"}},
            }}})
def list_machines(
    key: CurrentKey, services: ServicesDep, request: Request, response: Response,
    limit: Annotated[int | None, Query(ge=1, le=1000, description="machines per page "
                                       "(default: all)")] = None,
    offset: Annotated[int, Query(ge=0, le=1_000_000, description="machines to skip (after "
                                 "the filters)")] = 0,
    cursor: Annotated[str | None, Query(max_length=128, description="continue after this "
                                        "machine id (the `Link: rel=next` of the previous "
                                        "page carries it)")] = None,
    status: Annotated[str | None, Query(max_length=64, description="keep these statuses, "
                                        "comma-separated: live, idle, offline",
                                        examples=["live,idle"])] = None,
    model: Annotated[str | None, Query(max_length=1000, description="keep these machine "
                                       "description names, comma-separated",
                                       examples=["patu655"])] = None,
    bbox: Annotated[str | None, Query(max_length=200, description="location box "
                                      "min_lon,min_lat,max_lon,max_lat [deg]; machines "
                                      "without a location are left out",
                                      examples=["25.0,62.0,26.0,62.5"])] = None,
) -> list[MachinePublic]:
    """Registered machines by id: status (live/idle/offline), last seen, payload, alarms, GPS;
    filtered by status, model and location box, ``limit`` per page from ``offset`` or
    ``cursor``. Only the machines of the page are looked at in full."""
    from cranetwin.api.services import public
    from cranetwin.service.queries import MachineFilter, machines_page, parse_bbox

    flt = MachineFilter(status=_names(status, "status", ("live", "idle", "offline")),
                        model=_names(model, "model"), bbox=parse_bbox(bbox))
    page = machines_page(services.backend.list_machines(), services.fleet.machine_status, flt,
                         limit, offset, cursor)
    if page.next_cursor is not None:
        nxt = request.url.remove_query_params(["offset", "cursor", "key"]).include_query_params(
            cursor=page.next_cursor)
        response.headers["Link"] = f'<{nxt}>; rel="next"'
    if page.total is not None:
        response.headers["X-Total-Count"] = str(page.total)
    return [public(st) for st in page.items]


@router.post("", response_model=MachineCreated, status_code=status.HTTP_201_CREATED,
             summary="Register a machine (admin)",
             responses={409: {**PROBLEM_RESPONSES[404], "description": "Id already taken"}})
def create_machine(key: AdminKey, services: ServicesDep,
                   body: Annotated[MachineCreate, Body(openapi_examples={"crane": {"value": {
                       "machine_id": "crane-2", "model": "patu655", "name": "Crane 2"}}})],
                   ) -> MachineCreated:
    """Register a machine of a built-in model. The HMAC secret its sender needs is returned
    in this response only (409 if the id is taken, 422 for an unknown or invalid model, with
    the field path in ``errors``)."""
    check_registered_model(body.model)
    loc = (body.location.lat, body.location.lon) if body.location is not None else None
    rec, secret = services.backend.create_machine(body.machine_id, body.model, name=body.name,
                                                  wire_id=body.wire_id, location=loc)
    detail = services.machine_detail(rec)
    return MachineCreated(**detail.model_dump(by_alias=True), wire_id=rec.wire_id, secret=secret)


@router.patch("/{machine_id}", response_model=MachineDetail, summary="Update metadata (admin)")
def update_machine(key: AdminKey, machine: MachineDep, services: ServicesDep,
                   body: MachineUpdate) -> MachineDetail:
    """Change the display name or location; omitted fields stay."""
    loc = (body.location.lat, body.location.lon) if body.location is not None else None
    rec = services.backend.update_machine(machine.machine_id, name=body.name, location=loc)
    return services.machine_detail(rec)


@router.get("/{machine_id}", response_model=MachineDetail, summary="One machine")
def get_machine(key: CurrentKey, machine: MachineDep, services: ServicesDep) -> MachineDetail:
    """The machine, its status and the time range of its stored samples."""
    return services.machine_detail(machine)


@router.get("/{machine_id}/model", summary="Machine description (bodies, joints, cylinders…)",
            response_model=dict[str, Any])
def get_model(key: CurrentKey, machine: MachineDep, services: ServicesDep) -> dict[str, Any]:
    """The full machine description as JSON — the same fields as the machine's TOML file
    (``machine``, ``bodies`` with visuals, ``joints``, ``cylinders``, ``torque_drives``,
    ``channels``, ``load_point``, ``rated_load``, …), all SI: lengths [m], masses [kg],
    inertias [kg·m²], pressures [Pa]."""
    return services.backend.model_of(machine).model_dump(mode="json")


__all__ = ["router", "MachineIdPath"]
