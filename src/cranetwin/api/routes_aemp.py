"""ISO 15143-3 (AEMP 2.0) fleet and equipment snapshots (see :mod:`cranetwin.service.aemp`)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Request

from cranetwin.api.deps import FleetKey, MachineIdPath, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES

router = APIRouter(prefix="/api/v1/aemp", tags=["aemp (ISO 15143-3)"],
                   responses=PROBLEM_RESPONSES)

_FLEET_EXAMPLE = {
    "Links": [{"rel": "self", "href": "/api/v1/aemp/Fleet/1"},
              {"rel": "first", "href": "/api/v1/aemp/Fleet/1"},
              {"rel": "last", "href": "/api/v1/aemp/Fleet/1"}],
    "Version": "2", "SnapshotTime": "2026-11-23T10:42:00.000Z",
    "Equipment": [{
        "EquipmentHeader": {"OEMName": "cranetwin", "Model": "patu655",
                            "EquipmentID": "crane-1", "SerialNumber": "crane-1"},
        "Location": {"datetime": "2026-11-23T10:41:58.000Z", "Latitude": 62.24,
                     "Longitude": 25.75},
        "CumulativeOperatingHours": {"datetime": "2026-11-23T10:41:00.000Z", "Hour": 1523.2},
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


@router.get("/Fleet/{page}", summary="Fleet snapshot page (fleet)",
            responses={200: {"content": {"application/json": {"example": _FLEET_EXAMPLE}},
                             "description": "ISO 15143-3 Fleet page"}},
            response_model=dict[str, Any])
def fleet(key: FleetKey, services: ServicesDep, request: Request,
          page: Annotated[int, Path(ge=1, le=1_000_000, description="1-based page number")],
          ) -> dict[str, Any]:
    """≤ 100 equipment snapshots per page, sorted by id, with self/first/prev/next/last links;
    404 for a page past the last."""
    base = request.scope.get("root_path", "") + "/api/v1/aemp/Fleet"
    return services.fleet.aemp_fleet(page, base)


@router.get("/Equipment/{machine_id}", summary="One equipment snapshot (fleet)",
            response_model=dict[str, Any])
def equipment(key: FleetKey, services: ServicesDep, machine_id: MachineIdPath) -> dict[str, Any]:
    """The ISO 15143-3 snapshot of one machine (same elements as in ``Fleet``)."""
    return services.fleet.aemp_equipment(machine_id)
