"""Alarms over the API (SQLite and PostgreSQL): every machine's events with filters and paging,
acknowledged and cleared by the signed-in key's user with times kept in the database (migration
0003), role fleet for actions; machine_offline and data_gap events after configurable timeouts."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.settings import Settings
from cranetwin.storage import Event

T0 = 1_790_000_000.0


@pytest.fixture()
def ctx(db_url: str) -> Iterator[tuple[TestClient, dict[str, dict[str, str]], Any]]:
    app = create_app(Settings(database_url=db_url, worker_in_process=False,
                              alarm_check_interval_s=0, alarm_offline_s=60, alarm_gap_s=5))
    with TestClient(app) as client:
        services = app.state.services
        keys = {r: {"X-API-Key": services.backend.create_key(r, f"{r} user")[1]}
                for r in ("viewer", "fleet", "admin")}
        for mid in ("crane-1", "crane-2"):
            assert client.post("/api/v1/machines", headers=keys["admin"],
                               json={"machine_id": mid, "model": "patu655"}).status_code == 201
        evs = [Event("crane-1", T0 + i, "overload" if i % 2 else "over_pressure",
                     "critical" if i % 3 == 0 else "warning",
                     {"value": 2.84e4, "limit": 2e4, "unit": "N*m", "component": "load"})
               for i in range(12)]
        evs.append(Event("crane-2", T0 + 100, "shock_load", "warning", {}))
        services.backend.store.add_events(evs)
        yield client, keys, services


@pytest.mark.timeout(60)
def test_filters_and_paging(ctx: Any) -> None:
    client, keys, _ = ctx
    v = keys["viewer"]
    r = client.get("/api/v1/alarms", headers=v)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["total"] == 13 and len(body["items"]) == 13
    ts = [a["t"] for a in body["items"]]
    assert ts == sorted(ts, reverse=True)  # newest first
    assert {"overload", "over_pressure", "shock_load"} <= set(body["kinds"])
    first = body["items"][1]
    assert first["message"] == "overload on load: 28.4 kN·m (limit 20 kN·m, 142 % of it)"
    assert first["acknowledged"] is None and first["cleared"] is None
    q = lambda **p: client.get("/api/v1/alarms", headers=v, params=p).json()  # noqa: E731
    assert q(machine="crane-2")["total"] == 1
    assert q(machine="crane-1,crane-2")["total"] == 13
    assert q(severity="critical")["total"] == 4  # i = 0, 3, 6, 9
    assert q(kind="overload", machine="crane-1")["total"] == 6
    assert q(**{"from": T0 + 5, "to": T0 + 8})["total"] == 3
    page1, page2 = q(limit=5, offset=0), q(limit=5, offset=5)
    assert page1["total"] == 13 and len(page1["items"]) == 5 and len(page2["items"]) == 5
    assert not {a["id"] for a in page1["items"]} & {a["id"] for a in page2["items"]}
    assert q(limit=5, offset=10)["items"][-1]["t"] == T0
    assert client.get("/api/v1/alarms", headers=v, params={"limit": 0}).status_code == 422
    assert client.get("/api/v1/alarms", headers=v,
                      params={"from": "yesterday"}).status_code == 422
    assert client.get("/api/v1/alarms").status_code == 401


@pytest.mark.timeout(60)
def test_acknowledge_and_clear_with_user_and_time_kept(ctx: Any, db_url: str) -> None:
    client, keys, services = ctx
    items = client.get("/api/v1/alarms", headers=keys["viewer"]).json()["items"]
    a, b = items[0]["id"], items[1]["id"]
    # viewers look, fleet keys act
    assert client.post(f"/api/v1/alarms/{a}/acknowledge", headers=keys["viewer"]).status_code \
        == 403
    r = client.post(f"/api/v1/alarms/{a}/acknowledge", headers=keys["fleet"])
    assert r.status_code == 200, r.text
    ack = r.json()["acknowledged"]
    assert ack["by"] == "fleet user (fleet)" and ack["at"].endswith("Z")
    assert r.json()["cleared"] is None
    # a second acknowledgement keeps the first
    again = client.post(f"/api/v1/alarms/{a}/acknowledge", headers=keys["admin"]).json()
    assert again["acknowledged"] == ack
    r = client.post(f"/api/v1/alarms/{b}/clear", headers=keys["admin"])
    assert r.json()["cleared"]["by"] == "admin user (admin)"
    assert r.json()["acknowledged"]["by"] == "admin user (admin)"  # clearing acknowledges
    q = lambda s: {x["id"] for x in client.get(  # noqa: E731
        "/api/v1/alarms", headers=keys["viewer"], params={"state": s}).json()["items"]}
    assert b not in q("active") and a in q("active")
    assert a not in q("unacknowledged") and b not in q("unacknowledged")
    assert q("acknowledged") == {a} and q("cleared") == {b} and len(q("all")) == 13
    assert client.post("/api/v1/alarms/999999/clear", headers=keys["fleet"]).status_code == 404
    # kept in the database: a new app on the same database sees the same state
    app2 = create_app(Settings(database_url=db_url, worker_in_process=False,
                               alarm_check_interval_s=0))
    with TestClient(app2) as c2:
        rows = c2.get("/api/v1/alarms", headers=keys["viewer"],
                      params={"state": "all", "limit": 2}).json()["items"]
        assert rows[0]["acknowledged"] == ack and rows[1]["cleared"]["by"] == "admin user (admin)"


@pytest.mark.timeout(60)
def test_offline_and_data_gap_events_after_their_timeouts(ctx: Any) -> None:
    from cranetwin.model import load_machine
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    client, keys, services = ctx
    machine = load_machine("patu655")
    base = kinematic_samples(machine, 20.0)
    store = services.backend.store
    alarms = services.alarms
    store.write_blocks(list(tiled_blocks("crane-2", machine, T0, 10.0, 1.0, base=base)))
    last = services.backend.data_range("crane-2")[1]
    assert alarms.check_connectivity(now_s=last + 30) == 0  # silent 30 s < 60 s: online
    assert alarms.check_connectivity(now_s=last + 61) == 1  # offline
    assert alarms.check_connectivity(now_s=last + 90) == 0  # reported once
    # the stream resumes 100 s later: a data gap, and the offline alarm is cleared
    store.write_blocks(list(tiled_blocks("crane-2", machine, T0 + 110, 5.0, 1.0, base=base,
                                         seq0=1000)))
    assert alarms.check_connectivity(now_s=T0 + 116) == 1
    got = client.get("/api/v1/alarms", headers=keys["viewer"],
                     params={"kind": "machine_offline,data_gap", "state": "all"}).json()
    by_kind = {a["kind"]: a for a in got["items"]}
    off, gap = by_kind["machine_offline"], by_kind["data_gap"]
    assert off["t"] == pytest.approx(last + 60) and off["severity"] == "warning"
    assert "no samples since" in off["message"] and "timeout 60 s" in off["message"]
    assert off["cleared"]["by"] == "cranetwin (data resumed)"
    assert gap["t"] == pytest.approx(last)
    assert gap["evidence"]["gap_s"] == pytest.approx(T0 + 110 - last, abs=1.0)
    assert "data gap" in gap["message"]
    # times and durations for people: UTC to the second, "100 s", never 1.7e9 or ISO millis
    from cranetwin.service.events import format_time

    assert f"since {format_time(last)} (timeout 60 s)" in off["message"]
    assert gap["message"] == (f"data gap: no samples for 100 s (from {format_time(last)} to "
                              f"{format_time(T0 + 110)}; reported above 5 s)")
    # a short pause (< alarm_gap_s = 5 s) is no gap
    store.write_blocks(list(tiled_blocks("crane-2", machine, T0 + 118, 2.0, 1.0, base=base,
                                         seq0=2000)))
    assert alarms.check_connectivity(now_s=T0 + 121) == 0


@pytest.mark.timeout(60)
def test_fleet_figures(ctx: Any) -> None:
    import time

    from cranetwin.service.backend import Progress

    client, keys, services = ctx
    from dataclasses import replace

    p = replace(Progress.empty("crane-1"), operating_s=7200.0, load_count=12,
                payload_total_kg=4500.0)
    assert services.backend.save_progress(p, None)
    now = time.time()
    services.backend.store.add_events([Event("crane-2", now - 10, "overload", "critical", {}),
                                       Event("crane-2", now - 5, "data_gap", "info", {})])
    r = client.get("/api/v1/fleet/figures", headers=keys["viewer"])
    assert r.status_code == 200, r.text
    f = r.json()
    assert f["machines"]["crane-1"] == {"operating_h": 2.0, "lifts": 12.0, "tonnes": 4.5}
    assert f["machines"]["crane-2"]["lifts"] == 0
    assert f["total"]["tonnes"] == 4.5
    assert f["total"]["alarms_today"] == 1 and f["total"]["critical_today"] == 1
