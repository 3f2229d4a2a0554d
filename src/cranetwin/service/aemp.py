"""ISO 15143-3 (AEMP 2.0) telematics snapshots in JSON, plus the cranetwin crane extension.

Conformant core per equipment (element names as in ISO 15143-3; each element carries its own
``datetime``, the time its value was observed):

* ``EquipmentHeader``: ``OEMName``, ``Model``, ``EquipmentID``, ``SerialNumber``;
* ``Location``: ``Latitude``, ``Longitude`` [deg, WGS 84];
* ``CumulativeOperatingHours``: ``Hour`` — time with the machine reporting samples [h];
* ``CumulativeIdleHours``: ``Hour`` — part of it with no motion [h];
* ``CumulativeLoadCount``: ``Count`` — lifts (payload above the lift threshold, then released);
* ``CumulativePayloadTotals``: ``PayloadUnits`` (``"metric tonne"``), ``Payload`` — sum of the
  peak payload of every lift [t].

Elements without an observation are omitted (the standard makes every element optional).
``Fleet`` pages are 1-based, hold ≤ 100 equipment and carry ``Links`` with ``rel`` = ``self``,
``first``, ``prev``, ``next``, ``last``.

Extension (not part of ISO 15143-3; consumers that do not know it ignore it): each equipment
has ``"Extension": {"cranetwin": {...}}`` with ``datetime``, ``MaxPayload_kg``,
``LoadSpectrumFactor`` (kp = Σ (P_i/P_max)³ / C over the work cycles, ISO 4301-1, with P_i the
mean payload of work cycle i and P_max the rated payload at its reach — the same work cycles and
ratios as every report, from the twin worker's stored analytics),
``OverloadCount`` (lifts whose peak payload exceeded the rated load), ``RatedLoad_kg`` and
``DesignLifeUsedFraction`` (ISO 12482 S/(C_T·kp_design) with S = Σ (P_i/P_max)³, prior use
taken as zero; null when the machine has no classification).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from cranetwin.model import Machine
from cranetwin.service.timerange import iso

PAGE_SIZE = 100


@dataclass(frozen=True)
class EquipmentFigures:
    """What the service knows of one machine for a snapshot.

    Attributes:
        machine_id: Identifier (``EquipmentID``).
        name: Display name.
        model: Machine description name.
        machine: The description (rated load, classification).
        location: (lat, lon) [deg] and its time [s], or None.
        counters_t_s: Time up to which the counters below are complete [s], or None if the twin
            worker has not processed anything.
        operating_s: Time with samples [s].
        idle_s: Time with samples but no motion [s].
        load_count: Completed lifts.
        payload_total_kg: Sum of lift peak payloads [kg].
        load_cube_sum: Σ (peak / rated)³ over the lifts.
        overloads: Lifts above the rated load.
        max_payload_kg: Largest lift peak [kg].
        duty: (work cycles, Σ (P_i/P_max)³) of the machine's processed history from the same
            work-cycle detection as the reports (:class:`cranetwin.service.history.DutyToDate`),
            or None (then kp and design life used are null).
    """

    machine_id: str
    name: str
    model: str
    machine: Machine
    location: tuple[float, float, float] | None
    counters_t_s: float | None
    operating_s: float
    idle_s: float
    load_count: int
    payload_total_kg: float
    load_cube_sum: float
    overloads: int
    max_payload_kg: float
    duty: tuple[int, float] | None = None


def rated_load_kg(machine: Machine) -> float:
    """Largest payload of the rated-load chart [kg]."""
    return float(max(machine.rated_load.payload_kg))


def equipment(fig: EquipmentFigures) -> dict[str, Any]:
    """One ``Equipment`` snapshot object."""
    out: dict[str, Any] = {
        "EquipmentHeader": {"OEMName": "cranetwin", "Model": fig.model,
                            "EquipmentID": fig.machine_id, "SerialNumber": fig.machine_id},
    }
    if fig.location is not None:
        lat, lon, t = fig.location
        out["Location"] = {"datetime": iso(t), "Latitude": lat, "Longitude": lon}
    if fig.counters_t_s is not None:
        when = iso(fig.counters_t_s)
        out["CumulativeOperatingHours"] = {"datetime": when,
                                           "Hour": round(fig.operating_s / 3600.0, 3)}
        out["CumulativeIdleHours"] = {"datetime": when, "Hour": round(fig.idle_s / 3600.0, 3)}
        out["CumulativeLoadCount"] = {"datetime": when, "Count": int(fig.load_count)}
        out["CumulativePayloadTotals"] = {"datetime": when, "PayloadUnits": "metric tonne",
                                          "Payload": round(fig.payload_total_kg / 1000.0, 4)}
        # kp and design life used from the reports' work cycles (one answer: the API analytics
        # and the CLI report of [first minute, counters time) give the same figures)
        kp = used = None
        if fig.duty is not None and fig.duty[0] > 0:
            kp = fig.duty[1] / fig.duty[0]
            cls = fig.machine.classification
            if cls is not None:
                used = fig.duty[1] / (cls.design_total_cycles * cls.design_spectrum_factor)
        out["Extension"] = {"cranetwin": {
            "datetime": when,
            "RatedLoad_kg": rated_load_kg(fig.machine),
            "MaxPayload_kg": round(fig.max_payload_kg, 1),
            "LoadSpectrumFactor": None if kp is None else round(kp, 5),
            "OverloadCount": int(fig.overloads),
            "DesignLifeUsedFraction": None if used is None else float(f"{used:.6g}"),
        }}
    return out


def fleet_links(page: int, last: int, base_url: str) -> list[dict[str, str]]:
    """``Links`` of Fleet page ``page`` of ``last``: self, first, prev, next, last."""
    links = [{"rel": "self", "href": f"{base_url}/{page}"},
             {"rel": "first", "href": f"{base_url}/1"}]
    if page > 1:
        links.append({"rel": "prev", "href": f"{base_url}/{min(page - 1, last)}"})
    if page < last:
        links.append({"rel": "next", "href": f"{base_url}/{page + 1}"})
    links.append({"rel": "last", "href": f"{base_url}/{last}"})
    return links


def fleet_page(items: list[EquipmentFigures], page: int, n_total: int, base_url: str,
               snapshot_t_s: float) -> dict[str, Any]:
    """``Fleet`` page ``page`` (1-based) holding ``items`` (≤ :data:`PAGE_SIZE`) of a fleet of
    ``n_total`` equipment."""
    last = max(1, math.ceil(n_total / PAGE_SIZE))
    return {"Links": fleet_links(page, last, base_url), "Version": "2",
            "SnapshotTime": iso(snapshot_t_s), "Equipment": [equipment(f) for f in items]}
