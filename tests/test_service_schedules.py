"""Service schedules (SQLite and PostgreSQL): items due by operating hours, lifts, damage
fraction or calendar days, counted from the twin worker's stored analytics (no replay); what is
due when over the API, one ``service_due`` event per due item (raised by the worker, kept with the
alarms, cleared by marking the item done), fleet role for writes."""

from __future__ import annotations

import csv
import io
import zipfile
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service import schedules as sv
from cranetwin.service.analytics import direct_report
from cranetwin.service.replayer import Replayer
from cranetwin.service.timerange import TimeRange
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage.schedules import Schedule
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0
MID = "crane-s"
MACHINE = load_machine("patu655")
NOW = T0 + 86400.0 * 3  # the planner's clock: three days after the data


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


@pytest.fixture()
def ctx(db_url: str, base: SampleArrays) -> Iterator[tuple[TestClient, dict[str, Any], Any]]:
    settings = Settings(database_url=db_url, worker_in_process=False, alarm_check_interval_s=0,
                        warm_up=False)
    app = create_app(settings)
    with TestClient(app) as client:
        services = app.state.services
        b = services.backend
        keys = {r: {"X-API-Key": b.create_key(r, f"{r} user")[1]}
                for r in ("viewer", "fleet", "admin")}
        assert client.post("/api/v1/machines", headers=keys["admin"],
                           json={"machine_id": MID, "model": "patu655"}).status_code == 201
        b.store.write_blocks(list(tiled_blocks(MID, MACHINE, T0, 245.0, 1.0, base=base,
                                               origin_s=T0)))
        worker = TwinWorker(b, settings, replayer=Replayer())
        assert worker.catch_up(b.machine(MID)) == 4
        yield client, keys, services


def _sched(basis: str, interval: float, done: float, detail: str | None = None) -> Schedule:
    return Schedule(1, MID, "x", basis, interval, detail, done, T0, None, T0, "me")


@pytest.mark.timeout(30)
def test_due_status_ok_due_overdue_and_estimated_date() -> None:
    u = sv.Usage(T0 + 100.0, NOW, {"operating_hours": 90.0, "calendar_days": NOW / 86400,
                                   "damage_fraction:a": 0.02, "damage_fraction:b": 0.05},
                 {"operating_hours": 8.0, "calendar_days": 1.0, "damage_fraction:a": 0.001,
                  "damage_fraction:b": 0.002})
    ok = sv.due_status(_sched("operating_hours", 100.0, 0.0), u, 0.05)
    assert ok.status == "ok" and ok.remaining == pytest.approx(10.0)
    assert ok.due_at_s == pytest.approx(T0 + 100.0 + 10.0 / 8.0 * 86400)  # from the counters'
    assert sv.due_status(_sched("operating_hours", 100.0, 0.0), u).status == "due"  # ≤ 10 %
    over = sv.due_status(_sched("operating_hours", 50.0, 20.0), u)
    assert over.status == "overdue" and over.remaining == pytest.approx(-20.0)
    # damage: the named detail, else the most damaged one (named in the status)
    assert sv.due_status(_sched("damage_fraction", 0.1, 0.0, "a"), u).detail == "a"
    worst = sv.due_status(_sched("damage_fraction", 0.1, 0.0), u)
    assert worst.detail == "b" and worst.due_at_s == pytest.approx(
        T0 + 100.0 + 0.05 / 0.002 * 86400)
    # calendar: exactly the last date + the interval
    cal = sv.due_status(_sched("calendar_days", 30.0, T0 / 86400), u)
    assert cal.due_at_s == pytest.approx(T0 + 30 * 86400) and cal.status == "ok"
    assert cal.remaining == pytest.approx(27.0)
    assert sv.due_status(_sched("lifts", 10.0, 0.0), u).status == "unknown"  # no counter
    # a due date extrapolated past the year 9999 has no calendar date: null, not an error
    slow = sv.due_status(_sched("operating_hours", 1e9, 0.0), u)
    assert slow.due_at_s is not None and slow.due_at_s > 253402300800.0
    assert sv.status_json(slow)["due_at"]["at"] is None


@pytest.mark.timeout(300)
def test_counters_are_the_stored_analytics(ctx: Any) -> None:
    client, keys, services = ctx
    b = services.backend
    prog = b.progress(MID)
    assert prog is not None and prog.watermark_s == T0 + 240.0
    u = sv.usage_of(b, MID, now_s=NOW)
    assert u.until_s == prog.watermark_s
    assert u.values["operating_hours"] == pytest.approx(240.0 / 3600, rel=1e-9)
    # the report of the processed range, replayed minute by minute: same lifts and damage
    rep = direct_report(b, Replayer(), MACHINE, MID, TimeRange(T0, T0 + 240.0),
                        services.settings.twin_margin_s)
    assert rep is not None and len(rep.cycles) > 0
    assert u.values["lifts"] == len(rep.cycles)
    for life in rep.life:
        assert u.values[f"damage_fraction:{life.name}"] == pytest.approx(life.damage, rel=1e-9)
    # 4 minutes of data in the last 7 days (the whole span counts: 4 min over 4 min of days)
    span_d = 240.0 / 86400
    assert u.rates_per_day["operating_hours"] == pytest.approx(240.0 / 3600 / span_d)
    assert u.rates_per_day["lifts"] == pytest.approx(len(rep.cycles) / span_d)


