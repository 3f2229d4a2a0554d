"""HTTP API on a real store: auth per role on every route, each route's happy path, bad input.

Data: 4 minutes of exact kinematic samples (:func:`cranetwin.testing.blocks.kinematic_samples`:
a known motion, a payload of 400 kg in the second half of every minute, pressures from inverse
dynamics) written through the store's write path, then the twin worker's windows.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.testing.blocks import PAYLOAD_KG, kinematic_samples, payload_schedule, tiled_blocks

T0 = 1795420800.0  # 2026-11-23T08:00:00Z, a whole minute
SPAN = 240.0
MID = "crane-1"


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(load_machine("patu655"), 120.0)


@dataclass
class Ctx:
    client: TestClient
    services: Services
    keys: dict[str, str]

    def h(self, role: str) -> dict[str, str]:
        return {"X-API-Key": self.keys[role]}

    def get(self, path: str, role: str = "viewer", **params: Any) -> Any:
        return self.client.get(path, params=params, headers=self.h(role))


def _populate(url: str, base: SampleArrays) -> Iterator[Ctx]:
    app = create_app(Settings(database_url=url, worker_in_process=False))
    with TestClient(app) as client:
        services: Services = app.state.services
        keys = {r: services.backend.create_key(r, f"test {r}")[1]
                for r in ("viewer", "fleet", "admin")}
        ctx = Ctx(client, services, keys)
        r = client.post("/api/v1/machines", headers=ctx.h("admin"),
                        json={"machine_id": MID, "model": "patu655", "name": "Crane 1",
                              "location": {"lat": 62.24, "lon": 25.75}})
        assert r.status_code == 201, r.text
        machine = load_machine("patu655")
        services.backend.store.write_blocks(list(tiled_blocks(MID, machine, T0, SPAN, 1.0,
                                                              base=base)))
        worker = TwinWorker(services.backend, services.settings, services.metrics,
                            services.fleet.replayer)
        assert worker.catch_up(services.backend.machine(MID)) == 3  # 4th needs settle
        yield ctx


@pytest.fixture(scope="module")
def ctx(base: SampleArrays, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ctx]:
    """A populated SQLite database shared by the read-only tests of this module."""
    url = f"sqlite:///{tmp_path_factory.mktemp('api') / 'api.db'}"
    yield from _populate(url, base)


# --- auth: every route, every role ------------------------------------------------------------

R = f"from={T0}&to={T0 + 60}"
TS = f"CumulativeOperatingHours/{T0}/{T0 + 60}/1"
ROUTES: list[tuple[str, str, str, dict[str, Any] | None]] = [
    ("GET", "/metrics", "viewer", None),
    ("GET", "/api/v1/machines", "viewer", None),
    ("POST", "/api/v1/machines", "admin", {"machine_id": "x-auth", "model": "patu655"}),
    ("PATCH", f"/api/v1/machines/{MID}", "admin", {"name": "Crane 1"}),
    ("GET", f"/api/v1/machines/{MID}", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/model", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/samples?{R}&limit=10", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/twin?from={T0 + 60}&to={T0 + 62}&rate_hz=10", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/history?{R}&channels=lift_pA", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/events?{R}", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/find?{R}&channel=lift_pA&op=gt&value=0", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/analytics?{R}", "fleet", None),
    ("GET", f"/api/v1/machines/{MID}/report?{R}&format=csv", "fleet", None),
    ("GET", "/api/v1/aemp/Fleet/1", "fleet", None),
    ("GET", f"/api/v1/aemp/Equipment/{MID}", "fleet", None),
    ("GET", f"/api/v1/aemp/Fleet/Equipment/ID/{MID}", "fleet", None),
    ("GET", f"/api/v1/aemp/Fleet/Equipment/ID/{MID}/{TS}", "fleet", None),
    ("GET", f"/api/v1/machines/{MID}/export?{R}&series=raw", "fleet", None),
    ("GET", "/api/v1/fleet/figures", "viewer", None),
    ("GET", f"/api/v1/machines/{MID}/schedules", "viewer", None),
    ("PUT", f"/api/v1/machines/{MID}/schedules/{{item}}", "fleet",
     {"basis": "operating_hours", "interval": 500}),
    ("POST", f"/api/v1/machines/{MID}/schedules/{{item}}/done", "fleet", {}),
    ("DELETE", f"/api/v1/machines/{MID}/schedules/{{item}}", "fleet", None),
]
RANK = {"viewer": 0, "fleet": 1, "admin": 2}


def test_routes_table_covers_every_api_route(ctx: Ctx) -> None:
    documented = {(m.upper(), p) for p, item in ctx.client.app.openapi()["paths"].items()
                  for m in item
                  # sign-in needs no key (test_api_session.py covers it); alarms: test_api_alarms
                  if not p.endswith(("/scene", "/export.html", "/api/v1/session"))
                  and not p.startswith("/api/v1/alarms")}
    tested = {(m, p.split("?")[0].replace(MID, "{machine_id}").replace("Fleet/1", "Fleet/{page}")
               .replace(TS, "{element}/{start}/{end}/{page}")) for m, p, _, _ in ROUTES}
    assert documented - {("GET", "/healthz")} == tested


@pytest.mark.parametrize(("method", "path", "role", "body"), ROUTES,
                         ids=[f"{m} {p.split('?')[0]}" for m, p, _, _ in ROUTES])
def test_route_without_key_is_401_and_lower_roles_403(ctx: Ctx, method: str, path: str,
                                                       role: str, body: Any) -> None:
    r = ctx.client.request(method, path, json=body)
    assert r.status_code == 401
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["status"] == 401
    r = ctx.client.request(method, path, json=body, headers={"X-API-Key": "ctk_000000000000_x"})
    assert r.status_code == 401
    for other, rank in RANK.items():
        if rank < RANK[role]:
            r = ctx.client.request(method, path, json=body, headers=ctx.h(other))
            assert r.status_code == 403, (other, r.text)
            assert r.json()["title"] == "Insufficient role"


@pytest.mark.parametrize("how", ["header", "bearer", "query"])
def test_key_accepted_in_header_bearer_and_query(ctx: Ctx, how: str) -> None:
    key = ctx.keys["viewer"]
    if how == "header":
        r = ctx.client.get("/api/v1/machines", headers={"X-API-Key": key})
    elif how == "bearer":
        r = ctx.client.get("/api/v1/machines", headers={"Authorization": f"Bearer {key}"})
    else:
        r = ctx.client.get("/api/v1/machines", params={"key": key})
    assert r.status_code == 200


def test_key_with_wrong_secret_is_rejected(ctx: Ctx) -> None:
    key = ctx.keys["admin"]
    forged = key[:-4] + ("AAAA" if not key.endswith("AAAA") else "BBBB")
    assert ctx.client.get("/api/v1/machines", headers={"X-API-Key": forged}).status_code == 401


def test_keys_are_stored_hashed(ctx: Ctx) -> None:
    from sqlalchemy import text

    with ctx.services.backend.session() as s:
        stored = [tuple(r) for r in s.execute(text("SELECT key_id, secret_sha256 FROM api_keys"))]
    for token in ctx.keys.values():
        secret = token.split("_", 2)[2]
        assert all(secret not in h for _, h in stored)
    assert all(len(h) == 64 for _, h in stored)


def test_healthz_needs_no_key(ctx: Ctx) -> None:
    r = ctx.client.get("/healthz")
    assert r.status_code == 200 and r.json()["status"] == "ok"


# --- happy paths ---------------------------------------------------------------------------


def test_list_machines_reports_status_range_and_payload(ctx: Ctx) -> None:
    [m] = [x for x in ctx.get("/api/v1/machines").json() if x["machine_id"] == MID]
    assert m["status"] == "offline"  # samples are from the past
    assert m["location"] == {"lat": 62.24, "lon": 25.75}
    assert m["last_seen"].startswith("2026-11-23T08:03:59.99")
    one = ctx.get(f"/api/v1/machines/{MID}").json()
    assert one["data_range"]["from"] == "2026-11-23T08:00:00.000Z"


def test_model_is_the_machine_description(ctx: Ctx) -> None:
    from cranetwin.model import machine_from_dict

    data = ctx.get(f"/api/v1/machines/{MID}/model").json()
    assert machine_from_dict(data) == load_machine("patu655")


def test_samples_pages_reassemble_the_stored_samples(ctx: Ctx, base: SampleArrays) -> None:
    t: list[float] = []
    vals: list[list[float]] = []
    cursor = None
    pages = 0
    while True:
        params: dict[str, Any] = {"from": T0 + 1.0, "to": T0 + 4.0, "limit": 70}
        if cursor:
            params["cursor"] = cursor
        page = ctx.get(f"/api/v1/machines/{MID}/samples", **params).json()
        t += page["t"]
        vals += page["values"]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert pages == math.ceil(300 / 70)
    assert len(t) == 300 and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.array(t) - T0, base.t_s[100:400], atol=1e-6)
    np.testing.assert_allclose(np.array(vals, dtype=float), base.values[100:400], rtol=1e-9,
                               atol=1e-9)


def test_twin_recovers_the_known_payload_and_matches_the_kinematics(ctx: Ctx) -> None:
    from cranetwin.physics import body_poses

    r = ctx.get(f"/api/v1/machines/{MID}/twin", **{"from": T0 + 60, "to": T0 + 120,
                                                    "rate_hz": 50})
    assert r.status_code == 200
    j = r.json()
    t = np.array(j["t"])
    assert len(t) == 3000 and np.allclose(np.diff(t), 0.02, atol=1e-6)
    kg = np.array(j["payload"]["kg"], dtype=float)
    truth = payload_schedule(t - T0)
    steady = np.abs(np.mod(t - T0, 30.0) - 15.0) < 12.0  # away from the payload steps
    np.testing.assert_allclose(kg[steady], truth[steady], atol=0.02 * PAYLOAD_KG)
    machine = load_machine("patu655")
    q = np.array(j["q"])
    poses = body_poses(machine, q)
    tip_body = np.swapaxes(poses[:, -1], 1, 2).reshape(-1, 16)
    np.testing.assert_allclose(np.array(j["poses"]["extension_boom"]), tip_body, atol=1e-4)
    assert set(j["cylinder_forces"]) == {"lift", "jib", "extension"}
    util = np.array(j["utilisation"]["lift"])
    assert np.all((util >= 0) & (util <= 1))
    assert np.array(j["wrenches"]).shape == (3000, 4, 6)
    # every field of the observability verdict survives the response model
    obs = j["force_observability"]
    assert [o["cylinder"] for o in obs] == ["lift", "jib", "extension"]
    for o in obs:
        assert {"systematic_n", "systematic_share", "causes"} <= set(o), o
        assert o["observable"] == (o["causes"] == []), o


def test_twin_second_call_is_served_from_cache(ctx: Ctx) -> None:
    p = {"from": T0 + 10, "to": T0 + 20, "rate_hz": 25}
    first = ctx.get(f"/api/v1/machines/{MID}/twin", **p).content
    hits = ctx.services.fleet.twin_cache.hits
    assert ctx.get(f"/api/v1/machines/{MID}/twin", **p).content == first
    assert ctx.services.fleet.twin_cache.hits == hits + 1


def test_history_of_raw_channel_agrees_with_samples(ctx: Ctx, base: SampleArrays) -> None:
    j = ctx.get(f"/api/v1/machines/{MID}/history", **{"from": T0, "to": T0 + 120,
                                                       "channels": "lift_pA", "max_points": 4})
    s = j.json()["channels"]["lift_pA"]
    assert len(s["t"]) <= 4
    col = base.column("lift_pA")
    for i, b in enumerate(s["t"]):
        w = (base.t_s >= b - T0) & (base.t_s < b - T0 + (s["t"][1] - s["t"][0]))
        assert s["min"][i] == pytest.approx(col[w].min())
        assert s["max"][i] == pytest.approx(col[w].max())
        assert s["mean"][i] == pytest.approx(col[w].mean(), rel=1e-9)


def test_history_of_derived_payload_comes_from_the_worker(ctx: Ctx) -> None:
    j = ctx.get(f"/api/v1/machines/{MID}/history", **{"from": T0, "to": T0 + 180,
                                                       "channels": "payload,force:lift,working",
                                                       "max_points": 180}).json()["channels"]
    t = np.array(j["payload"]["t"])
    assert len(t) == 180  # 3 windows of 60 s were processed, 1-s buckets
    mean = np.array(j["payload"]["mean"], dtype=float)
    inside = np.abs(np.mod(t - T0 + 0.5, 30.0) - 15.0) < 12.0
    np.testing.assert_allclose(mean[inside], payload_schedule(t - T0 + 0.5)[inside],
                               atol=0.02 * PAYLOAD_KG)
    assert max(x for x in j["working"]["max"] if x is not None) == 1.0
    assert all(lo <= hi for lo, hi in zip(j["force:lift"]["min"], j["force:lift"]["max"],
                                          strict=True))


def test_find_first_and_last_exact_sample(ctx: Ctx, base: SampleArrays) -> None:
    col = base.column("lift_pA")
    thr = float(np.quantile(col, 0.9))
    first = ctx.get(f"/api/v1/machines/{MID}/find", **{"from": T0, "to": T0 + 120,
                                                        "channel": "lift_pA", "op": "gt",
                                                        "value": thr}).json()
    i = int(np.argmax(col > thr))
    assert first["t"] == pytest.approx(T0 + base.t_s[i], abs=1e-6)
    assert first["value"] == pytest.approx(col[i])
    last = ctx.get(f"/api/v1/machines/{MID}/find", **{"from": T0, "to": T0 + 120,
                                                       "channel": "lift_pA", "op": "lt",
                                                       "value": thr, "which": "last"}).json()
    k = int(np.flatnonzero(col < thr)[-1])
    assert last["t"] == pytest.approx(T0 + base.t_s[k], abs=1e-6)
    never = ctx.get(f"/api/v1/machines/{MID}/find", **{"from": T0, "to": T0 + 120,
                                                        "channel": "lift_pA", "op": "gt",
                                                        "value": 1e12}).json()
    assert never == {"t": None, "value": None}


def test_find_on_derived_payload_is_the_lift_start(ctx: Ctx) -> None:
    j = ctx.get(f"/api/v1/machines/{MID}/find", **{"from": T0, "to": T0 + 120,
                                                    "channel": "payload", "op": "gt",
                                                    "value": PAYLOAD_KG / 2}).json()
    assert j["t"] == pytest.approx(T0 + 30.0, abs=1.0)


def test_events_lists_stored_events(ctx: Ctx) -> None:
    from cranetwin.storage import Event

    ctx.services.backend.store.add_events([Event(MID, T0 + 5.0, "overload", "critical",
                                                 {"value": 1210.0, "limit": 900.0})])
    [e] = ctx.get(f"/api/v1/machines/{MID}/events", **{"from": T0, "to": T0 + 60}).json()
    assert e["kind"] == "overload" and e["t"] == pytest.approx(T0 + 5.0)
    assert e["evidence"]["limit"] == 900.0 and "overload" in e["message"]


def test_aemp_equipment_counts_lifts_and_hours(ctx: Ctx) -> None:
    j = ctx.get(f"/api/v1/aemp/Equipment/{MID}", role="fleet", format="json").json()
    assert j["EquipmentHeader"]["EquipmentID"] == MID
    assert j["CumulativeOperatingHours"]["Hour"] == pytest.approx(180 / 3600, abs=1e-3)
    assert j["CumulativeLoadCount"]["Count"] == 2  # lifts at 30–60 s and 90–120 s ended
    assert j["CumulativePayloadTotals"]["Payload"] == pytest.approx(0.8, abs=0.02)
    for el in ("Location", "CumulativeOperatingHours", "CumulativeIdleHours",
               "CumulativeLoadCount", "CumulativePayloadTotals"):
        assert j[el]["datetime"].endswith("Z")
    assert j["Extension"]["cranetwin"]["RatedLoad_kg"] > 0


def test_aemp_fleet_pages_and_links(ctx: Ctx) -> None:
    j = ctx.get("/api/v1/aemp/Fleet/1", role="fleet", format="json").json()
    rels = {link["rel"]: link["href"] for link in j["Links"]}
    assert rels["self"].endswith("/Fleet/1") and rels["last"].endswith("/Fleet/1")
    assert "next" not in rels and "prev" not in rels
    assert MID in [e["EquipmentHeader"]["EquipmentID"] for e in j["Equipment"]]
    assert ctx.get("/api/v1/aemp/Fleet/2", role="fleet").status_code == 404


def test_metrics_expose_request_counts(ctx: Ctx) -> None:
    ctx.get("/api/v1/machines")
    text = ctx.get("/metrics").text
    assert 'cranetwin_http_requests_total{method="GET",route="/api/v1/machines",status="200"}' \
        in text


def test_live_websocket_sends_hello_then_frames_of_new_samples(ctx: Ctx,
                                                              base: SampleArrays) -> None:
    machine = load_machine("patu655")
    with ctx.client.websocket_connect(f"/api/v1/machines/{MID}/live?key={ctx.keys['viewer']}") \
            as ws:
        hello = ws.receive_json()
        assert hello == {"type": "hello", "machine_id": MID, "model": "patu655",
                         "rate_hz": ctx.services.settings.live_rate_hz}
        blocks = list(tiled_blocks(MID, machine, T0 + SPAN, 1.0, 1.0, base=base, seq0=90_000))
        ctx.services.backend.store.write_blocks(blocks)
        frame = ws.receive_json()
    assert frame["t"] == pytest.approx(T0 + SPAN + 0.99, abs=1e-6)
    assert len(frame["q"]) == 4 and len(frame["poses"]["extension_boom"]) == 16
    assert set(frame["cylinder_forces"]) == {"lift", "jib", "extension"}
    assert "lift_pA" in frame["pressures"]


@pytest.mark.parametrize(("key", "code"), [(None, 4401), ("bad", 4401)])
def test_live_websocket_rejects_bad_keys(ctx: Ctx, key: str | None, code: int) -> None:
    url = f"/api/v1/machines/{MID}/live" + (f"?key={key}" if key else "")
    with ctx.client.websocket_connect(url) as ws:
        msg = ws.receive_json()
        assert msg["type"] == "error" and msg["status"] == 401
        closed = ws.receive()
    assert closed["code"] == code


def test_live_websocket_unknown_machine(ctx: Ctx) -> None:
    with ctx.client.websocket_connect(f"/api/v1/machines/nope/live?key={ctx.keys['viewer']}") \
            as ws:
        assert ws.receive_json()["status"] == 404


# --- bad input → 4xx problem JSON ----------------------------------------------------------

BAD = [
    (f"/api/v1/machines/nope/samples?{R}", 404),
    (f"/api/v1/machines/{MID}/samples?from={T0 + 10}&to={T0}", 422),
    (f"/api/v1/machines/{MID}/samples?from=yesterday&to={T0}", 422),
    (f"/api/v1/machines/{MID}/samples?from=nan&to={T0}", 422),
    (f"/api/v1/machines/{MID}/samples?to={T0}", 422),
    (f"/api/v1/machines/{MID}/samples?{R}&limit=0", 422),
    (f"/api/v1/machines/{MID}/samples?{R}&limit=99999", 422),
    (f"/api/v1/machines/{MID}/samples?{R}&cursor=zzz", 422),
    (f"/api/v1/machines/{MID}/twin?from={T0}&to={T0 + 3600}", 422),
    (f"/api/v1/machines/{MID}/twin?{R}&rate_hz=-1", 422),
    (f"/api/v1/machines/{MID}/twin?{R}&rate_hz=1000", 422),
    (f"/api/v1/machines/{MID}/history?{R}&channels=nope", 422),
    (f"/api/v1/machines/{MID}/history?{R}&channels=", 422),
    (f"/api/v1/machines/{MID}/history?{R}&channels=lift_pA&max_points=99999", 422),
    (f"/api/v1/machines/{MID}/history?from=0&to=1e11&channels=lift_pA", 422),
    (f"/api/v1/machines/{MID}/find?{R}&channel=lift_pA&op=eq&value=1", 422),
    (f"/api/v1/machines/{MID}/find?{R}&channel=lift_pA&op=gt&value=inf", 422),
    ("/api/v1/aemp/Fleet/0", 422),
    ("/api/v1/aemp/Equipment/nope", 404),
    ("/api/v1/nothing-here", 404),
]


@pytest.mark.parametrize(("path", "status"), BAD, ids=[p for p, _ in BAD])
def test_bad_input_is_4xx_problem_json(ctx: Ctx, path: str, status: int) -> None:
    r = ctx.client.get(path, headers=ctx.h("admin"))
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]


def test_malformed_json_body_is_400(ctx: Ctx) -> None:
    r = ctx.client.post("/api/v1/machines", content=b"{not json", headers={
        **ctx.h("admin"), "content-type": "application/json"})
    assert r.status_code == 400 and r.json()["title"] == "Malformed JSON"


@pytest.mark.parametrize(("body", "status"), [
    ({"machine_id": MID, "model": "patu655"}, 409),
    ({"machine_id": "new-1", "model": "no-such-crane"}, 422),
    ({"machine_id": "bad id!", "model": "patu655"}, 422),
    ({"machine_id": "new-2", "model": "patu655", "extra": 1}, 422),
    ([1, 2], 422),
])
def test_create_machine_rejects_bad_bodies(ctx: Ctx, body: Any, status: int) -> None:
    r = ctx.client.post("/api/v1/machines", json=body, headers=ctx.h("admin"))
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")


def test_patch_machine_changes_name_and_location(ctx: Ctx) -> None:
    r = ctx.client.patch(f"/api/v1/machines/{MID}", headers=ctx.h("admin"),
                         json={"name": "Crane One", "location": {"lat": 60.0, "lon": 24.9}})
    assert r.status_code == 200 and r.json()["name"] == "Crane One"
    assert ctx.get(f"/api/v1/machines/{MID}").json()["location"] == {"lat": 60.0, "lon": 24.9}
    r = ctx.client.patch(f"/api/v1/machines/{MID}", headers=ctx.h("admin"),
                         json={"location": {"lat": 91.0, "lon": 0}})
    assert r.status_code == 422


def test_analytics_of_a_range_counts_work_and_spectra(ctx: Ctx) -> None:
    r = ctx.get(f"/api/v1/machines/{MID}/analytics", role="fleet", **{"from": T0,
                                                                       "to": T0 + 120})
    assert r.status_code == 200, r.text
    j = r.json()
    assert j["n_samples"] == 12000
    assert j["productivity"]["recorded_s"] == pytest.approx(120.0, abs=1.0)
    assert {s["channel"] for s in j["spectra"]} >= {"cylinder:lift:force"}
    empty = ctx.get(f"/api/v1/machines/{MID}/analytics", role="fleet",
                    **{"from": T0 - 600, "to": T0 - 300}).json()
    assert empty["n_samples"] == 0


@pytest.mark.parametrize(("fmt", "media", "magic"), [("csv", "application/zip", b"PK"),
                                                      ("html", "text/html", b"<!"),
                                                      ("pdf", "application/pdf", b"%PDF")])
def test_report_downloads(ctx: Ctx, fmt: str, media: str, magic: bytes) -> None:
    r = ctx.get(f"/api/v1/machines/{MID}/report", role="fleet",
                **{"from": T0, "to": T0 + 60, "format": fmt})
    assert r.status_code == 200
    assert r.headers["content-type"].startswith(media)
    assert r.content.lstrip().startswith(magic)
    assert "attachment" in r.headers["content-disposition"]


def test_report_of_an_empty_range_is_a_stub(ctx: Ctx) -> None:
    r = ctx.get(f"/api/v1/machines/{MID}/report", role="fleet",
                **{"from": T0 - 600, "to": T0 - 300, "format": "csv"})
    assert r.status_code == 200 and r.content.startswith(b"quantity,value")


def test_live_frames_follow_bus_notes(base: SampleArrays, tmp_path) -> None:
    from cranetwin.storage.live import InProcessBus

    bus = InProcessBus()
    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'bus.db'}",
                              worker_in_process=False), bus=bus)
    machine = load_machine("patu655")
    with TestClient(app) as client:
        services: Services = app.state.services
        _, key = services.backend.create_key("viewer")
        services.backend.store.add_machine(MID, wire_id=3, secret=b"k" * 32)
        with client.websocket_connect(f"/api/v1/machines/{MID}/live?key={key}") as ws:
            assert ws.receive_json()["type"] == "hello"
            for k in range(3):
                blocks = list(tiled_blocks(MID, machine, T0 + k, 1.0, 1.0, base=base, seq0=k))
                services.backend.store.write_blocks(blocks)
                bus.publish(blocks)
                frame = ws.receive_json()
                assert frame["t"] == pytest.approx(T0 + k + 0.99, abs=1e-6)
