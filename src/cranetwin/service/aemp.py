"""ISO 15143-3 (AEMP 2.0) telematics feed: fleet snapshots, one equipment, time series; XML (the
default) or JSON, plus the cranetwin crane extension in its own namespace.

Documents (element names and casing as ISO 15143-3 and the AEMP 2.0 feeds of Trackunit,
Takeuchi and Deere serve them; the ISO text and XSD could not be obtained here, so the element
list below is what the tests check):

* ``Fleet`` (attributes ``version``, ``snapshotTime``): ``Links`` (``rel``, ``href``, absolute
  URLs) ``self``/``first``/``prev``/``next``/``last``, then ≤ 100 ``Equipment`` by id;
* ``Equipment``: ``EquipmentHeader`` (``UnitInstallDateTime``, ``OEMName``, ``Model``,
  ``EquipmentID``, ``SerialNumber``, ``PIN``), then data elements, each with a ``datetime``
  attribute (the time its value was observed):

  - ``Location``: ``Latitude``, ``Longitude`` [deg, WGS 84] (``datetime``: the time of the
    status report or of the REST update that set it);
  - ``CumulativeOperatingHours``: ``Hour`` — the hour meter the machine reports in its status
    datagrams (protocol ``operating_hours``), at that report's time; for a machine that reports
    none, the time the twin worker counted it operating [h];
  - ``CumulativeIdleHours``: ``Hour`` — time with samples but no motion [h];
  - ``CumulativeLoadCount``: ``Count`` — lifts (payload above the lift threshold, then
    released);
  - ``CumulativePayloadTotals``: ``PayloadUnits`` (``metric tonne``), ``Payload`` [t];
* time series ``{element}`` (``CumulativeOperatingHours``, ``CumulativeIdleHours``) of one
  equipment over [start, end], 100 points per page, one point per hour with processed data
  (the cumulative value at the end of the hour's last processed minute). Operating hours
  follow the twin worker's counted time, offset so that they equal the machine's hour meter at
  its newest report when it reports one.

Crane extension (not ISO 15143-3; a consumer that does not know it ignores it): XML
``<ct:CraneExtension xmlns:ct="urn:cranetwin:aemp-extension:1" datetime=…>``, JSON
``"Extension": {"cranetwin": {…}}``, with ``RatedLoad_kg``, ``MaxPayload_kg``,
``LoadSpectrumFactor`` (kp = Σ (P_i/P_max)³ / C over the work cycles, ISO 4301-1, the same
work cycles and ratios as every report, from the twin worker's stored analytics),
``OverloadCount`` (lifts whose peak payload exceeded the rated load) and
``DesignLifeUsedFraction`` (ISO 12482 S/(C_T·kp_design), prior use taken as zero; null when the
machine has no classification).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any
from xml.etree import ElementTree as ET

from cranetwin.model import Machine
from cranetwin.service.timerange import iso

PAGE_SIZE = 100
VERSION = "2"
ISO_NS = "http://standards.iso.org/iso/15143/-3"
EXT_NS = "urn:cranetwin:aemp-extension:1"
EXT_PREFIX = "ct"
SERIES = ("CumulativeOperatingHours", "CumulativeIdleHours")
"""Data elements served as time series."""
ATTRIBUTES = frozenset({"datetime", "version", "snapshotTime"})
"""Keys written as XML attributes (everything else is an element)."""
XML_MEDIA = "application/xml"
JSON_MEDIA = "application/json"


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
        operating_s: Time the worker counted operating [s].
        idle_s: Time with samples but no motion [s].
        load_count: Completed lifts.
        payload_total_kg: Sum of lift peak payloads [kg].
        load_cube_sum: Σ (peak / rated)³ over the lifts.
        overloads: Lifts above the rated load.
        max_payload_kg: Largest lift peak [kg].
        duty: (work cycles, Σ (P_i/P_max)³) of the machine's processed history from the same
            work-cycle detection as the reports, or None (then kp and design life used are null).
        hour_meter: (hour meter [h], report time [s]) the machine reported, or None.
        install_t_s: When the unit was installed: registration time, else the first stored
            sample [s], or None.
        serial_number: Serial number (metadata ``serial_number``, else the id).
        pin: Product identification number (metadata ``pin``, else the serial number).
        oem_name: Manufacturer (metadata ``oem_name``, else ``cranetwin``).
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
    hour_meter: tuple[float, float] | None = None
    install_t_s: float | None = None
    serial_number: str | None = None
    pin: str | None = None
    oem_name: str = "cranetwin"


def rated_load_kg(machine: Machine) -> float | None:
    """Largest payload of the rated-load chart [kg]; None (null) without a chart (unknown)."""
    rl = machine.rated_load
    return None if rl is None else float(max(rl.payload_kg))


def header(fig: EquipmentFigures) -> dict[str, Any]:
    """``EquipmentHeader`` of one machine (elements in the standard's order)."""
    serial = fig.serial_number or fig.machine_id
    return {"UnitInstallDateTime": iso(fig.install_t_s), "OEMName": fig.oem_name,
            "Model": fig.model, "EquipmentID": fig.machine_id, "SerialNumber": serial,
            "PIN": fig.pin or serial}


def equipment(fig: EquipmentFigures) -> dict[str, Any]:
    """One ``Equipment`` snapshot object (JSON form; :func:`to_xml` writes it as XML)."""
    out: dict[str, Any] = {"EquipmentHeader": header(fig)}
    if fig.location is not None:
        lat, lon, t = fig.location
        out["Location"] = {"datetime": iso(t), "Latitude": lat, "Longitude": lon}
    if fig.hour_meter is not None:
        out["CumulativeOperatingHours"] = {"datetime": iso(fig.hour_meter[1]),
                                           "Hour": round(fig.hour_meter[0], 3)}
    if fig.counters_t_s is not None:
        when = iso(fig.counters_t_s)
        out.setdefault("CumulativeOperatingHours",
                       {"datetime": when, "Hour": round(fig.operating_s / 3600.0, 3)})
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


def links(page: int, last: int, base_url: str) -> list[dict[str, str]]:
    """``Links`` of page ``page`` of ``last`` under ``base_url`` (absolute): self, first,
    prev, next, last."""
    out = [{"rel": "self", "href": f"{base_url}/{page}"},
           {"rel": "first", "href": f"{base_url}/1"}]
    if page > 1:
        out.append({"rel": "prev", "href": f"{base_url}/{min(page - 1, last)}"})
    if page < last:
        out.append({"rel": "next", "href": f"{base_url}/{page + 1}"})
    out.append({"rel": "last", "href": f"{base_url}/{last}"})
    return out


fleet_links = links


def fleet_page(items: list[EquipmentFigures], page: int, n_total: int, base_url: str,
               snapshot_t_s: float) -> dict[str, Any]:
    """``Fleet`` page ``page`` (1-based) holding ``items`` (≤ :data:`PAGE_SIZE`) of a fleet of
    ``n_total`` equipment; ``base_url`` is the absolute URL of ``…/Fleet``."""
    last = max(1, math.ceil(n_total / PAGE_SIZE))
    return {"version": VERSION, "snapshotTime": iso(snapshot_t_s),
            "Links": links(page, last, base_url),
            "Equipment": [equipment(f) for f in items]}


def equipment_document(fig: EquipmentFigures, self_url: str,
                       snapshot_t_s: float) -> dict[str, Any]:
    """The single-equipment document (root ``Equipment``)."""
    return {"version": VERSION, "snapshotTime": iso(snapshot_t_s),
            "Links": [{"rel": "self", "href": self_url}], **equipment(fig)}


def hourly_points(minutes: list[tuple[float, float, float, float]], element: str,
                  before: tuple[float, float], offset_h: float = 0.0) -> list[dict[str, Any]]:
    """Time-series points of ``element`` from the worker's minute windows (start, end,
    operating s, idle s): one per hour with windows, at the end of its last window, cumulative
    from ``before`` (operating s, idle s before the first window) plus ``offset_h``."""
    col = 2 if element == "CumulativeOperatingHours" else 3
    total = before[col - 2]
    out: list[dict[str, Any]] = []
    hour = None
    for w in minutes:
        total += w[col]
        h = math.floor(w[0] / 3600.0)
        point = {"datetime": iso(w[1]), "Hour": round(total / 3600.0 + offset_h, 3)}
        if h == hour:
            out[-1] = point
        else:
            out.append(point)
            hour = h
    return out


def series_document(element: str, points: list[dict[str, Any]], page: int, base_url: str,
                    snapshot_t_s: float) -> dict[str, Any]:
    """Page ``page`` of a time series (root ``element``; JSON: the points under the element's
    lowerCamel name, as AEMP 2.0 feeds serve them)."""
    last = max(1, math.ceil(len(points) / PAGE_SIZE))
    items = points[(page - 1) * PAGE_SIZE: page * PAGE_SIZE]
    return {"version": VERSION, "snapshotTime": iso(snapshot_t_s),
            "Links": links(page, last, base_url),
            element[0].lower() + element[1:]: items}


# -- XML -----------------------------------------------------------------------------------------
def _text(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _fill(el: ET.Element, data: dict[str, Any], ns: str) -> None:
    for k, v in data.items():
        if v is None:
            continue
        if k in ATTRIBUTES:
            el.set(k, _text(v))
        elif k == "Extension" and isinstance(v, dict):
            for body in v.values():
                ext = ET.SubElement(el, f"{{{EXT_NS}}}CraneExtension")
                _fill(ext, body, EXT_NS)
        elif isinstance(v, list):
            for item in v:
                child = ET.SubElement(el, f"{{{ns}}}{k}")
                if isinstance(item, dict):
                    _fill(child, item, ns)
                else:
                    child.text = _text(item)
        elif isinstance(v, dict):
            _fill(ET.SubElement(el, f"{{{ns}}}{k}"), v, ns)
        else:
            ET.SubElement(el, f"{{{ns}}}{k}").text = _text(v)


def to_xml(root: str, doc: dict[str, Any]) -> bytes:
    """``doc`` (the JSON form) as an XML document with root element ``root`` in the ISO
    15143-3 namespace; ``datetime``, ``version`` and ``snapshotTime`` become attributes, lists
    repeated elements, the crane extension ``ct:CraneExtension``; a time series' lowerCamel
    point list is written as repeated ``root`` elements."""
    ET.register_namespace("", ISO_NS)
    ET.register_namespace(EXT_PREFIX, EXT_NS)
    el = ET.Element(f"{{{ISO_NS}}}{root}")
    key = root[0].lower() + root[1:]
    if key in doc:  # a time series: the points are <root datetime=…> elements
        doc = {**{k: v for k, v in doc.items() if k != key}, root: doc[key]}
    _fill(el, doc, ISO_NS)
    out: bytes = ET.tostring(el, encoding="utf-8", xml_declaration=True)
    return out


def negotiate(accept: str | None, fmt: str | None) -> str:
    """``"xml"`` or ``"json"``: ``fmt`` when given, else the ``Accept`` header's preferred
    one of XML (``application/xml``, ``text/xml``) and JSON; XML when neither is asked for."""
    if fmt is not None:
        return fmt
    best, best_q = "xml", 0.0
    for part in (accept or "").split(","):
        media, _, params = part.strip().partition(";")
        q = 1.0
        for p in params.split(";"):
            name, _, val = p.strip().partition("=")
            if name == "q":
                try:
                    q = float(val)
                except ValueError:
                    q = 0.0
        kind = {"application/json": "json", "application/xml": "xml",
                "text/xml": "xml"}.get(media.strip().lower())
        if kind is not None and q > best_q:  # the first listed wins a tie
            best, best_q = kind, q
    return best