@pytest.mark.timeout(300)
def test_api_worker_event_once_and_done(ctx: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    client, keys, services = ctx
    b = services.backend
    monkeypatch.setattr(sv.time, "time", lambda: NOW)
    url = f"/api/v1/machines/{MID}/schedules"
    items = {"oil filter": {"basis": "operating_hours", "interval": 0.05, "last_done_value": 0},
             "greasing": {"basis": "lifts", "interval": 1000},
             "boom inspection": {"basis": "damage_fraction", "interval": 0.5,
                                 "detail": MACHINE.fatigue[0].name, "last_done_value": 0},
             "annual": {"basis": "calendar_days", "interval": 365,
                        "last_done_at": "2025-12-01T00:00:00Z"}}
    # viewers may look, not set
    assert client.put(f"{url}/oil%20filter", headers=keys["viewer"],
                      json=items["oil filter"]).status_code == 403
    for name, body in items.items():
        r = client.put(f"{url}/{name}", headers=keys["fleet"], json=body)
        assert r.status_code == 200, r.text
    assert client.put(f"{url}/x", headers=keys["fleet"],
                      json={"basis": "damage_fraction", "interval": 0.1,
                            "detail": "no such detail"}).status_code == 422
    assert client.put(f"{url}/x", headers=keys["fleet"],
                      json={"basis": "fuel", "interval": 1}).status_code == 422
    # an interval past any calendar (it answered 500: a due date in the year 10000)
    assert client.put(f"{url}/x", headers=keys["fleet"],
                      json={"basis": "calendar_days", "interval": 2912108.0}).status_code == 422
    assert client.put(f"{url}/x", headers=keys["fleet"],
                      json={"basis": "damage_fraction", "interval": 1.5}).status_code == 422
    assert client.get("/api/v1/machines/nope/schedules", headers=keys["viewer"]).status_code \
        == 404
    got = client.get(url, headers=keys["viewer"]).json()
    st = {i["item"]: i for i in got["items"]}
    assert set(st) == set(items)
    assert st["oil filter"]["status"] == "overdue"  # 0.0667 h run, due at 0.05 h
    assert st["oil filter"]["current"] == pytest.approx(240.0 / 3600)
    assert st["greasing"]["status"] == "ok"  # counted from the lifts when it was set
    assert st["greasing"]["last_done"]["value"] == st["greasing"]["current"]
    assert st["greasing"]["created"]["by"] == "fleet user (fleet)"
    assert st["boom inspection"]["detail"] == MACHINE.fatigue[0].name
    assert st["annual"]["status"] == "due"  # 2025-12-01 + 365 d, within 10 % of NOW
    assert st["annual"]["due_at"]["at"].startswith("2026-12-01")
    # the twin worker's pass raises one event per due item, once
    worker = TwinWorker(b, services.settings, replayer=Replayer(), schedule_check_s=0.0)
    assert worker.catch_up(b.machine(MID)) == 0  # no new window: the check runs all the same
    assert worker.catch_up(b.machine(MID)) == 0
    assert sv.check_due(b, MID, now_s=NOW) == 0
    alarms = client.get("/api/v1/alarms", headers=keys["viewer"],
                        params={"kind": "service_due"}).json()
    assert alarms["total"] == 2
    by_item = {a["evidence"]["item"]: a for a in alarms["items"]}
    assert set(by_item) == {"oil filter", "annual"}
    assert by_item["oil filter"]["severity"] == "critical"
    assert "oil filter" in by_item["oil filter"]["message"]
    # marking done clears its alarm and re-arms the item
    r = client.post(f"{url}/oil%20filter/done", headers=keys["fleet"], json={})
    assert r.status_code == 200, r.text
    assert r.json()["status"] == "ok" and r.json()["last_done"]["by"] == "fleet user (fleet)"
    active = client.get("/api/v1/alarms", headers=keys["viewer"],
                        params={"kind": "service_due"}).json()
    assert [a["evidence"]["item"] for a in active["items"]] == ["annual"]
    assert sv.check_due(b, MID, now_s=NOW) == 0
    # done long ago: due again, a second event
    assert client.post(f"{url}/oil%20filter/done", headers=keys["fleet"],
                       json={"value": 0.0}).status_code == 200
    assert sv.check_due(b, MID, now_s=NOW) == 1
    assert client.post(f"{url}/nope/done", headers=keys["fleet"]).status_code == 404
    # the report has a Service schedule section (CSV: schedule.csv; HTML: the section)
    rng = {"from": T0, "to": T0 + 240}
    r = client.get(f"/api/v1/machines/{MID}/report", headers=keys["fleet"],
                   params={**rng, "format": "csv"})
    assert r.status_code == 200, r.text
    with zipfile.ZipFile(io.BytesIO(r.content)) as z:
        rows = list(csv.DictReader(io.StringIO(z.read("schedule.csv").decode())))
    got_rows = {row["item"]: row for row in rows}
    assert set(got_rows) == set(items)
    assert got_rows["oil filter"]["status"] == "overdue"
    assert got_rows["annual"]["due (UTC, estimated)"].startswith("2026-12-01")
    page = client.get(f"/api/v1/machines/{MID}/report", headers=keys["fleet"],
                      params={**rng, "format": "html"}).text
    assert "<h1>Service schedule</h1>" in page and "boom inspection" in page
    # the machine page's table of the items (filled by schedule.js from the list above)
    html = client.get(f"/machines/{MID}").text
    assert 'id="schedule-rows"' in html
    js = client.get("/static/js/schedule.js")
    assert js.status_code == 200 and "/schedules`" in js.text
    assert client.delete(f"{url}/greasing", headers=keys["fleet"]).status_code == 204
    assert client.delete(f"{url}/greasing", headers=keys["fleet"]).status_code == 404
