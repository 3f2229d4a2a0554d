"""Machines: list, register, update, one machine, its description (geometry for the 3D view)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, status
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


@router.get("", response_model=list[MachinePublic], summary="All machines with their status")
def list_machines(key: CurrentKey, services: ServicesDep) -> list[MachinePublic]:
    """Every registered machine: status (live/idle/offline), last seen, payload, alarms, GPS."""
    return [services.machine_public(rec) for rec in services.backend.list_machines()]


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
