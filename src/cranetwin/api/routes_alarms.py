"""Alarms: every machine's events with filters and paging, acknowledged and cleared by the
signed-in user (the key's name and role), kept in the database (``service.alarms``)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Path, Query

from cranetwin.api.auth import ApiKey
from cranetwin.api.deps import CurrentKey, FleetKey, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.api.params import AFTER_FROM
from cranetwin.service.errors import InvalidRequestError
from cranetwin.service.timerange import parse_time

router = APIRouter(prefix="/api/v1/alarms", tags=["alarms"])

StateQ = Literal["active", "unacknowledged", "acknowledged", "cleared", "all"]


def _list(v: list[str] | None) -> list[str] | None:
    """Repeated or comma-separated values, without empties."""
    if not v:
        return None
    out = [x.strip() for item in v for x in item.split(",") if x.strip()]
    return out or None


def _user(key: ApiKey) -> str:
    return f"{key.name or 'key ' + key.key_id} ({key.role})"


@router.get("", summary="Events of every machine with their alarm state, newest first",
            responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401, 422)})
def list_alarms(
    key: CurrentKey, services: ServicesDep,
    machine: Annotated[list[str] | None, Query(description="machine id(s), repeated or comma "
                                                "separated")] = None,
    severity: Annotated[list[str] | None, Query(description="info, warning, critical")] = None,
    kind: Annotated[list[str] | None, Query(description="event kind(s), e.g. overload, "
                                             "machine_offline, data_gap")] = None,
    from_: Annotated[str | None, Query(alias="from", description="from (epoch s or ISO 8601)")]
    = None,
    to: Annotated[str | None, Query(description="to, exclusive (epoch s or ISO 8601); with "
                                    f"`from`, {AFTER_FROM}")] = None,
    state: Annotated[StateQ, Query(description="active: not cleared; unacknowledged; "
                                   "acknowledged (not cleared); cleared; all")] = "active",
    limit: Annotated[int, Query(ge=1, le=500, description="items per page")] = 50,
    offset: Annotated[int, Query(ge=0, le=1_000_000, description="items skipped")] = 0,
) -> dict[str, Any]:
    """``{total, offset, limit, kinds, items: [{id, machine_id, t, kind, severity, message,
    evidence, acknowledged: {by, at}|null, cleared: {by, at}|null}]}``."""
    t0 = parse_time(from_, "from") if from_ else None
    t1 = parse_time(to, "to") if to else None
    if t0 is not None and t1 is not None and not t1 > t0:  # 422, as on every ranged route
        raise InvalidRequestError("Invalid range", f"to ({to}) must be after from ({from_})")
    return services.alarms.list(machine_ids=_list(machine), severities=_list(severity),
                                kinds=_list(kind), t0_s=t0, t1_s=t1, state=state, limit=limit,
                                offset=offset)


EventId = Annotated[int, Path(ge=1, le=2**62, description="event id (`id` of the list)")]


@router.post("/{event_id}/acknowledge", summary="Acknowledge an event (role fleet)",
             responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401, 403, 404)})
def acknowledge(event_id: EventId, key: FleetKey, services: ServicesDep) -> dict[str, Any]:
    """Marks the event acknowledged by the caller now (a second time keeps the first)."""
    return services.alarms.act(event_id, "acknowledge", _user(key))


@router.post("/{event_id}/clear", summary="Clear an event (role fleet)",
             responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401, 403, 404)})
def clear(event_id: EventId, key: FleetKey, services: ServicesDep) -> dict[str, Any]:
    """Marks the event cleared (and acknowledged, if it was not) by the caller now."""
    return services.alarms.act(event_id, "clear", _user(key))


fleet_router = APIRouter(prefix="/api/v1/fleet", tags=["alarms"])


@fleet_router.get("/figures", summary="Fleet-wide figures: working hours, lifts, tonnes, "
                  "today's alarms",
                  responses={k: v for k, v in PROBLEM_RESPONSES.items() if k in (401,)})
def fleet_figures(key: CurrentKey, services: ServicesDep) -> dict[str, Any]:
    """Per machine and in total: working hours [h], lifts, tonnes lifted [t] (the twin worker's
    counters); in total also today's warning and critical events (since 00:00 UTC)."""
    from cranetwin.service.fleetfigures import fleet_figures as figures

    return figures(services.backend)
