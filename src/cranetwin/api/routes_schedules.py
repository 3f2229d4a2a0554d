"""Service schedules of a machine: what is due when (any key), set, mark done and delete items
(role fleet: fleet managers and admins). Each route calls one function of
:mod:`cranetwin.service.schedules`."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Path, status
from pydantic import BaseModel, ConfigDict, Field

from cranetwin.api.auth import ApiKey
from cranetwin.api.deps import CurrentKey, FleetKey, MachineDep, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.service import schedules as svc
from cranetwin.service.timerange import parse_time

router = APIRouter(prefix="/api/v1/machines/{machine_id}/schedules", tags=["schedules"],
                   responses={k: v for k, v in PROBLEM_RESPONSES.items()
                              if k in (401, 404, 422, 503)})
WRITE: dict[int | str, dict[str, Any]] = {k: v for k, v in PROBLEM_RESPONSES.items() if k in (403,)}



def _user(key: ApiKey) -> str:
    """Who did it, as the alarms name the user: the key's name (or id) and role."""
    return f"{key.name or 'key ' + key.key_id} ({key.role})"


Basis = Literal["operating_hours", "lifts", "damage_fraction", "calendar_days"]
ItemPath = Annotated[str, Path(min_length=1, max_length=200, description="maintenance item "
                               "name (unique per machine)", examples=["hydraulic oil filter"])]


class ScheduleSet(BaseModel):
    """An item's interval and when it was last done."""

    model_config = ConfigDict(extra="forbid")

    basis: Basis = Field(description="operating_hours [h], lifts (work cycles), "
                         "damage_fraction (Miner damage D of a fatigue detail) or calendar_days")
    interval: float = Field(gt=0, le=1e9, description="interval in the basis' unit (at most "
                            "1 for damage_fraction, 36525 for calendar_days)")
    detail: str | None = Field(None, max_length=128, description="fatigue detail of a "
                               "damage_fraction item (default: the most damaged detail)")
    last_done_value: float | None = Field(None, ge=0, le=1e12, description="the basis' "
                                          "counter when last done (default: the counter now)")
    last_done_at: str | None = Field(None, max_length=64, description="when last done, epoch "
                                     "s or ISO 8601 (default: now)")


class DoneBody(BaseModel):
    """When an item was done (defaults: now, at the counter now)."""

    model_config = ConfigDict(extra="forbid")

    value: float | None = Field(None, ge=0, le=1e12, description="the basis' counter when done")
    at: str | None = Field(None, max_length=64, description="when done, epoch s or ISO 8601")


@router.get("", summary="Service schedule: what is due when")
def list_schedule(key: CurrentKey, machine: MachineDep, services: ServicesDep) -> dict[str, Any]:
    """``{machine_id, counters_until, items: [{item, basis, interval, unit, detail, last_done:
    {value, at, by}, created: {at, by}, current, due_at: {value, at}, remaining, rate_per_day,
    status: ok|due|overdue|unknown, event_id}]}``; ``due_at.at`` is estimated from the
    counter's growth over the last 7 days."""
    return svc.list_schedule(services.backend, machine.machine_id)


@router.put("/{item}", summary="Set a maintenance item (role fleet)", responses=WRITE)
def put_item(item: ItemPath, key: FleetKey, machine: MachineDep, services: ServicesDep,
             body: Annotated[ScheduleSet, Body(openapi_examples={"oil": {"value": {
                 "basis": "operating_hours", "interval": 500}}})]) -> dict[str, Any]:
    """Create or replace the item; returns its status (as one item of the list)."""
    done_s = parse_time(body.last_done_at, "last_done_at") if body.last_done_at else None
    inp = svc.ScheduleInput(body.basis, body.interval, body.detail, body.last_done_value, done_s)
    return svc.set_schedule(services.backend, machine.machine_id, item, inp, _user(key))


@router.post("/{item}/done", summary="Mark a maintenance item done (role fleet)",
             responses=WRITE)
def item_done(item: ItemPath, key: FleetKey, machine: MachineDep, services: ServicesDep,
              body: Annotated[DoneBody | None, Body()] = None) -> dict[str, Any]:
    """Records the item done (the next interval counts from here) and clears the alarm of its
    ``service_due`` event; returns its status."""
    b = body or DoneBody()
    at = parse_time(b.at, "at") if b.at else None
    return svc.mark_done(services.backend, machine.machine_id, item, _user(key), b.value, at)


@router.delete("/{item}", status_code=status.HTTP_204_NO_CONTENT,
               summary="Delete a maintenance item (role fleet)", responses=WRITE)
def delete_item(item: ItemPath, key: FleetKey, machine: MachineDep,
                services: ServicesDep) -> None:
    """Deletes the item (its stored events stay)."""
    svc.delete_schedule(services.backend, machine.machine_id, item)
