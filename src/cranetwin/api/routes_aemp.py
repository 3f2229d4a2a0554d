"""ISO 15143-3 (AEMP 2.0) fleet snapshots, one equipment and time series, as XML (default) or
JSON (see :mod:`cranetwin.service.aemp`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import orjson
from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response

from cranetwin.api.deps import FleetKey, MachineIdPath, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.service import aemp
from cranetwin.service.timerange import TimeRange

router = APIRouter(prefix="/api/v1/aemp", tags=["aemp (ISO 15143-3)"],
                   responses=PROBLEM_RESPONSES)

_BASE = "https://cranetwin.example/api/v1/aemp/Fleet"
_FLEET_EXAMPLE = {
    "version": "2", "snapshotTime": "2026-11-23T10:42:00.000Z",
    "Links": [{"rel": "self", "href": f"{_BASE}/1"}, {"rel": "first", "href": f"{_BASE}/1"},
              {"rel": "last", "href": f"{_BASE}/1"}],
    "Equipment": [{
        "EquipmentHeader": {"UnitInstallDateTime": "2026-11-01T08:00:00.000Z",
                            "OEMName": "cranetwin", "Model": "patu655", "EquipmentID": "crane-1",
                            "SerialNumber": "crane-1", "PIN": "crane-1"},
        "Location": {"datetime": "2026-11-23T10:41:58.000Z", "Latitude": 62.24,
                     "Longitude": 25.75},
        "CumulativeOperatingHours": {"datetime": "2026-11-23T10:41:00.000Z", "Hour": 1004.9},
        "CumulativeIdleHours": {"datetime": "2026-11-23T10:41:00.000Z", "Hour": 311.9},
        "CumulativeLoadCount": {"datetime": "2026-11-23T10:41:00.000Z", "Count": 48211},
        "CumulativePayloadTotals": {"datetime": "2026-11-23T10:41:00.000Z",
                                    "PayloadUnits": "metric tonne", "Payload": 17420.5},
        "Extension": {"cranetwin": {"datetime": "2026-11-23T10:41:00.000Z",
                                    "RatedLoad_kg": 900.0, "MaxPayload_kg": 1012.0,
                                    "LoadSpectrumFactor": 0.21, "OverloadCount": 3,
                                    "DesignLifeUsedFraction": 0.083}},
    }],
}
_XML_EXAMPLE = aemp.to_xml("Fleet", _FLEET_EXAMPLE).decode()

FormatQuery = Annotated[Literal["xml", "json"] | None, Query(
    description="xml or json; overrides the Accept header (default: XML unless Accept "
                "prefers application/json)")]


def _doc_responses(what: str, example: dict[str, Any] | None = None) -> dict[int | str, Any]:
    json_c: dict[str, Any] = {"schema": {"type": "object"}}
    xml_c: dict[str, Any] = {"schema": {"type": "string"}}
    if example is not None:
        json_c["example"] = example
        xml_c["example"] = _XML_EXAMPLE
    return {200: {"content": {aemp.XML_MEDIA: xml_c, aemp.JSON_MEDIA: json_c},
                  "description": f"ISO 15143-3 {what} (XML by default)"}}


def _respond(request: Request, fmt: str | None, root: str, doc: dict[str, Any]) -> Response:
    kind = aemp.negotiate(request.headers.get("accept"), fmt)
    headers = {"Vary": "Accept"}
    if kind == "json":
        return Response(orjson.dumps(doc), media_type=aemp.JSON_MEDIA, headers=headers)
    return Response(aemp.to_xml(root, doc), media_type=aemp.XML_MEDIA, headers=headers)


def _base(request: Request) -> str:
    """Absolute URL of ``/api/v1/aemp/Fleet`` as the client reached the server."""
    return str(request.base_url).rstrip("/") + "/api/v1/aemp/Fleet"


@router.get("/Fleet/{page}", summary="Fleet snapshot page (fleet)",
            responses=_doc_responses("Fleet page", _FLEET_EXAMPLE), response_class=Response)
def fleet(key: FleetKey, services: ServicesDep, request: Request,
          page: Annotated[int, Path(ge=1, le=1_000_000, description="1-based page number")],
          format: FormatQuery = None) -> Response:
    """≤ 100 equipment snapshots per page, sorted by id, with absolute self/first/prev/next/last
    links; 404 for a page past the last."""
    return _respond(request, format, "Fleet", services.fleet.aemp_fleet(page, _base(request)))


@router.get("/Fleet/Equipment/ID/{machine_id}", summary="One equipment snapshot (fleet)",
            responses=_doc_responses("Equipment"), response_class=Response)
def equipment(key: FleetKey, services: ServicesDep, request: Request,
              machine_id: MachineIdPath, format: FormatQuery = None) -> Response:
    """The ISO 15143-3 snapshot of one machine (the same elements as in ``Fleet``)."""
    doc = services.fleet.aemp_equipment(machine_id, f"{_base(request)}/Equipment/ID/"
                                        f"{machine_id}")
    return _respond(request, format, "Equipment", doc)


@router.get("/Equipment/{machine_id}", summary="One equipment snapshot (fleet; alias)",
            responses=_doc_responses("Equipment"), response_class=Response)
def equipment_alias(key: FleetKey, services: ServicesDep, request: Request,
                    machine_id: MachineIdPath, format: FormatQuery = None) -> Response:
    """The same as ``/Fleet/Equipment/ID/{machine_id}``."""
    return equipment(key, services, request, machine_id, format)


@router.get("/Fleet/Equipment/ID/{machine_id}/{element}/{start}/{end}/{page}",
            summary="Time series of one equipment (fleet)",
            responses=_doc_responses("time series"), response_class=Response)
def series(
    key: FleetKey, services: ServicesDep, request: Request, machine_id: MachineIdPath,
    element: Annotated[Literal["CumulativeOperatingHours", "CumulativeIdleHours"],
                       Path(description="data element")],
    start: Annotated[str, Path(max_length=64, description="startDateUTC (ISO 8601)",
                               examples=["2026-11-01T00:00:00Z"])],
    end: Annotated[str, Path(max_length=64, description="endDateUTC (ISO 8601); must be after "
                             "`start`: `end` ≤ `start` is answered 422",
                             examples=["2026-11-30T00:00:00Z"])],
    page: Annotated[int, Path(ge=1, le=1_000_000, description="1-based page number")],
    format: FormatQuery = None,
) -> Response:
    """``element`` of one machine over [start, end]: one point per hour with processed data,
    100 per page, with absolute links."""
    rng = TimeRange.parse(start, end)
    base = f"{_base(request)}/Equipment/ID/{machine_id}/{element}/{start}/{end}"
    doc = services.fleet.aemp_series(machine_id, element, rng, page, base)
    return _respond(request, format, element, doc)
