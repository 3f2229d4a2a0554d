"""ISO 15143-3 (AEMP 2.0) feed: XML by default and JSON on request, the standard's element names
and casing, absolute links, the equipment header, the reported hour meter, datetimes, and the
time-series endpoints — checked against the element list below (no published XSD could be
obtained here).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from xml.etree import ElementTree as ET

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.service import aemp
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

pytestmark = pytest.mark.timeout(240)

T0 = 1795420800.0  # 2026-11-23T08:00:00Z
MID = "crane-1"
NS = "{" + aemp.ISO_NS + "}"
EXT = "{" + aemp.EXT_NS + "}"

# The ISO 15143-3 elements this feed may write, per parent (children in the standard's order),
# and the attributes each may carry.
CHILDREN: dict[str, list[str]] = {
    "Fleet": ["Links", "Equipment"],
    "Links": ["rel", "href"],
    "Equipment": ["Links", "EquipmentHeader", "Location", "CumulativeOperatingHours",
                  "CumulativeIdleHours", "CumulativeLoadCount", "CumulativePayloadTotals"],
    "EquipmentHeader": ["UnitInstallDateTime", "OEMName", "Model", "EquipmentID",
                        "SerialNumber", "PIN"],
    "Location": ["Latitude", "Longitude"],
    "CumulativeOperatingHours": ["Links", "CumulativeOperatingHours", "Hour"],
    "CumulativeIdleHours": ["Links", "CumulativeIdleHours", "Hour"],
    "CumulativeLoadCount": ["Count"],
    "CumulativePayloadTotals": ["PayloadUnits", "Payload"],
}
ROOT_ATTRS = {"version", "snapshotTime"}
DATA_ELEMENTS = {"Location", "CumulativeOperatingHours", "CumulativeIdleHours",
                 "CumulativeLoadCount", "CumulativePayloadTotals"}


def _dt(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def check_element(el: ET.Element, root: bool = False) -> None:
    """``el`` and its children against the element list: names and namespace, order, the
    ``datetime`` attribute on data elements (an xs:dateTime), only the crane extension in its
    own namespace."""
    assert el.tag.startswith(NS), el.tag
    name = el.tag[len(NS):]
    allowed = CHILDREN.get(name, [])
    order = []
    for child in el:
        if child.tag.startswith(EXT):
            assert name == "Equipment" and child.tag == f"{EXT}CraneExtension"
            assert child.get("datetime") is not None
            continue
        cname = child.tag[len(NS):]
        assert cname in allowed, f"{cname} not allowed in {name}"
        order.append(allowed.index(cname))
        check_element(child)
    assert order == sorted(order), f"children of {name} out of order"
    attrs = set(el.attrib)
    if root:
        assert attrs == ROOT_ATTRS, attrs
        _dt(el.attrib["snapshotTime"])
    elif name in DATA_ELEMENTS and not list(el.iter(f"{NS}Links")):
        assert attrs == {"datetime"}, (name, attrs)
        assert _dt(el.attrib["datetime"]) > 1.0e9  # never 1970
    else:
        assert not attrs, (name, attrs)


@dataclass
class Ctx:
    client: TestClient
    services: Services
    key: str
    registered_s: float

    def get(self, path: str, **kw: Any) -> Any:
        headers = {"X-API-Key": self.key, **kw.pop("headers", {})}
        return self.client.get(path, headers=headers, **kw)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ctx]:
    url = f"sqlite:///{tmp_path_factory.mktemp('aemp') / 'api.db'}"
    app = create_app(Settings(database_url=url, worker_in_process=False))
    machine = load_machine("patu655")
    with TestClient(app) as client:
        services: Services = app.state.services
        admin = services.backend.create_key("admin", "a")[1]
        key = services.backend.create_key("fleet", "f")[1]
        t_reg = time.time()
        for mid in (MID, "crane-2"):
            r = client.post("/api/v1/machines", headers={"X-API-Key": admin},
                            json={"machine_id": mid, "model": "patu655",
                                  "location": {"lat": 62.24, "lon": 25.75}})
            assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        services.backend.store.write_blocks(list(tiled_blocks(MID, machine, T0, 240.0, 1.0,
                                                              base=base)))
        TwinWorker(services.backend, services.settings, services.metrics,
                   services.fleet.replayer).catch_up(services.backend.machine(MID))
        # crane-2 reports its hour meter in a status datagram
        services.backend.store.update_status("crane-2", T0 + 100.0, operating_hours=1004.9)
        yield Ctx(client, services, key, t_reg)


def test_xml_by_default_and_json_on_request(ctx: Ctx) -> None:
    r = ctx.get("/api/v1/aemp/Fleet/1")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/xml")
    root = ET.fromstring(r.content)
    assert root.tag == f"{NS}Fleet"
    check_element(root, root=True)
    for accept, kind in [("application/json", "json"), ("application/xml", "xml"),
                         ("text/xml", "xml"), ("*/*", "xml"),
                         ("application/xml;q=0.5, application/json", "json"),
                         ("application/json;q=0.2, text/xml;q=0.9", "xml")]:
        r = ctx.get("/api/v1/aemp/Fleet/1", headers={"Accept": accept})
        assert r.headers["content-type"].startswith(f"application/{kind}"), accept
    r = ctx.get("/api/v1/aemp/Fleet/1", params={"format": "json"},
                headers={"Accept": "application/xml"})
    assert r.headers["content-type"].startswith("application/json")
    j = r.json()
    assert set(j) == {"version", "snapshotTime", "Links", "Equipment"}
    assert ctx.get("/api/v1/aemp/Fleet/1", params={"format": "yaml"}).status_code == 422


def test_links_are_absolute_with_rel_and_href(ctx: Ctx) -> None:
    root = ET.fromstring(ctx.get("/api/v1/aemp/Fleet/1").content)
    links = {ln.findtext(f"{NS}rel"): ln.findtext(f"{NS}href")
             for ln in root.findall(f"{NS}Links")}
    assert links["self"] == "http://testserver/api/v1/aemp/Fleet/1"
    assert set(links) == {"self", "first", "last"}
    j = ctx.get("/api/v1/aemp/Fleet/1", params={"format": "json"}).json()
    assert all(ln["href"].startswith("http://testserver/") for ln in j["Links"])


def test_equipment_header_hour_meter_and_datetimes(ctx: Ctx) -> None:
    r = ctx.get(f"/api/v1/aemp/Fleet/Equipment/ID/{MID}")
    root = ET.fromstring(r.content)
    assert root.tag == f"{NS}Equipment"
    check_element(root, root=True)
    hdr = root.find(f"{NS}EquipmentHeader")
    assert hdr is not None
    assert [c.tag[len(NS):] for c in hdr] == CHILDREN["EquipmentHeader"]
    assert hdr.findtext(f"{NS}PIN") == MID and hdr.findtext(f"{NS}EquipmentID") == MID
    install = _dt(hdr.findtext(f"{NS}UnitInstallDateTime") or "")
    assert ctx.registered_s - 1 <= install <= time.time()
    loc = root.find(f"{NS}Location")
    assert loc is not None  # registered over REST: its time is the registration time
    assert ctx.registered_s - 1 <= _dt(loc.attrib["datetime"]) <= time.time()
    ext = root.find(f"{EXT}CraneExtension")
    assert ext is not None and float(ext.findtext(f"{EXT}RatedLoad_kg") or 0) > 0
    # no hour meter reported: the worker's counted operating time
    hours = root.find(f"{NS}CumulativeOperatingHours")
    assert hours is not None and float(hours.findtext(f"{NS}Hour") or -1) == pytest.approx(
        180 / 3600, abs=1e-3)
    # the machine's hour meter when it reports one, at the report's time
    j = ctx.get("/api/v1/aemp/Fleet/Equipment/ID/crane-2",
                headers={"Accept": "application/json"}).json()
    assert j["CumulativeOperatingHours"] == {"datetime": "2026-11-23T08:01:40.000Z",
                                             "Hour": 1004.9}
    # the position was set at registration (the status report carried none and is older)
    assert ctx.registered_s - 1 <= _dt(j["Location"]["datetime"]) <= time.time()
    same = ctx.get(f"/api/v1/aemp/Equipment/{MID}", params={"format": "json"}).json()
    assert same["EquipmentHeader"]["EquipmentID"] == MID
    assert ctx.get("/api/v1/aemp/Fleet/Equipment/ID/nope").status_code == 404


def test_time_series_endpoints(ctx: Ctx) -> None:
    base = f"/api/v1/aemp/Fleet/Equipment/ID/{MID}"
    r = ctx.get(f"{base}/CumulativeOperatingHours/2026-11-23T00:00:00Z/2026-11-24T00:00:00Z/1")
    assert r.status_code == 200, r.text
    root = ET.fromstring(r.content)
    assert root.tag == f"{NS}CumulativeOperatingHours"
    check_element(root, root=True)
    points = root.findall(f"{NS}CumulativeOperatingHours")
    assert len(points) == 1  # one hour of processed minutes
    assert float(points[0].findtext(f"{NS}Hour") or -1) == pytest.approx(180 / 3600, abs=1e-3)
    assert _dt(points[0].attrib["datetime"]) == T0 + 180
    links = {ln.findtext(f"{NS}rel"): ln.findtext(f"{NS}href")
             for ln in root.findall(f"{NS}Links")}
    assert links["self"] == (f"http://testserver{base}/CumulativeOperatingHours/"
                             "2026-11-23T00:00:00Z/2026-11-24T00:00:00Z/1")
    j = ctx.get(f"{base}/CumulativeIdleHours/{T0}/{T0 + 120}/1",
                params={"format": "json"}).json()
    assert set(j) == {"version", "snapshotTime", "Links", "cumulativeIdleHours"}
    assert [p["datetime"] for p in j["cumulativeIdleHours"]] == ["2026-11-23T08:02:00.000Z"]
    empty = ctx.get(f"{base}/CumulativeIdleHours/{T0 - 9000}/{T0 - 10}/1",
                    params={"format": "json"}).json()
    assert empty["cumulativeIdleHours"] == []
    assert ctx.get(f"{base}/CumulativeIdleHours/{T0}/{T0 + 120}/2").status_code == 404
    assert ctx.get(f"{base}/FuelUsed/{T0}/{T0 + 120}/1").status_code == 422
    assert ctx.get(f"{base}/CumulativeIdleHours/{T0 + 9}/{T0}/1").status_code == 422


def test_hourly_points_offset_to_the_hour_meter() -> None:
    minutes = [(0.0, 60.0, 60.0, 0.0), (60.0, 120.0, 30.0, 30.0), (3600.0, 3660.0, 60.0, 0.0)]
    pts = aemp.hourly_points(minutes, "CumulativeOperatingHours", (3600.0, 0.0), 1000.0)
    assert pts == [{"datetime": "1970-01-01T00:02:00.000Z", "Hour": round(1001 + 90 / 3600, 3)},
                   {"datetime": "1970-01-01T01:01:00.000Z",
                    "Hour": round(1001 + 150 / 3600, 3)}]
